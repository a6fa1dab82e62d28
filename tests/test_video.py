"""Video files and the run-directory config round trip of ``rebel_jax.run.video``."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import pathlib

import imageio.v3 as iio
import jax
import numpy as np
import pytest

from rebel_jax.agents.drqv2 import DrQV2, DrQV2Config
from rebel_jax.config import PRESETS, from_dict, to_dict
from rebel_jax.envs import dmc, render
from rebel_jax.envs.pixels import PixelEnv
from rebel_jax.run import video


def test_gif_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    # Few distinct colours, so that the GIF palette keeps them exactly.
    palette = rng.integers(0, 256, (8, 3), dtype=np.uint8)
    frames = palette[rng.integers(0, 8, (5, 12, 10))]
    path = video.write(tmp_path / "clip.gif", frames, fps=25)
    back = iio.imread(path, index=None)
    assert back.shape[:3] == (5, 12, 10)
    np.testing.assert_array_equal(back[..., :3], frames)


def test_bad_frames_and_formats_raise(tmp_path):
    frames = np.zeros((2, 4, 4, 3), np.uint8)
    with pytest.raises(ValueError, match="uint8"):
        video.write(tmp_path / "a.gif", frames.astype(np.float32), fps=10)
    with pytest.raises(ValueError, match="T >= 1"):
        video.write(tmp_path / "a.gif", frames[:0], fps=10)
    with pytest.raises(ValueError, match=".avi"):
        video.write(tmp_path / "a.avi", frames, fps=10)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_config_read_back_from_a_run_directory_equals_the_original(preset):
    cfg = PRESETS[preset]
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, task="cheetah_run"))
    text = json.dumps(to_dict(cfg))  # what the command line writes as config.json
    assert from_dict(type(cfg), json.loads(text)) == cfg


@pytest.mark.heavy  # make test-heavy: compiles a pixel walker's episode, its step and two cameras (about 40 s)
def test_a_pixel_policy_s_clip_is_its_episode_seen_by_the_clip_camera():
    # A pixel task's policy acts on its own frame stacks (here 16x16); the clip's camera (24x24) draws the same
    # physics. Against a Python loop of reset, policy, step and render.
    env = PixelEnv(dmc.make_env("walker_walk", episode_length=20), size=16)
    agent = DrQV2(DrQV2Config(feature_dim=8, hidden=16), env.observation_shape, env.action_size)
    params = agent.init(jax.random.PRNGKey(0))
    policy = functools.partial(agent.act_deterministic, params)
    camera = render.make_camera(env.mj_model, 0, 24, 24)
    key, steps = jax.random.PRNGKey(1), 4
    frames, total = jax.jit(lambda k: video.episode_frames(env, policy, k, steps, camera))(key)
    state = jax.jit(env.reset)(key)
    expected, rewards = [camera.render(state.pipeline_state)], []
    step = jax.jit(lambda s: env.step(s, policy(s.obs)))
    for _ in range(steps):
        state = step(state)
        expected.append(camera.render(state.pipeline_state))
        rewards.append(float(state.reward))
    expected = np.stack(expected)
    assert frames.shape == expected.shape == (steps + 1, 24, 24, 3) and len(np.unique(expected[-1])) > 2
    assert np.mean(np.abs(np.asarray(frames, int) - expected) <= 1) > 0.99  # the same pixels, up to rounding
    assert not np.array_equal(expected[0], expected[-1])  # the walker moved
    np.testing.assert_allclose(total, sum(rewards), rtol=1e-5)


# -- python -m rebel_jax.run.video's inputs: one line, exit status 2, nothing written --------------------------------
def _run_dir(tmp_path, task: str = "cheetah_run", **meta) -> pathlib.Path:
    """A run directory as the trainer leaves it, but for its checkpoint's content (the checks come first)."""
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints" / "1").mkdir(parents=True)
    cfg = dataclasses.replace(PRESETS["tiny"], env=dataclasses.replace(PRESETS["tiny"].env, task=task))
    (run_dir / "config.json").write_text(json.dumps(to_dict(cfg)))
    (run_dir / "meta.json").write_text(json.dumps({"columns": 2, "device_columns": 2, **meta}))
    return run_dir


def _fifo_config(tmp_path) -> pathlib.Path:
    run_dir = _run_dir(tmp_path)
    (run_dir / "config.json").unlink()
    os.mkfifo(run_dir / "config.json")
    return run_dir


VIDEO_BAD = {
    "missing-run-dir": (lambda t: t / "none", [], "it does not exist"),
    "empty-run-dir": (lambda t: t, [], "has no config.json"),
    "fifo-config": (_fifo_config, [], "config.json is invalid: allowed a regular file"),
    "no-checkpoint": (lambda t: _run_dir(t).joinpath("checkpoints", "1").rmdir() or t / "run", [], "no checkpoint"),
    "probe-task": (lambda t: _run_dir(t, "probe_point"), [], "no MuJoCo model to render"),
    "meta-types": (lambda t: _run_dir(t, columns="x"), [], "columns='x' is invalid"),
    "column": (_run_dir, ["--column", "5"], "column=5 is invalid: allowed 0 to 1"),
    "huge-seed": (_run_dir, ["--seed", str(2**63)], "seed=9223372036854775808 is invalid"),
    "negative-steps": (_run_dir, ["--steps", "-3"], "steps=-3 is invalid: allowed integers 1 to"),
    "size-0": (_run_dir, ["--size", "0"], "size=0 is invalid: allowed integers 16 to"),
    "size-huge": (_run_dir, ["--size", "100000"], "size=100000 is invalid"),
    "frames-too-large": (_run_dir, ["--steps", "100000", "--size", "1024"], "the clip's frames would take"),
    "format": (_run_dir, ["--out", "clip.avi"], "allowed a file ending in .gif or .mp4"),
    "out-parent-missing": (_run_dir, ["--out", "nowhere/deeper/clip.gif"], "does not exist (create it first)"),
    "camera": (_run_dir, ["--camera", "nonesuch"], "camera='nonesuch' is invalid"),
    # A checkpoint without its checksums is damaged: refused, and left where it is (the run is not changed).
    "damaged-checkpoint": (lambda t: _run_dir(t, checkpoint_checksums=True), [], "no readable checkpoint"),
    "not-a-number": (_run_dir, ["--column", "x"], "argument --column: invalid int value"),
}


@pytest.mark.parametrize("make,flags,expected", VIDEO_BAD.values(), ids=VIDEO_BAD.keys())
def test_a_bad_video_input_is_one_line_with_exit_status_2_and_writes_nothing(
    tmp_path, monkeypatch, capsys, make, flags, expected
):
    run_dir = make(tmp_path)
    monkeypatch.chdir(tmp_path)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(SystemExit) as end:
        video.main([str(run_dir), *flags, "--no-compile-cache"])
    assert end.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    *warnings, line = err  # a damaged checkpoint's warning, as the trainer prints it, before the error
    assert line.startswith("error: ") and expected in line, err
    assert all(w.startswith("warning: checkpoint ") and "left it in place" in w for w in warnings), err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # no directory made, no file
