"""Clips for the labelling page: the probe's plot, the frame sheet, and MuJoCo's renderer on the MJX tasks."""

from __future__ import annotations

import io
import json
import os
import pathlib
import subprocess
import sys
import textwrap

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


def _rendered(script: str) -> dict:
    """The JSON line a render script prints, run in a fresh process (MuJoCo reads MUJOCO_GL at import); skips
    where MuJoCo finds no OpenGL."""
    gl = os.environ.get("MUJOCO_GL", "egl")
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"), MUJOCO_GL=gl)
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
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
