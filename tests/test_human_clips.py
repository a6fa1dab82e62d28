"""Clips for the labelling page: the probe's plot, the frame sheet, and MuJoCo's renderer on the MJX tasks."""

from __future__ import annotations

import io
import json
import os
import pathlib
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
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
