"""Clips for the labelling page: the probe's plot, the frame sheet, and MuJoCo's renderer on the MJX and Meta-World
tasks."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import pathlib
import subprocess
import sys
import textwrap

import flax.struct
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from brax.envs.base import Env, State
from PIL import Image

from rebel_jax.envs.dmc import TASKS, mj_model
from rebel_jax.run.human import clips

ROOT = pathlib.Path(__file__).parents[1]


def test_probe_clip_draws_the_point_where_it_is():
    renderer = clips.ProbeRenderer(size=128)
    positions = np.array([[-1.5, 1.5], [0.0, 0.0], [0.75, -0.5]], np.float32)  # A corner of the box first.
    frames = renderer.frames(positions)
    assert frames.shape == (3, 128, 128, 3) and frames.dtype == np.uint8
    for frame, (x, y) in zip(frames, positions, strict=True):
        dot = np.all(frame == (30, 70, 200), axis=-1)  # The current point's colour.
        rows, cols = np.nonzero(dot)
        half = renderer.bound  # The plot spans [-half, half] on both axes.
        centre_x = (cols.mean() + 0.5) / 128 * 2 * half - half
        centre_y = half - (rows.mean() + 0.5) / 128 * 2 * half
        assert abs(centre_x - x) < 0.05 and abs(centre_y - y) < 0.05
    trail = np.all(frames[2] == (150, 170, 220), axis=-1)
    assert trail.any() and not np.all(frames[0] == (150, 170, 220), axis=-1).any()  # The trail grows.


def test_sheet_holds_the_frames_in_rows_of_ten():
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (13, 8, 8, 3), dtype=np.uint8)
    image = np.asarray(Image.open(io.BytesIO(clips.sheet(frames, "PNG"))))
    assert image.shape == (16, 80, 3)  # 2 rows of 10 frames of 8x8
    for k, frame in enumerate(frames):
        r, c = divmod(k, clips.COLUMNS)
        np.testing.assert_array_equal(image[8 * r : 8 * r + 8, 8 * c : 8 * c + 8], frame)


@pytest.mark.parametrize("task", ["walker_walk", "cheetah_run"])
def test_render_model_has_the_physics_models_kinematics(task):
    physics = mj_model(task)
    render = mujoco.MjModel.from_xml_string(clips.render_xml(task))
    assert render.ntex >= 2 and render.nlight >= 1  # dm_control's skybox, checker floor and a light
    for field in ("body_pos", "body_quat", "body_parentid", "jnt_type", "jnt_axis", "jnt_pos", "qpos0", "geom_size"):
        np.testing.assert_allclose(getattr(render, field), getattr(physics, field), err_msg=field)
    assert [render.camera(i).name for i in range(render.ncam)] == ["side"]
    assert TASKS[task].name == task


# MuJoCo reads MUJOCO_GL when it is imported, so the renderer runs in a fresh process.
RENDER = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from rebel_jax.envs.dmc import mj_model
    from rebel_jax.run.human import clips

    try:
        renderer = clips.make_renderer("walker_walk", 256)
    except clips.ClipError as err:
        print(json.dumps({"error": str(err)}))
        sys.exit(0)
    qpos = np.tile(mj_model("walker_walk").qpos0, (3, 1))
    qpos[1, 1] = 0.5   # rootx: the walker moved forward; the tracking camera shows the floor moving back
    qpos[2, 4] = 1.2   # right hip bent: the leg moves in the picture
    frames = renderer.frames(qpos)
    torso = np.all(np.abs(frames.astype(int) - (179, 128, 77)) < 60, axis=-1)  # material "self", lit
    print(json.dumps({
        "shape": list(frames.shape), "fps": renderer.fps,
        "floor_moved": float(np.abs(frames[1, 200:].astype(int) - frames[0, 200:]).mean()),
        "leg_moved": float(np.abs(frames[2].astype(int) - frames[0]).mean()),
        "body_pixels": int(torso[0].sum()), "body_centre": float(np.nonzero(torso[0])[1].mean()),
    }))
    """
)


def _rendered(script: str, *args: str) -> dict:
    """The JSON line a render script prints, run in a fresh process (MuJoCo reads MUJOCO_GL at import); skips
    where MuJoCo finds no OpenGL."""
    gl = os.environ.get("MUJOCO_GL", "egl")
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"), MUJOCO_GL=gl)
    cmd = [sys.executable, "-c", script, *args]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    if "error" in result:
        pytest.skip(f"no OpenGL for MuJoCo here (MUJOCO_GL={gl}): {result['error']}")
    return result


def test_walker_clip_with_mujocos_renderer():
    result = _rendered(RENDER)
    assert result["shape"] == [3, 256, 256, 3] and result["fps"] == 40.0  # dm_control's walker: 25 ms per step
    assert result["body_pixels"] > 500 and 96 < result["body_centre"] < 160  # centred by the tracking camera
    assert result["floor_moved"] > 1.0 and result["leg_moved"] > 0.5


QUADRUPED_RENDER = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from rebel_jax.envs.dmc import mj_model
    from rebel_jax.run.human import clips

    try:
        renderer = clips.make_renderer("quadruped_walk", 256)
    except clips.ClipError as err:
        print(json.dumps({"error": str(err)}))
        sys.exit(0)
    qpos = np.tile(mj_model("quadruped_walk").qpos0, (3, 1))  # standing on its toes, facing +x
    qpos[1, 0] = 0.5   # the root moved forward; the tracking camera shows the floor moving back
    qpos[2, 7] = 0.8   # the front left hip's yaw: the leg swings in the picture
    frames = renderer.frames(qpos)
    body = np.all(np.abs(frames.astype(int) - (179, 128, 77)) < 60, axis=-1)  # materials "self" and "effector", lit
    print(json.dumps({
        "shape": list(frames.shape), "fps": renderer.fps, "camera": renderer.camera,
        "floor_moved": float(np.abs(frames[1, 200:].astype(int) - frames[0, 200:]).mean()),
        "leg_moved": float(np.abs(frames[2].astype(int) - frames[0]).mean()),
        "body_pixels": int(body[0].sum()), "body_centre": float(np.nonzero(body[0])[1].mean()),
    }))
    """
)


def test_quadruped_clip_with_mujocos_renderer():
    """The quadruped (ellipsoid and cylinder geoms, which the pure-JAX camera does not draw) through its side
    camera ``y``, which tracks the centre of mass."""
    result = _rendered(QUADRUPED_RENDER)
    assert result["shape"] == [3, 256, 256, 3] and result["fps"] == 50.0  # dm_control's quadruped: 20 ms per step
    assert result["camera"] == "y" and clips.INSTRUCTIONS["quadruped_walk"]
    assert result["body_pixels"] > 500 and 96 < result["body_centre"] < 160  # centred by the tracking camera
    assert result["floor_moved"] > 1.0 and result["leg_moved"] > 0.5


def test_cli_without_opengl_stops_at_once_naming_the_fix(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(ROOT / "src")
    cmd = [sys.executable, "-m", "rebel_jax.train", "--preset", "tiny", "--algo", "pebble", "--task", "walker_walk"]
    cmd += ["--teacher", "human", "--human.port", "0", "--run-dir", str(tmp_path / "run"), "--no-progress"]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2, out.stderr[-3000:]
    assert "MUJOCO_GL=egl" in out.stderr and "MUJOCO_GL=osmesa" in out.stderr
    assert not (tmp_path / "run" / "metrics.jsonl").exists()  # Before any training.


# Meta-World: MuJoCo draws a state from its qpos, the mocap and the model as the episode's reset left it (the reset
# moves bodies and the goal site of the model itself). The reference is Meta-World's own recorded state
# (tests/data/metaworld/<task>.npz): its model's body positions after each reset, and the goal site where each task's
# reset_model writes it (``self.model.site("goal").pos = self._target_pos``): metaworld@3.1.1:metaworld/envs/
# sawyer_drawer_open_v3.py:112, sawyer_door_v3.py:120, sawyer_sweep_into_goal_v3.py:115, sawyer_window_open_v3.py:122.
METAWORLD_DATA = ROOT / "tests" / "data" / "metaworld"
GOAL_SITE_WRITTEN = {"drawer-open", "door-open", "sweep-into", "window-open"}


def _metaworld_model(task: str, ref: dict, e: int) -> mujoco.MjModel:
    """Meta-World's model as the reset of recorded episode ``e`` left it."""
    from rebel_jax.envs import metaworld

    model = metaworld.mj_model(task)
    model.body_pos[:] = ref["episode_body_pos"][e]
    if task in GOAL_SITE_WRITTEN:
        model.site("goal").pos = ref["episode_target_pos"][e]
    return model


def _metaworld_data(model: mujoco.MjModel, ref: dict, row: int) -> mujoco.MjData:
    """MuJoCo's kinematics (float64) of Meta-World's full recorded state at ``row`` (``model``: its episode's)."""
    data = mujoco.MjData(model)
    for field in ("qpos", "qvel", "mocap_pos", "mocap_quat"):
        getattr(data, field)[:] = ref[field][row]
    mujoco.mj_forward(model, data)
    return data


def _recorded_scenes(task: str, ref: dict, rows: np.ndarray) -> np.ndarray:
    """``MetaWorldEnv.scene`` of the recorded rows, from the state as our env holds it: the mocap (float32, as MJX
    stores it) and the episode's info as our reset writes it: ``body_pos`` is the reset's draw (Meta-World's last,
    ``episode_draws``), ``target_pos`` the goal (test_envs_metaworld.py checks it equals Meta-World's at the same
    draws)."""
    import types

    from rebel_jax.envs import metaworld

    episodes = ref["episode"][rows]
    state = types.SimpleNamespace(
        pipeline_state=types.SimpleNamespace(mocap_pos=jnp.asarray(ref["mocap_pos"][rows], jnp.float32)),
        info={
            "body_pos": jnp.asarray(ref["episode_draws"][episodes, -1], jnp.float32),
            "target_pos": jnp.asarray(ref["episode_target_pos"][episodes], jnp.float32),
        },
    )
    return np.asarray(metaworld.frame_scene(metaworld.TASKS[task], state))


@pytest.mark.parametrize(
    "task", ["drawer-open", "button-press", "door-open", "sweep-into", "window-open", "door-unlock", "hammer"]
)
def test_metaworld_frame_state_equals_mujocos_of_metaworlds_recorded_state(task):
    """What a clip's frame is drawn from (``metaworld.pose`` of the stored qpos and scene: every body, geom and site,
    the arm's hand, the objects, the goal and the mocap) equals MuJoCo's kinematics of Meta-World's full recorded
    state, every 50th step of the 4 recorded episodes (random and scripted)."""
    from rebel_jax.envs import metaworld

    ref = dict(np.load(METAWORLD_DATA / f"{task}.npz"))
    rows = np.arange(0, len(ref["t"]), 50)
    scenes = _recorded_scenes(task, ref, rows)
    assert scenes.shape == (len(rows), metaworld.scene_size(task))
    model = metaworld.mj_model(task)
    data = mujoco.MjData(model)
    plain = metaworld.mj_model(task)  # the model as compiled: what drawing qpos alone would show
    plain_data = mujoco.MjData(plain)
    shown = {"hand": model.body("hand").id, "mocap": model.body("mocap").id}
    stale = 0.0
    for row, scene in zip(rows, scenes, strict=True):
        expected = _metaworld_data(_metaworld_model(task, ref, ref["episode"][row]), ref, row)
        metaworld.pose(task, model, data, np.asarray(ref["qpos"][row], np.float32), scene)
        for field in ("xpos", "xmat", "geom_xpos", "geom_xmat", "site_xpos", "cam_xpos"):
            np.testing.assert_allclose(getattr(data, field), getattr(expected, field), atol=2e-6, err_msg=field)
        for name, body in shown.items():
            np.testing.assert_allclose(data.xpos[body], expected.xpos[body], atol=2e-6, err_msg=name)
        plain_data.qpos[:] = ref["qpos"][row]
        mujoco.mj_forward(plain, plain_data)
        stale = max(stale, np.abs(plain_data.geom_xpos - expected.geom_xpos).max())
        stale = max(stale, np.abs(plain_data.site_xpos - expected.site_xpos).max())
    spec = metaworld.TASKS[task]
    if spec.moved_body is not None or task in GOAL_SITE_WRITTEN - {"sweep-into"}:  # sweep-into's goal: its XML's
        assert stale > 1e-2  # without the scene, the moved body or the goal would be drawn centimetres away


def test_metaworld_renderer_names_the_valid_tasks_and_cameras():
    with pytest.raises(clips.ClipError, match="valid: drawer-open, button-press"):
        clips.make_renderer("metaworld_drawer-close", 64)
    with pytest.raises(clips.ClipError, match="no camera 'side'; valid: topview, corner, corner2"):
        clips.MetaWorldRenderer("metaworld_drawer-open", 64, camera="side")


def test_metaworld_pose_refuses_a_scene_of_another_size():
    from rebel_jax.envs import metaworld

    model = metaworld.mj_model("drawer-open")
    with pytest.raises(ValueError, match=r"scene \(9,\)"):
        metaworld.pose("drawer-open", model, mujoco.MjData(model), model.qpos0, np.zeros(6))


# MuJoCo reads MUJOCO_GL when it is imported: a fresh process, which reads the recorded states as the test above does.
METAWORLD_RENDER = textwrap.dedent(
    """
    import json, sys
    import mujoco
    import numpy as np
    sys.path.insert(0, sys.argv[1])
    from test_human_clips import METAWORLD_DATA, _metaworld_data, _metaworld_model, _recorded_scenes
    from rebel_jax.run.human import clips

    SKY = np.array([128, 126, 122])  # the scene's skybox (rgb .50 .495 .48), unlit
    out = {}
    for task in ("drawer-open", "sweep-into", "door-open"):
        try:
            renderer = clips.make_renderer("metaworld_" + task, 128)
        except clips.ClipError as err:
            print(json.dumps({"error": str(err)}))
            sys.exit(0)
        ref = dict(np.load(METAWORLD_DATA / f"{task}.npz"))
        rows = np.where(ref["t"] % 250 == 0)[0]  # 3 states of each recorded episode, its reset among them
        scenes = _recorded_scenes(task, ref, rows)
        frames = renderer.frames(ref["qpos"][rows], scenes).astype(int)
        others = renderer.frames(ref["qpos"][rows], np.roll(scenes, 3, axis=0)).astype(int)  # other episodes' scenes
        renderer.close()
        # The reference: MuJoCo's renderer on Meta-World's full recorded state, through its camera corner4, turned by
        # 180 degrees (the camera's image y axis points down: Meta-World's documentation shows it turned).
        expected = []
        for e in range(4):
            model = _metaworld_model(task, ref, e)
            with mujoco.Renderer(model, 128, 128) as other:
                for row in rows[ref["episode"][rows] == e]:
                    other.update_scene(_metaworld_data(model, ref, row), camera="corner4")
                    expected.append(other.render()[::-1, ::-1])
        expected = np.asarray(expected, int)
        sky = np.all(np.abs(frames - SKY) <= 3, axis=-1)
        out[task] = {
            "shape": list(frames.shape), "fps": renderer.fps, "camera": renderer.camera,
            "error": float(np.abs(frames - expected).mean()),
            "pixels_off": float((np.abs(frames - expected).max(-1) > 16).mean()),
            "other_scenes": float(np.abs(others - expected).mean()),
            "sky_top": float(sky[:, :16].mean()), "sky_bottom": float(sky[:, -16:].mean()),
        }
    print(json.dumps(out))
    """
)


def test_metaworld_clip_draws_what_mujoco_draws_of_metaworlds_state():
    """The clips of drawer-open, sweep-into and door-open (recorded states, 128 px) equal MuJoCo's renderer on
    Meta-World's full recorded states through the same camera, right side up (the sky at the top); drawn with other
    episodes' scenes (another drawer or door position), they would not."""
    result = _rendered(METAWORLD_RENDER, str(ROOT / "tests"))
    for task, r in result.items():
        assert r["shape"] == [12, 128, 128, 3] and r["fps"] == 80.0 and r["camera"] == "corner4", task  # 12.5 ms
        assert r["error"] < 0.05 and r["pixels_off"] < 1e-3, (task, r)
        assert r["sky_top"] > 0.3 and r["sky_bottom"] < 0.01, (task, r)
    for task in ("drawer-open", "door-open"):  # their reset moves the drawer, the door and the goal
        assert result[task]["other_scenes"] > 0.5, (task, result[task])


@flax.struct.dataclass
class _Pipeline:
    qpos: jax.Array
    mocap_pos: jax.Array


class KinematicDrawer(Env):
    """``metaworld_drawer-open`` stepped kinematically (MJX's step of the Sawyer arm compiles for minutes on a CPU; the
    tests above check the drawing of Meta-World's own states): the reset's draw, goal and MuJoCo state are the
    task's; a step moves the mocap by the action (1 cm per unit) and the drawer's slide joint by its y. The
    observation is the mocap's position and the slide joint's, so that a stored transition shows which step's
    positions and scene stand beside it."""

    reports_success = False

    def __init__(self, episode_length: int):
        from rebel_jax.envs import metaworld

        self.task = metaworld.MetaWorldEnv("drawer-open", episode_length)
        self.episode_length = episode_length
        self.goal = metaworld.TASKS["drawer-open"].goal(self.task.mujoco_model)

    observation_size = property(lambda self: 4)
    action_size = property(lambda self: 4)
    backend = property(lambda self: "mjx")

    def scene(self, state: State) -> jax.Array:
        return self.task.scene(state)

    def _state(self, p: _Pipeline, reward, info: dict, done: jax.Array) -> State:
        obs = jnp.concatenate([p.mocap_pos[0], p.qpos[9:10]])
        return State(p, obs, jnp.asarray(reward, jnp.float32), done, {}, info)

    def reset(self, rng: jax.Array) -> State:
        draw = self.task.draw(rng)
        target, _ = self.goal(draw, None)
        start = self.task.hand_reset
        p = _Pipeline(jnp.asarray(start.qpos, jnp.float32), jnp.asarray(start.mocap_pos, jnp.float32))
        zero = jnp.zeros(())
        info = {"body_pos": draw, "target_pos": target, "steps": jnp.zeros((), jnp.int32), "truncation": zero}
        return self._state(p, 0.0, info, zero)

    def step(self, state: State, action: jax.Array) -> State:
        p = state.pipeline_state
        slide = jnp.clip(p.qpos[9] + 0.01 * action[1], -0.16, 0.0)
        p = _Pipeline(p.qpos.at[9].set(slide), p.mocap_pos + 0.01 * action[:3])
        steps = state.info["steps"] + 1
        done = (steps >= self.episode_length).astype(jnp.float32)
        return self._state(p, -slide, dict(state.info, steps=steps, truncation=done), done)


def metaworld_host_config():
    """test_human_session.py's REBEL run (sessions at rounds 2 and 3, 4 queries of 8 steps) on drawer-open."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_human_session import FLAGS

    from rebel_jax.run.cli import parse

    flags = [f if f != "probe_point" else "metaworld_drawer-open" for f in FLAGS]
    return parse([*flags, "--teacher", "human"]).config


def kinematic_make_env(task, *args, **kwargs):
    """``make_env`` with ``metaworld_drawer-open`` stepped kinematically (:class:`KinematicDrawer`)."""
    from rebel_jax.envs import make_env

    if task != "metaworld_drawer-open":
        return make_env(task, *args, **kwargs)
    solver, episode_length = args
    return KinematicDrawer(episode_length)


def test_the_buffer_stores_each_metaworld_steps_scene_beside_its_positions(monkeypatch):
    """A human-teacher run's buffer on a Meta-World task: each transition's qpos and scene (mocap, the episode's drawer
    and goal) are those of the state its observation was made in."""
    import rebel_jax.train.trainer as trainer_module
    from rebel_jax.train import Trainer, compiled, seed_keys

    monkeypatch.setattr(trainer_module, "make_env", kinematic_make_env)
    trainer = Trainer(metaworld_host_config(), host_teacher=True)
    init, round_fn, _ = compiled(trainer)
    state, _ = round_fn(init(seed_keys(0, 1)), jnp.int32(0))
    buffer = jax.device_get(state.buffer)
    filled = int(buffer.size[0])
    obs, qpos, scene = buffer.obs[0, :filled], buffer.qpos[0, :filled], buffer.scene[0, :filled]
    assert filled > 0 and qpos.shape[-1] == 10 and scene.shape[-1] == 9
    np.testing.assert_array_equal(scene[..., :3], obs[..., :3])  # the mocap of the observed state
    np.testing.assert_array_equal(qpos[..., 9], obs[..., 3])  # the drawer's slide joint of the observed state
    drawer, goal = scene[..., 3:6].reshape(-1, 3), scene[..., 6:9].reshape(-1, 3)
    assert len(np.unique(drawer, axis=0)) > 1  # a fresh draw at each reset
    assert np.all(np.abs(drawer[:, 0]) <= 0.1) and np.allclose(drawer[:, 1:], [0.9, 0.0])  # Meta-World's reset space
    np.testing.assert_allclose(goal, drawer + [0.0, -0.36, 0.09], atol=1e-6)  # sawyer_drawer_open_v3.py:110-112
    assert Trainer(trainer.cfg)._init_buffer().scene is None  # stored for the human teacher only
    walker = dataclasses.replace(trainer.cfg, env=dataclasses.replace(trainer.cfg.env, task="walker_walk"))
    assert Trainer(walker, host_teacher=True)._init_buffer().scene is None  # qpos is all a walker's frame needs


# The whole path, in a fresh process (MuJoCo reads MUJOCO_GL at import): a robot fetches each clip from the page's
# HTTP API and answers; the clips must be the renderer's frames of the segments' stored positions and scenes.
METAWORLD_SESSION = textwrap.dedent(
    """
    import io, json, pathlib, sys, tempfile, threading, time, urllib.request
    import jax.numpy as jnp
    import numpy as np
    from PIL import Image
    sys.path.insert(0, sys.argv[1])
    from test_human_clips import kinematic_make_env, metaworld_host_config
    from test_human_session import _scripted_answer
    import rebel_jax.train.trainer as trainer_module
    from rebel_jax.run.human import ClipError, HostTeacher, HumanOptions, clips
    from rebel_jax.train import Trainer, compiled, seed_keys

    trainer_module.make_env = kinematic_make_env
    cfg = metaworld_host_config()
    trainer = Trainer(cfg, host_teacher=True)
    init, round_fn, _ = compiled(trainer)
    options = HumanOptions(port=0, clip_size=64)
    try:
        host = HostTeacher(trainer, "human", pathlib.Path(tempfile.mkdtemp()), options, False)
    except ClipError as err:
        print(json.dumps({"error": str(err)}))
        sys.exit(0)
    drawn = []  # the renderer's inputs and frames, call by call
    frames_of = host.renderer.frames
    def logged(positions, scenes):
        frames = frames_of(positions, scenes)
        drawn.append((np.asarray(positions), np.asarray(scenes), frames))
        return frames
    host.renderer.frames = logged
    served, done = [], threading.Event()

    def call(path, body=None):
        headers = {"Authorization": f"token {host.server.token}"}
        if body is not None:
            headers["Content-Type"] = "application/json"
        data = None if body is None else json.dumps(body).encode()
        with urllib.request.urlopen(urllib.request.Request(host.server.url + path, data, headers)) as response:
            return response.read()

    def robot():
        while not done.is_set():
            session = host.labelling.session
            pending = [q for q in session.queries if q.id not in session.answers.answers] if session else []
            if session is not None and session.closed is None and session.complete:
                call("api/finish", {})
            elif pending and pending[0].clips:
                query = pending[0]
                for side in ("left", "right"):
                    served.append(call(f"clips/{query.id}/{side}"))
                call("api/shown", {"query": query.id})
                call("api/answer", {"query": query.id, "answer": _scripted_answer(query)})
            time.sleep(0.01)

    threading.Thread(target=robot, daemon=True).start()
    state = init(seed_keys(0, 1))
    try:
        for r in range(cfg.train.num_rounds):
            state, _ = host.before_round(state, r)
            state, _ = round_fn(state, jnp.int32(r))
    finally:
        done.set()
        host.close()
    sheets = [clips.sheet(frames) for _, _, frames in drawn]
    scenes = np.concatenate([s for _, s, _ in drawn])
    buffer = state.buffer
    stored = {(tuple(np.asarray(q).round(6)), tuple(np.asarray(s).round(6)))
              for q, s in zip(np.asarray(buffer.qpos[0]).reshape(-1, 10), np.asarray(buffer.scene[0]).reshape(-1, 9))}
    print(json.dumps({
        "renderer": type(host.renderer).__name__, "instruction": host.labelling.instruction,
        "served": len(served), "drawn": len(drawn), "served_as_drawn": sum(image in sheets for image in served),
        "sheet_size": list(Image.open(io.BytesIO(served[0])).size),
        "frames": list(drawn[0][2].shape), "positions": list(drawn[0][0].shape), "scenes": list(drawn[0][1].shape),
        "from_buffer": all((tuple(q.round(6)), tuple(s.round(6))) in stored
                           for positions, scenes_, _ in drawn for q, s in zip(positions, scenes_)),
        "drawers": len(np.unique(scenes[:, 3:6], axis=0)),
        "labels": int(np.asarray(state.reward.data.count)[0]),
    }))
    """
)


@pytest.mark.heavy  # ~1 min on 2 cores (the REBEL run's compiles, 128 frames drawn); make test checks the buffer's
# scenes (above), the drawing of Meta-World's states, and the probe's sessions end to end (test_human_session.py)
def test_a_human_session_on_metaworld_serves_clips_of_the_stored_states():
    result = _rendered(METAWORLD_SESSION, str(ROOT / "tests"))
    assert (
        result["renderer"] == "MetaWorldRenderer"
        and result["instruction"] == clips.INSTRUCTIONS["metaworld_drawer-open"]
    )
    # 2 sessions of 4 queries, 2 clips each; every clip the page served is the renderer's sheet of one segment,
    # drawn from positions and scenes the buffer stored.
    assert result["served"] == result["drawn"] == 16 and result["served_as_drawn"] == 16 and result["from_buffer"]
    assert result["frames"] == [8, 64, 64, 3] and result["sheet_size"] == [8 * 64, 64]  # 8 frames in one row
    assert result["positions"] == [8, 10] and result["scenes"] == [8, 9]  # qpos; the mocap, drawer and goal
    assert result["drawers"] >= 2  # the clips show more than one episode's drawer
    assert result["labels"] > 0


# A Meta-World episode's video (the eval.gif of the training command, python -m rebel_jax.run.video), in a new process.
METAWORLD_VIDEO = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp
    import numpy as np
    sys.path.insert(0, sys.argv[1])
    from test_human_clips import KinematicDrawer
    from rebel_jax.run import video
    from rebel_jax.run.human import clips

    class Drawn(KinematicDrawer):
        spec = property(lambda self: self.task.spec)
        dt = property(lambda self: self.task.dt)

    env, steps, size = Drawn(500), 8, 96
    policy = lambda obs: jnp.array([1.0, -1.0, 0.0, 0.0])  # the hand 1 cm in +x and -y, the drawer 1 cm open a step
    written = {}
    video.write = lambda path, frames, fps: written.update(frames=np.asarray(frames), fps=fps)
    try:
        total = video.policy_video(env, policy, jax.random.PRNGKey(3), "unused.gif", steps, size)
    except clips.ClipError as err:
        print(json.dumps({"error": str(err)}))
        sys.exit(0)
    # The reference: the same episode stepped one step at a time, each state drawn by a renderer of its own.
    state, positions, scenes, rewards = env.reset(jax.random.PRNGKey(3)), [], [], []
    for t in range(steps + 1):
        positions.append(np.asarray(state.pipeline_state.qpos))
        scenes.append(np.asarray(env.scene(state)))
        if t < steps:
            state = env.step(state, policy(state.obs))
            rewards.append(float(state.reward))
    renderer = clips.make_renderer("metaworld_drawer-open", size)
    expected = renderer.frames(np.asarray(positions), np.asarray(scenes)).astype(int)
    renderer.close()
    frames = written["frames"].astype(int)
    print(json.dumps({
        "shape": list(frames.shape), "fps": written["fps"], "total": total, "rewards": sum(rewards),
        "largest_error": float(np.abs(frames - expected).max()), "moved": float(np.abs(frames[-1] - frames[0]).mean()),
    }))
    """
)


def test_a_metaworld_episodes_video_draws_each_state_of_the_episode():
    """``video.policy_video`` on a Meta-World task (drawer-open stepped kinematically) draws the reset state and then
    each step's state with its scene, at Meta-World's 80 frames a second, and returns the episode's return."""
    result = _rendered(METAWORLD_VIDEO, str(ROOT / "tests"))
    assert result["shape"] == [9, 96, 96, 3] and result["fps"] == pytest.approx(80.0)
    assert result["largest_error"] == 0.0 and result["moved"] > 0.1  # the hand and the drawer moved
    assert result["total"] == pytest.approx(result["rewards"], rel=1e-6)
