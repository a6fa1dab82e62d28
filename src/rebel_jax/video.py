"""Videos of policy episodes, rendered with the pure-JAX camera (:mod:`rebel_jax.render`).

    python -m rebel_jax.video RUN_DIR [--out FILE.gif|FILE.mp4] [--column 0] [--steps 500] [--size 240]

renders a deterministic episode of a saved run's latest checkpoint. Its compiled programs are kept in the
persistent compilation cache of ``python -m rebel_jax.train`` (``--compile-cache DIR``, ``--no-compile-cache``;
:mod:`rebel_jax.compile_cache`). GIFs are written with
imageio's Pillow plugin; MP4 needs imageio's ffmpeg plugin (``pip install imageio-ffmpeg``).
``rebel_jax.cli`` writes ``eval.gif`` at the end of each run of a MuJoCo task. The tasks the pure-JAX
camera cannot draw (the quadruped: ellipsoids and cylinders) are drawn by MuJoCo's renderer from the
episode's positions, as the labelling page's clips are (:class:`rebel_jax.human.clips.MujocoRenderer`;
it needs ``MUJOCO_GL=egl`` or ``osmesa``).
"""

from __future__ import annotations

import argparse
import functools
import json
import pathlib
import sys
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rebel_jax import compile_cache, render
from rebel_jax.errors import ConfigError
from rebel_jax.rundir import EXIT_USAGE


def write(path: str | pathlib.Path, frames: np.ndarray, fps: float) -> pathlib.Path:
    """Writes uint8 frames ``(T, H, W, 3)`` as a GIF or MP4 (by the file's suffix)."""
    import imageio.v3 as iio

    path = pathlib.Path(path)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise ValueError(f"frames must be uint8 (T >= 1, H, W, 3); got {frames.dtype} {frames.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".gif":
        # Pillow stores GIF frame durations in milliseconds; loop forever.
        iio.imwrite(path, frames, extension=".gif", duration=1000.0 / fps, loop=0)
    elif path.suffix.lower() == ".mp4":
        iio.imwrite(path, frames, extension=".mp4", fps=fps, codec="libx264", macro_block_size=1)
    else:
        raise ValueError(f"unknown video format {path.suffix!r}; use .gif or .mp4")
    return path


def episode_frames(
    env, policy: Callable[[jax.Array], jax.Array], key: jax.Array, steps: int, camera: render.Camera
) -> tuple[jax.Array, jax.Array]:
    """Frames ``(steps + 1, H, W, 3)`` and the total reward of one episode of ``policy(obs) -> action``.

    Jittable (``env``, ``policy``, ``steps`` and ``camera`` static). The first frame is the reset state.
    """
    state = env.reset(key)

    def body(state, _):
        state = env.step(state, policy(state.obs))
        return state, (camera.render(state.pipeline_state), state.reward)

    _, (frames, rewards) = jax.lax.scan(body, state, length=steps)
    return jnp.concatenate([camera.render(state.pipeline_state)[None], frames]), rewards.sum()


def episode_positions(
    env, policy: Callable[[jax.Array], jax.Array], key: jax.Array, steps: int
) -> tuple[jax.Array, jax.Array]:
    """Positions ``(steps + 1, nq)`` and the total reward of one episode of ``policy(obs) -> action``, for a
    renderer outside JAX. Jittable (``env``, ``policy`` and ``steps`` static). The first row is the reset state."""
    state = env.reset(key)

    def body(state, _):
        state = env.step(state, policy(state.obs))
        return state, (state.pipeline_state.qpos, state.reward)

    _, (qpos, rewards) = jax.lax.scan(body, state, length=steps)
    return jnp.concatenate([state.pipeline_state.qpos[None], qpos]), rewards.sum()


def drawn_by_mujoco(env) -> bool:
    """Whether ``env`` (a state task) has geoms that the pure-JAX camera does not draw, so that its videos are
    drawn by MuJoCo's renderer."""
    spec = getattr(env, "spec", None)
    return spec is not None and not spec.has_pixels


def policy_video(
    env,
    policy,
    key: jax.Array,
    path: str | pathlib.Path,
    steps: int,
    size: int = 240,
    camera: int | str | None = None,
) -> float:
    """Renders one episode of ``policy`` on ``env`` (a MuJoCo task) to ``path``; returns its return.

    ``camera``: a camera id or name of the model; None: camera 0, or where MuJoCo's renderer draws the task, the
    labelling page's camera (``rebel_jax.human.clips.CAMERAS``). Raises ``rebel_jax.human.ClipError`` where MuJoCo's
    renderer is needed and has no OpenGL context.
    """
    if drawn_by_mujoco(env):
        from rebel_jax.human.clips import MujocoRenderer

        renderer = MujocoRenderer(env.spec.name, size, camera)
        try:
            positions, total = jax.jit(lambda k: episode_positions(env, policy, k, steps))(key)
            frames = renderer.frames(np.asarray(positions))
        finally:
            renderer.close()
    else:
        cam = render.make_camera(env.mj_model, 0 if camera is None else camera, size, size)
        frames, total = jax.jit(lambda k: episode_frames(env, policy, k, steps, cam))(key)
    write(path, np.asarray(frames), fps=1.0 / env.dt)
    return float(total)


def load_policy(run_dir: pathlib.Path, column: int = 0):
    """(trainer, checkpoint step, policy parameters) of one column of a run's latest checkpoint; the trainer
    (on a pixel run too) acts with them through ``trainer.mean_action(params, obs)``.

    Only the policy's leaves are read from the checkpoint (not the replay buffer, gigabytes for a pixel run).
    """
    from rebel_jax import api
    from rebel_jax.checkpoint import Checkpointer
    from rebel_jax.config import read_config
    from rebel_jax.train import seed_keys

    cfg = read_config(run_dir / "config.json")
    meta = json.loads((run_dir / "meta.json").read_text())
    columns = int(meta["columns"])
    if not 0 <= column < columns:
        raise ValueError(f"column {column} out of range: the run has {columns} columns")
    trainer = api.make_trainer(cfg)
    keys = seed_keys(cfg.train.seed, columns)
    like = jax.eval_shape(jax.vmap(trainer.init), keys)
    ckpt = Checkpointer(run_dir / "checkpoints")
    try:
        step, params = ckpt.restore_leaves(like, trainer.policy_params)
    finally:
        ckpt.close()
    return trainer, step, jax.tree.map(lambda x: jnp.asarray(x[column]), params)


def main(argv: list[str] | None = None) -> pathlib.Path:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=pathlib.Path)
    parser.add_argument("--out", type=pathlib.Path, default=None, help="GIF or MP4; default RUN_DIR/policy.gif")
    parser.add_argument("--column", type=int, default=0, help="which vmapped seed column")
    parser.add_argument("--steps", type=int, default=None, help="agent steps (default: one episode)")
    parser.add_argument("--size", type=int, default=240, help="frame height and width")
    parser.add_argument(
        "--camera", default=None, help="camera id or name (default: 0; the quadruped: the labelling page's, y)"
    )
    parser.add_argument("--seed", type=int, default=0, help="reset key")
    parser.add_argument(
        "--compile-cache",
        metavar="DIR",
        default=None,
        help="the persistent compilation cache's directory (default: as python -m rebel_jax.train's)",
    )
    parser.add_argument("--no-compile-cache", action="store_true", help="no persistent compilation cache")
    args = parser.parse_args(argv)
    try:
        compile_cache.configure(args.compile_cache, args.no_compile_cache)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE) from None
    trainer, step, params = load_policy(args.run_dir, args.column)
    policy = functools.partial(trainer.mean_action, params)
    env = trainer.env
    if not hasattr(env, "mj_model"):
        raise ValueError(f"task {trainer.cfg.env.task!r} has no MuJoCo model to render")
    camera = int(args.camera) if args.camera and args.camera.isdigit() else args.camera
    out = args.out or args.run_dir / "policy.gif"
    steps = args.steps or env.episode_length
    total = policy_video(env, policy, jax.random.PRNGKey(args.seed), out, steps, args.size, camera)
    print(f"{out}: checkpoint {step}, column {args.column}, {steps} steps, return {total:.1f}")
    return out


if __name__ == "__main__":
    main()
