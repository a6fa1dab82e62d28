"""Clips of query segments for a person, drawn from the physics positions the buffer stored.

- The MJX tasks: MuJoCo's own renderer (``mujoco.Renderer``) with dm_control's ``side``
  camera (it tracks the centre of mass; the quadruped's side view is its camera ``y``, the one
  DrQ-v2 renders the quadruped with), on a copy of the task's model with dm_control's
  visual assets added back (skybox, checker floor, light), which the physics model leaves out.
  Only visual elements are added, so the positions mean the same. MuJoCo needs an OpenGL
  context: ``MUJOCO_GL=egl`` (a GPU, or Mesa's software EGL) or ``MUJOCO_GL=osmesa``.
- Meta-World's tasks (``metaworld_*``): MuJoCo's renderer on Meta-World's own model (its scene, table and
  lights) through its camera ``corner4`` (:data:`METAWORLD_CAMERA`), turned right side up. Meta-World's reset moves
  bodies and the goal site of the model, and the hand follows a mocap body, so each frame is drawn from the step's
  ``qpos`` and its *scene* (the mocap's position, the moved body's and the goal site's, which the buffer stores per
  step for these tasks: ``rebel_jax.envs.metaworld.frame_scene``).
- ``probe_point``: it has no MuJoCo model; a clip is a 2-D plot of the point (NumPy), its
  trail and the goal at the centre, shaded by the reward.

A clip goes to the page as one image, a *sheet* of its frames in rows of ``COLUMNS``, which the
page draws frame by frame on a canvas: both clips of a query run off one clock, so they stay in step.
"""

from __future__ import annotations

import io
import os
from typing import Protocol

import numpy as np
from PIL import Image

COLUMNS = 10
"""Frames per row of a clip's sheet."""

INSTRUCTIONS = {
    "probe_point": "Which dot gets closer to the target in the centre, and stays there?",
    "walker_stand": "Which walker stands up taller and more upright?",
    "walker_walk": "Which walker walks forward (to the right) better, while staying upright?",
    "walker_run": "Which walker runs forward (to the right) faster, while staying upright?",
    "cheetah_run": "Which cheetah runs forward (to the right) faster?",
    "quadruped_walk": "Which quadruped walks forward (the way its head points) better, while staying upright?",
    "quadruped_run": "Which quadruped runs forward (the way its head points) faster, while staying upright?",
    "metaworld_drawer-open": "Which arm pulls the drawer further open (by its handle, towards the green dot)?",
    "metaworld_sweep-into": "Which arm sweeps the small block closer to the hole (the blue dot), or into it?",
    "metaworld_door-open": "Which arm swings the door further open (by its handle, towards the green dot)?",
    "metaworld_button-press": "Which arm pushes the button further in?",
    "metaworld_window-open": "Which arm slides the window further open (by its handle, towards the green dot)?",
    "metaworld_door-unlock": "Which arm turns the door's lock further open?",
    "metaworld_hammer": "Which arm drives the nail further into the box with the hammer?",
}
"""The question the page asks for each task."""

CAMERAS = {"quadruped_walk": "y", "quadruped_run": "y"}
"""The camera of each MJX task's clips where it is not ``side``: the quadruped's side view, ``y`` (camera 2,
DrQ-v2's quadruped camera), which tracks the centre of mass from 4 m away."""


METAWORLD_CAMERA = "corner4"
"""The camera of Meta-World's clips: ``corner4`` of its scene (``metaworld_assets/objects/assets/xyz_base.xml``,
one of the cameras Meta-World's documentation lists, metaworld@3.1.1:docs/rendering/rendering.md:29), close enough
that the arm, the object and the goal of every task fill the picture (``corner`` shows the door's back, ``corner2``
and ``corner3`` the whole table from further away)."""


class ClipError(RuntimeError):
    """Clips cannot be rendered here (no OpenGL context, most often)."""


class Renderer(Protocol):
    fps: float

    def frames(self, positions: np.ndarray) -> np.ndarray:
        """(H, nq) positions -> (H, S, S, 3) uint8 frames (a Meta-World task's renderer also takes the (H, k)
        scenes, :meth:`MetaWorldRenderer.frames`)."""
        ...


def sheet(frames: np.ndarray, image_format: str = "JPEG") -> bytes:
    """One image of ``frames`` (H, S, S, 3), row-major in rows of ``COLUMNS`` frames."""
    count, height, width, _ = frames.shape
    columns = min(COLUMNS, count)
    rows = -(-count // columns)
    canvas = np.zeros((rows * height, columns * width, 3), np.uint8)
    for i, frame in enumerate(frames):
        r, c = divmod(i, columns)
        canvas[r * height : (r + 1) * height, c * width : (c + 1) * width] = frame
    out = io.BytesIO()
    options = {"quality": 90} if image_format == "JPEG" else {}
    Image.fromarray(canvas).save(out, format=image_format, **options)
    return out.getvalue()


class ProbeRenderer:
    """``probe_point``'s clip: the point, its trail so far and the goal; the box [-BOUND, BOUND]^2 and a margin."""

    image_format = "PNG"

    def __init__(self, size: int = 256, dt: float = 0.1):
        from rebel_jax.envs import probe

        self.size, self.fps = size, 1.0 / dt
        self.bound = 1.1 * probe.BOUND  # A margin: the point often rests on the box's wall.
        coords = (np.arange(size) + 0.5) / size * 2 * self.bound - self.bound
        x, y = np.meshgrid(coords, -coords)  # y grows upwards
        shade = np.asarray(probe.reward_of(np.stack([x, y], -1)))  # 1 at the goal
        base = np.array([250, 250, 245], np.float32)
        goal = np.array([150, 215, 150], np.float32)
        self.background = (base + shade[..., None] * (goal - base)).astype(np.uint8)
        pixel = 2 * self.bound / size
        axis = (np.abs(x) < pixel) | (np.abs(y) < pixel)
        self.background[axis] = (200, 200, 200)
        self.x, self.y = x, y

    def _disc(self, image: np.ndarray, pos: np.ndarray, radius_px: float, colour) -> None:
        radius = radius_px * 2 * self.bound / self.size
        image[(self.x - pos[0]) ** 2 + (self.y - pos[1]) ** 2 <= radius**2] = colour

    def frames(self, positions: np.ndarray) -> np.ndarray:
        positions = np.asarray(positions, np.float32)
        out = np.empty((len(positions), self.size, self.size, 3), np.uint8)
        for t, pos in enumerate(positions):
            image = self.background.copy()
            for past in positions[:t]:
                self._disc(image, past, 2.5, (150, 170, 220))
            self._disc(image, pos, 9, (30, 70, 200))
            out[t] = image
        return out


def render_xml(task: str) -> str:
    """The task's MJCF for MuJoCo's renderer. ``envs/models.py`` writes dm_control's visual assets
    (``common/skybox.xml``, ``visual.xml``, ``materials.xml``) and the torso's tracking light into
    the physics model itself, so the clips render the physics model as it is."""
    from rebel_jax.envs.dmc import TASKS

    return TASKS[task].xml()


class MujocoRenderer:
    """An MJX task's clip: MuJoCo's renderer, dm_control's ``side`` camera (:data:`CAMERAS` where another)."""

    image_format = "JPEG"

    def __init__(self, task: str, size: int = 256, camera: int | str | None = None):
        import mujoco

        from rebel_jax.envs.dmc import TASKS, mj_model

        physics = mj_model(task)
        self.model = mujoco.MjModel.from_xml_string(render_xml(task))
        if (self.model.nq, self.model.nbody) != (physics.nq, physics.nbody):
            raise ClipError(f"{task}: the render model's bodies differ from the physics model's")
        self.data = mujoco.MjData(self.model)
        self.fps = 1.0 / (float(physics.opt.timestep) * TASKS[task].n_substeps)
        self.size = size
        self.camera = CAMERAS.get(task, "side") if camera is None else camera
        self._mujoco = mujoco
        self.renderer = open_renderer(self.model, size)

    def frames(self, positions: np.ndarray) -> np.ndarray:
        mujoco = self._mujoco
        out = np.empty((len(positions), self.size, self.size, 3), np.uint8)
        for t, qpos in enumerate(np.asarray(positions, np.float64)):
            self.data.qpos[:] = qpos
            self.data.qvel[:] = 0.0
            mujoco.mj_forward(self.model, self.data)
            self.renderer.update_scene(self.data, camera=self.camera)
            out[t] = self.renderer.render()
        return out

    def close(self) -> None:
        self.renderer.close()


def open_renderer(model, size: int):
    """MuJoCo's renderer of ``model``, ``size`` pixels square; :class:`ClipError` naming the fix where MuJoCo finds
    no OpenGL context."""
    import mujoco

    try:
        return mujoco.Renderer(model, size, size)
    except Exception as err:  # glfw without a display, EGL or OSMesa libraries missing, ...
        backend = os.environ.get("MUJOCO_GL") or "unset (glfw, which needs a display)"
        raise ClipError(
            f"MuJoCo could not open an OpenGL context to render clips (MUJOCO_GL is {backend}): {err}. "
            "Set MUJOCO_GL=egl (a GPU, or Mesa's EGL: apt-get install libegl1 libgl1-mesa-dri) or "
            "MUJOCO_GL=osmesa (apt-get install libosmesa6) before starting."
        ) from err


class MetaWorldRenderer:
    """A Meta-World task's clip: MuJoCo's renderer on Meta-World's model, posed per frame by
    ``rebel_jax.envs.metaworld.pose`` (the step's ``qpos`` and scene), through :data:`METAWORLD_CAMERA`.

    Meta-World's corner cameras look at the table upside down (their image ``y`` axis points down in the world; its
    documentation shows them rotated, metaworld@3.1.1:docs/rendering/rendering.md:45): a frame whose camera is so
    is turned by 180 degrees, the picture of the same camera rolled right side up (not a mirror image).

    Args:
      task: ``metaworld_<task>`` or ``<task>``, a key of ``rebel_jax.envs.metaworld.TASKS`` (the tasks whose step
        is refused too: their clips draw recorded states).
      size: width and height of a frame, in pixels.
      camera: a camera of the model (name or id); None: :data:`METAWORLD_CAMERA`.
    """

    image_format = "JPEG"

    def __init__(self, task: str, size: int = 256, camera: int | str | None = None):
        import mujoco

        from rebel_jax.envs import metaworld

        name = task.removeprefix(metaworld.PREFIX)
        if name not in metaworld.TASKS:
            raise ClipError(f"unknown Meta-World task {task!r}; valid: {', '.join(metaworld.TASKS)}")
        self.task, self._pose = name, metaworld.pose
        self.model = metaworld.mj_model(name)
        self.data = mujoco.MjData(self.model)
        self.fps = 1.0 / (float(self.model.opt.timestep) * metaworld.FRAME_SKIP)
        self.size = size
        self.camera = METAWORLD_CAMERA if camera is None else camera
        try:
            self._camera_id = self.model.camera(self.camera).id
        except (KeyError, IndexError) as err:
            names = ", ".join(self.model.camera(i).name for i in range(self.model.ncam))
            raise ClipError(f"metaworld_{name} has no camera {self.camera!r}; valid: {names}") from err
        self.renderer = open_renderer(self.model, size)

    def upside_down(self) -> bool:
        """Whether the camera's image ``y`` axis points down in the world at the current pose."""
        return bool(self.data.cam_xmat[self._camera_id, 7] < 0)  # row 2 (world z), column 1 (image y)

    def frames(self, positions: np.ndarray, scenes: np.ndarray | None = None) -> np.ndarray:
        """(H, nq) positions and their (H, k) scenes -> (H, S, S, 3) uint8 frames."""
        if scenes is None:
            raise ClipError(f"metaworld_{self.task}'s clips need the stored scenes beside the positions")
        positions, scenes = np.asarray(positions, np.float64), np.asarray(scenes, np.float64)
        out = np.empty((len(positions), self.size, self.size, 3), np.uint8)
        for t, (qpos, scene) in enumerate(zip(positions, scenes, strict=True)):
            self._pose(self.task, self.model, self.data, qpos, scene)
            self.renderer.update_scene(self.data, camera=self._camera_id)
            frame = self.renderer.render()
            out[t] = frame[::-1, ::-1] if self.upside_down() else frame
        return out

    def close(self) -> None:
        self.renderer.close()


def make_renderer(task: str, size: int = 256) -> ProbeRenderer | MujocoRenderer | MetaWorldRenderer:
    """The clip renderer of ``task`` (raises :class:`ClipError` where it cannot render)."""
    if size < 16:
        raise ClipError(f"clip size {size} is too small: allowed >= 16")
    if task == "probe_point":
        return ProbeRenderer(size)
    from rebel_jax.envs.metaworld import PREFIX

    if task.startswith(PREFIX):
        return MetaWorldRenderer(task, size)
    return MujocoRenderer(task, size)
