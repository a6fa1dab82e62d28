"""Videos of policy episodes, rendered with the pure-JAX camera (:mod:`rebel_jax.envs.render`).

    python -m rebel_jax.run.video RUN_DIR [--out FILE.gif|FILE.mp4] [--column 0] [--steps 500] [--size 240]

renders a deterministic episode of a saved run's latest checkpoint. Its compiled programs are kept in the
persistent compilation cache of ``python -m rebel_jax.train`` (``--compile-cache DIR``, ``--no-compile-cache``;
:mod:`rebel_jax.run.compile_cache`). GIFs are written with
imageio's Pillow plugin; MP4 needs imageio's ffmpeg plugin (``pip install imageio-ffmpeg``).
``rebel_jax.run.cli`` writes ``eval.gif`` at the end of each run of a MuJoCo task. The tasks the pure-JAX
camera cannot draw (the quadruped: ellipsoids and cylinders; Meta-World's) are drawn by MuJoCo's renderer from the
episode's positions (and a Meta-World task's scenes), as the labelling page's clips are
(:mod:`rebel_jax.run.human.clips`; it needs ``MUJOCO_GL=egl`` or ``osmesa``).
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

from rebel_jax.core.errors import ConfigError
from rebel_jax.envs import render
from rebel_jax.run import compile_cache
from rebel_jax.run.rundir import EXIT_USAGE


def write(path: str | pathlib.Path, frames: np.ndarray, fps: float) -> pathlib.Path:
    """Writes uint8 frames ``(T, H, W, 3)`` as a GIF or MP4 (by the file's suffix), into an existing directory."""
    import imageio.v3 as iio

    path = pathlib.Path(path)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise ValueError(f"frames must be uint8 (T >= 1, H, W, 3); got {frames.dtype} {frames.shape}")
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
) -> tuple[jax.Array, jax.Array | None, jax.Array]:
    """Positions ``(steps + 1, nq)``, scenes ``(steps + 1, k)`` and the total reward of one episode of
    ``policy(obs) -> action``, for a renderer outside JAX. The scenes are what a Meta-World frame needs beyond
    ``qpos`` (``env.scene``), None for a task without them. Jittable (``env``, ``policy`` and ``steps`` static). The
    first row is the reset state."""
    scene = getattr(env, "scene", lambda state: None)
    state = env.reset(key)

    def body(state, _):
        state = env.step(state, policy(state.obs))
        return state, (state.pipeline_state.qpos, scene(state), state.reward)

    _, (qpos, scenes, rewards) = jax.lax.scan(body, state, length=steps)
    first = scene(state)
    scenes = None if first is None else jnp.concatenate([first[None], scenes])
    return jnp.concatenate([state.pipeline_state.qpos[None], qpos]), scenes, rewards.sum()


def is_metaworld(env) -> bool:
    """Whether ``env`` is a Meta-World task, whose frames need its scene (``env.scene``) beside ``qpos``."""
    return hasattr(env, "scene")


def drawable(env) -> bool:
    """Whether videos of ``env`` can be drawn: a MuJoCo task (``mj_model``) or a Meta-World task."""
    return hasattr(env, "mj_model") or is_metaworld(env)


def render_model(env):
    """The MuJoCo model that ``env``'s frames are drawn from (its cameras are those of ``--camera``)."""
    return env.mujoco_model if is_metaworld(env) else env.mj_model


def drawn_by_mujoco(env) -> bool:
    """Whether ``env`` (a state task) has geoms that the pure-JAX camera does not draw, so that its videos are
    drawn by MuJoCo's renderer (every Meta-World task)."""
    if is_metaworld(env):
        return True
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
    labelling page's camera (``rebel_jax.run.human.clips.CAMERAS``; Meta-World's ``corner4``). Raises
    ``rebel_jax.run.human.ClipError`` where MuJoCo's renderer is needed and has no OpenGL context.
    """
    if drawn_by_mujoco(env):
        from rebel_jax.run.human.clips import MetaWorldRenderer, MujocoRenderer

        renderer = (MetaWorldRenderer if is_metaworld(env) else MujocoRenderer)(env.spec.name, size, camera)
        try:
            positions, scenes, total = jax.jit(lambda k: episode_positions(env, policy, k, steps))(key)
            if scenes is None:
                frames = renderer.frames(np.asarray(positions))
            else:
                frames = renderer.frames(np.asarray(positions), np.asarray(scenes))
        finally:
            renderer.close()
    else:
        cam = render.make_camera(env.mj_model, 0 if camera is None else camera, size, size)
        frames, total = jax.jit(lambda k: episode_frames(env, policy, k, steps, cam))(key)
    write(path, np.asarray(frames), fps=1.0 / env.dt)
    return float(total)


FORMATS = (".gif", ".mp4")
MAX_STEPS = 100_000
"""The most agent steps of a clip (100 episodes of dm_control's 1000 steps)."""
MAX_SIZE = 1024
"""The largest frame height and width."""
MAX_FRAME_BYTES = 2**31
"""The most bytes a clip's frames may take in memory (steps x size x size x 3)."""


def check_run_dir(run_dir: pathlib.Path) -> tuple[dict, dict]:
    """(config.json, meta.json) of a run directory that holds a run to render, each a JSON object of regular files
    (a FIFO or a device is refused unread, not waited on).

    Raises:
      ConfigError: one line naming what is missing or wrong.
    """
    from rebel_jax.run import rundir

    if not run_dir.is_dir():
        why = "not a directory" if run_dir.exists() else "it does not exist"
        raise ConfigError(f"RUN_DIR={str(run_dir)!r} is invalid: allowed a run directory ({why})")
    saved = {}
    for name in ("config.json", "meta.json"):
        path = run_dir / name
        if not path.exists():
            raise ConfigError(f"RUN_DIR={str(run_dir)!r} is invalid: it has no {name} (not a run's directory)")
        if not path.is_file():
            raise ConfigError(f"{path} is invalid: allowed a regular file (it is not one)")
        try:
            saved[name] = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise ConfigError(
                f"{path} is unreadable ({type(err).__name__}: {str(err).splitlines()[0][:120]})"
            ) from None
        if not isinstance(saved[name], dict):
            raise ConfigError(f"{path} is invalid: it holds a JSON {type(saved[name]).__name__}, not an object")
    meta = rundir.check_meta(run_dir / "meta.json", what="video")
    if not rundir.saved_steps(run_dir):
        raise ConfigError(f"RUN_DIR={str(run_dir)!r} is invalid: no checkpoint in {run_dir / 'checkpoints'} to render")
    return saved["config.json"], meta


def load_policy(run_dir: pathlib.Path, column: int = 0, before_restore: Callable | None = None):
    """(trainer, checkpoint step, policy parameters) of one column of a run's latest checkpoint; the trainer
    (on a pixel run too) acts with them through ``trainer.mean_action(params, obs)``.

    Only the policy's leaves are read from the checkpoint (not the replay buffer, gigabytes for a pixel run);
    ``before_restore(trainer)``, if given, is called before (the caller's checks that need the task's model).

    Raises:
      ConfigError: a run directory, config, column or checkpoint that cannot be rendered (one line).
    """
    from rebel_jax import api
    from rebel_jax.config import Config, from_dict
    from rebel_jax.run import rundir
    from rebel_jax.run.checkpoint import Checkpointer, CheckpointMismatch
    from rebel_jax.train import seed_keys

    data, meta = check_run_dir(run_dir)
    try:
        cfg = from_dict(Config, data).validate()
    except (TypeError, ValueError) as err:  # ConfigError is a ValueError
        raise ConfigError(f"{run_dir / 'config.json'}: {err}") from None
    columns = int(meta.get("columns", 1))
    if not 0 <= column < columns:
        raise ConfigError(f"column={column} is invalid: allowed 0 to {columns - 1} (the run's columns)")
    trainer = api.make_trainer(cfg)
    if before_restore is not None:
        before_restore(trainer)
    keys = seed_keys(cfg.train.seed, columns)
    like = jax.eval_shape(jax.vmap(trainer.init), keys)
    checksums = bool(meta.get(rundir.CHECKSUMS_FIELD))
    ckpt = Checkpointer(run_dir / "checkpoints", require_checksums=checksums, set_aside=False)  # the run unchanged
    try:
        step, params = ckpt.restore_leaves(like, trainer.policy_params)
    except (FileNotFoundError, CheckpointMismatch) as err:
        raise ConfigError(f"{err} (python -m rebel_jax.run.video renders a run's newest readable checkpoint)") from None
    finally:
        ckpt.close()
    return trainer, step, jax.tree.map(lambda x: jnp.asarray(x[column]), params)


class _Parser(argparse.ArgumentParser):
    """A bad argument is one line and exit status 2 (:class:`ConfigError`), as the trainer's are."""

    def error(self, message: str):
        raise ConfigError(message)


def _camera(env, camera: str | None) -> int | str | None:
    """``--camera`` as an id or a name of ``env``'s model (raises ConfigError for one it does not have)."""
    if camera is None:
        return None
    import mujoco

    model = render_model(env)
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
    if camera.isdigit() and int(camera) < max(model.ncam, 1):
        return int(camera)
    if camera in names:
        return camera
    allowed = f"0 to {model.ncam - 1} or one of {names}" if model.ncam else "0 (the model has no cameras)"
    raise ConfigError(f"camera={camera!r} is invalid: allowed {allowed}")


def check_frames(steps: int, size: int) -> None:
    """Refuses a clip whose frames would take more than :data:`MAX_FRAME_BYTES` (raises ConfigError)."""
    frame_bytes = (steps + 1) * size * size * 3
    if frame_bytes > MAX_FRAME_BYTES:
        raise ConfigError(
            f"steps={steps}, size={size} is invalid: the clip's frames would take {frame_bytes / 1e9:.1f} GB; allowed"
            f" at most {MAX_FRAME_BYTES / 1e9:.1f} GB (fewer --steps or a smaller --size)"
        )


def check_options(args: argparse.Namespace) -> pathlib.Path:
    """The options of :func:`main` in their ranges, and the file to write (raises ConfigError)."""
    from rebel_jax.core.ranges import Range, check_value

    check_value("column", args.column, int, Range())
    check_value("seed", args.seed, int, Range())
    check_value("size", args.size, int, Range(16, MAX_SIZE))
    if args.steps is not None:
        check_value("steps", args.steps, int, Range(1, MAX_STEPS))
    out = args.out or args.run_dir / "policy.gif"
    if out.suffix.lower() not in FORMATS:
        raise ConfigError(f"out={str(out)!r} is invalid: allowed a file ending in {' or '.join(FORMATS)}")
    if not out.parent.is_dir():
        raise ConfigError(f"out={str(out)!r} is invalid: its directory {out.parent} does not exist (create it first)")
    if out.exists() and not out.is_file():
        raise ConfigError(f"out={str(out)!r} is invalid: it exists and is not a regular file")
    return out


def main(argv: list[str] | None = None) -> pathlib.Path:
    """``python -m rebel_jax.run.video``: every input checked first; a bad one is one line and exit status 2."""
    try:
        return _main(argv)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE) from None


def _main(argv: list[str] | None) -> pathlib.Path:
    parser = _Parser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=pathlib.Path)
    parser.add_argument("--out", type=pathlib.Path, default=None, help="GIF or MP4; default RUN_DIR/policy.gif")
    parser.add_argument("--column", type=int, default=0, help="which vmapped seed column")
    parser.add_argument("--steps", type=int, default=None, help=f"agent steps, 1 to {MAX_STEPS} (default: one episode)")
    parser.add_argument("--size", type=int, default=240, help=f"frame height and width, 16 to {MAX_SIZE}")
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
    compile_cache.configure(args.compile_cache, args.no_compile_cache)
    check_run_dir(args.run_dir)
    out = check_options(args)
    chosen = {}

    def check_model(trainer) -> None:  # before the checkpoint is read
        if not drawable(trainer.env):
            raise ConfigError(f"the run's task {trainer.cfg.env.task!r} has no MuJoCo model to render")
        chosen["camera"] = _camera(trainer.env, args.camera)
        chosen["steps"] = args.steps or trainer.env.episode_length
        check_frames(chosen["steps"], args.size)

    trainer, step, params = load_policy(args.run_dir, args.column, check_model)
    policy = functools.partial(trainer.mean_action, params)
    env, camera, steps = trainer.env, chosen["camera"], chosen["steps"]
    total = policy_video(env, policy, jax.random.PRNGKey(args.seed), out, steps, args.size, camera)
    print(f"{out}: checkpoint {step}, column {args.column}, {steps} steps, return {total:.1f}")
    return out


if __name__ == "__main__":
    main()
