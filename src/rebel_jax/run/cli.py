"""``python -m rebel_jax.train``: the host loop over jitted rounds, and its command line.

    python -m rebel_jax.train sac --preset paper --task walker_walk --seeds 5
    python -m rebel_jax.train pebble --preset paper --feedback.labels 100 --teacher noisy

The method comes first; ``--preset`` (``paper``, ``tiny``, ``demo``, the last ``make train``'s, or SURF's pixel
protocols ``surf_pixels_walker`` and ``surf_pixels_cheetah``, the defaults on those pixel tasks) picks the defaults,
``--obs pixels`` runs the task's pixel version (``walker_walk`` -> ``walker_walk_pixels``) and
``--teacher`` (a B-Pref teacher: oracle, noisy, mistake, skip, equal, myopic) the teacher; every
other flag overrides one field of :class:`rebel_jax.config.Config` (``METHOD --help`` lists those that apply, with
their docs; :mod:`rebel_jax.run.cli_args`).

A finished run evaluates its final policy and uniform random actions on the same episodes, in one batch
(``final.json``), draws ``learning_curve.png`` (:mod:`rebel_jax.run.plots`) and ``eval.gif``, and
prints a table per column: both returns, the labels used and the learned reward's correlation
with the true one (:func:`summary_table`).

A run directory holds one run: a new run refuses a directory that holds one (``--resume``
continues it, ``--overwrite`` replaces it), and one process at a time (a lock, ``RUN_DIR/.lock``).
``--resume`` refuses a configuration that differs from the saved one, except a larger
``--total-steps``, which extends the run, and a directory whose run it cannot continue as it is
(``config.json`` or ``meta.json`` missing or unreadable, a run file it cannot read or write, a
``metrics.jsonl`` without the checkpointed rounds). Exit status: 0 done (or stopped by
``--time-limit``), 2 a bad flag or run directory (nothing written), 3 a seed diverged (see
``--on-divergence``), 4 an I/O failure during the run (disk full, a checkpoint that could not be
saved: the last complete one is kept; free space, then ``--resume``), 130 Ctrl-C (continue with ``--resume``).

``--teacher human`` asks a person on a web page between rounds, ``--teacher replay`` takes a
human run's answers from its ``labels.jsonl`` (:mod:`rebel_jax.run.human`).
"""

from __future__ import annotations

import concurrent.futures
import functools
import importlib.metadata
import importlib.util
import json
import math
import os
import pathlib
import pkgutil
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding

from rebel_jax import api
from rebel_jax.config import ConfigError
from rebel_jax.preference import teachers
from rebel_jax.run import compile_cache, rundir
from rebel_jax.run.checkpoint import Checkpointer, CheckpointMismatch
from rebel_jax.run.cli_args import (  # noqa: F401 - re-exported: the command line's parts, as callers import them
    MAX_STEPS,
    Args,
    check_devices,
    collector_paused,
    default_preset,
    feedback_sessions,
    observed_task,
    parse,
    swept_knob,
    usage_error,
)
from rebel_jax.run.cli_outputs import (  # noqa: F401 - re-exported
    SUMMARY_METRICS,
    _eval_clip,
    _final_result,
    _learning_curve,
    last_logged,
    method_metrics,
    sample_std,
    summary_table,
)
from rebel_jax.run.cli_rundir import (  # noqa: F401 - re-exported
    RUN_FILES,
    _git_commit,
    _record_resume,
    _write_meta,
    command_line,
    device_columns,
    flatten,
    keep_rounds_before,
    prepare_run_dir,
    resume_changes,
)
from rebel_jax.run.human import HostTeacher, HumanError
from rebel_jax.run.logging import RunLogger, write_json
from rebel_jax.train import compiled, grow_replay, placement, replay_rows, seed_keys

EXIT_USAGE = rundir.EXIT_USAGE
EXIT_DIVERGED = 3
STATE_FLAGS = {
    "buffer": "--buffer-capacity (0: --total-steps)",
    "agent": "--sac.hidden / --sac.depth (pixels: --drqv2.hidden, --drqv2.feature-dim)",
    "reward": "--reward.hidden, --reward.label-capacity (pixels: --pixel-reward.*)",
    "env": "--num-envs / --eval-episodes",
    "eval_trajectory": "--rebel.horizon / --rebel.episodes",
}
"""The flags that drive the size of each part of the run's state (for ``rundir.check_memory``)."""
NO_CPU_DEADLOCK = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
"""jaxlib 0.10.2's CPU runtime at times deadlocks (every thread idle in ``device_get``) unless
this scheduler is off; the CLI sets it on CPU before the backend starts (as tests/conftest.py)."""


# -- before the backend starts -------------------------------------------------------------
def _accelerator_plugins() -> list[str]:
    """Installed JAX accelerator plugins (as JAX discovers them), and libtpu."""
    names = [entry.value for entry in importlib.metadata.entry_points(group="jax_plugins")]
    try:
        import jax_plugins

        names += [module.name for module in pkgutil.iter_modules(jax_plugins.__path__)]
    except ImportError:
        pass
    if importlib.util.find_spec("libtpu") is not None:
        names.append("libtpu")
    return names


def runs_on_cpu(environ=os.environ) -> bool:
    """Whether JAX will run on the CPU: ``JAX_PLATFORMS`` names it first, or no accelerator plugin is installed."""
    platforms = environ.get("JAX_PLATFORMS") or getattr(jax.config, "jax_platforms", None) or ""
    if platforms.strip():
        return platforms.split(",")[0].strip() == "cpu"
    return not _accelerator_plugins()


def avoid_cpu_deadlock(environ=os.environ) -> None:
    """Adds :data:`NO_CPU_DEADLOCK` to ``XLA_FLAGS`` on CPU (unless the scheduler flag is set already).

    XLA reads ``XLA_FLAGS`` when the backend starts, so this must run before any computation.
    """
    flags = environ.get("XLA_FLAGS", "")
    if not runs_on_cpu(environ) or "xla_cpu_enable_concurrency_optimized_scheduler" in flags:
        return
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        print(f"warning: the JAX backend started before {NO_CPU_DEADLOCK} could be set", file=sys.stderr)
    environ["XLA_FLAGS"] = f"{flags} {NO_CPU_DEADLOCK}".strip()


def _restore(run_dir: pathlib.Path, ckpt: Checkpointer, state, sharding):
    """(first round to run, state) from the newest readable checkpoint; (0, ``state``) if there is none.

    A checkpoint of a run now extended by a larger ``--total-steps`` holds a smaller replay buffer:
    it is restored as saved (each buffer leaf's rows read from the checkpoint) and then grown.
    """
    rows = replay_rows(state)  # (seeds, rows, envs)
    leaves = jax.tree.leaves(state)
    reward_leaf = next(i for i, x in enumerate(leaves) if x is state.buffer.true_reward)
    first = next(i for i, x in enumerate(leaves) if x is jax.tree.leaves(state.buffer)[0])  # the buffer's leaves

    def adapt(like, shapes):
        saved = shapes[str(reward_leaf)]  # another leaf where other code saved another state: the check refuses it
        if len(saved) < 2 or saved[1] == rows:
            return like

        def saved_rows(i, x):  # x[:, :n] where the saved leaf has n < x.shape[1] rows (any other difference is
            saved = shapes.get(str(first + i), x.shape)  # left for the checkpoint's shape check to refuse)
            return x[:, : saved[1]] if x.ndim >= 2 and len(saved) == x.ndim and saved[1] < x.shape[1] else x

        buffer, treedef = jax.tree.flatten(like.buffer)
        return like.replace(buffer=jax.tree.unflatten(treedef, [saved_rows(i, x) for i, x in enumerate(buffer)]))

    finished = (run_dir / "final.json").exists()
    if ckpt.latest() is None and not finished:
        print(f"note: --resume: no checkpoint in {run_dir} yet; starting the run from scratch", file=sys.stderr)
        return 0, state
    try:
        start, restored = ckpt.restore(state, adapt=adapt)
    except CheckpointMismatch as err:  # Other code wrote it: refuse, and keep the run's logs as they are.
        commit = json.loads((run_dir / "meta.json").read_text()).get("git_commit", "unknown")
        raise ConfigError(
            f"--resume: {err}. It was written by other code (meta.json: git_commit {commit}); resume it "
            "with that code, or start a new --run-dir"
        ) from err
    except FileNotFoundError as err:
        if finished:  # Starting over would replace a finished run's results.
            raise ConfigError(
                f"--resume: {err}, and {run_dir} holds a finished run (final.json): it would start over and replace "
                "it; use another --run-dir, or --overwrite to replace it"
            ) from None
        print(f"note: --resume: {err}; starting the run from scratch", file=sys.stderr)
        return 0, state
    if replay_rows(restored) != rows:
        restored = placement.shard_seeds(grow_replay(restored, state), sharding)
    return start, restored


def _slow_checkpoint_note(r: int, saving: float, seconds: float, every: int) -> str:
    """Said once per run when a checkpoint takes longer than the round it follows (e.g. a large replay on a GPU)."""
    suggested = every * math.ceil(4 * saving / max(seconds, 1e-9))  # saves then take at most a fifth of the time
    return (
        f"note: round {r}'s checkpoint took {saving:.1f} s, longer than the round ({seconds:.1f} s): "
        f"--checkpoint-every {suggested} would spend at most a fifth of the time saving "
        f"(a kill then loses up to {suggested} rounds; 0 saves none)"
    )


def column_keys(args: Args, sharding: NamedSharding | None = None, total: int | None = None) -> jax.Array:
    """One key per column: the seed keys tiled over the grid (each lambda's and teacher's seed i uses key i), then
    the last one repeated up to ``total`` columns (``placement.padded_columns``; default ``args.columns``)."""
    keys = jnp.tile(seed_keys(args.config.train.seed, args.seeds), (args.columns // args.seeds, 1))
    return placement.shard_seeds(placement.pad_columns(keys, total or args.columns), sharding)


def initial_state(args: Args, init: Callable, keys: jax.Array, sharding: NamedSharding | None = None, trainer=None):
    """The run's first state: ``init`` (of ``train.compiled``) of the :func:`column_keys`, with each column's
    lambda and teacher knobs set by the trainer (``Trainer.with_knobs``; ``api.make_trainer(args.config)`` unless
    given); padding columns (beyond ``args.columns``) take the last column's."""
    trainer = trainer or api.make_trainer(args.config)
    grid = args.grid()
    grid += grid[-1:] * (keys.shape[0] - len(grid))
    lams = [lam for lam, _ in grid] if swept_knob(args.config) else None
    teacher_cfgs = [teachers.PRESETS[t] for _, t in grid] if args.teacher_grid else None
    return placement.shard_seeds(trainer.with_knobs(init(keys), lams, teacher_cfgs), sharding)


def _compiled_beside_kernels(trainer, round_fn: Callable, shapes, one_device: bool) -> tuple[Callable, float]:
    """With MuJoCo Warp's step, its kernels built in a thread (``DMCEnv.build_warp_kernels``) while XLA compiles
    the round ahead of its first call (on one device; several devices compile theirs at the first call), and the
    seconds that took; ``round_fn`` and 0 with the JAX step. The build ends here, before any program steps the
    environments (the cheetah's reset does)."""
    env = trainer.env
    while not hasattr(env, "build_warp_kernels") and hasattr(env, "env"):  # a PixelEnv holds its DMCEnv
        env = env.env
    if getattr(env, "impl", "jax") != "warp":
        return round_fn, 0.0
    if placement.is_primary():
        print("building MuJoCo Warp's kernels while the round program compiles", flush=True)
    started = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="warp_kernels") as pool:
        build = pool.submit(env.build_warp_kernels)
        if one_device:
            round_fn = round_fn.lower(shapes, jax.ShapeDtypeStruct((), jnp.int32)).compile()
        failed = build.exception()  # waits for the build
        if failed is not None:  # the first step builds them instead
            print(f"note: MuJoCo Warp's kernels were not built ahead: {failed}", file=sys.stderr)
    return round_fn, time.perf_counter() - started


FINAL_FLAGS = (False, True)
"""The final evaluation: the policy's and random actions' episodes on the same initial states, in one batch."""


def _final_evaluation(evaluate: Callable, trainer, shapes, keys: jax.Array) -> Callable:
    """The final evaluation as a function of the policy. On one device its program is compiled here: called while
    the first round runs on an accelerator (dispatched, not yet waited for), the compile is hidden behind the
    round instead of adding to the job's end (on a GPU, seconds). Several devices compile at the call."""
    if not hasattr(evaluate, "compile_ahead"):
        return lambda policy: evaluate(policy, keys, FINAL_FLAGS)
    program = evaluate.compile_ahead(jax.eval_shape(trainer.policy_params, shapes), keys, FINAL_FLAGS)
    return lambda policy: program(policy, keys)


def run(args: Args, run_dir: pathlib.Path, command: str, resuming: bool | None = None) -> dict:
    """Trains ``args.config`` on ``args.seeds`` seeds in ``run_dir`` (see :func:`prepare_run_dir`).

    With several processes (``--distributed``) every process calls it: each runs its devices'
    seeds and saves its part of each checkpoint; process 0 alone writes ``config.json``,
    ``meta.json``, ``metrics.jsonl``, ``final.json``, TensorBoard files and the clip, and prints.

    Args:
      resuming: whether ``run_dir`` holds a run to resume; default ``--resume`` and a saved
        ``config.json`` (with several processes, :func:`main` decides on process 0 and tells all).

    Returns:
      ``final.json``'s content, or ``{"stopped_at_round": r}`` after ``--time-limit``.

    Raises:
      SystemExit: with :data:`EXIT_DIVERGED` if a seed diverged and ``--on-divergence stop``.
    """
    cfg = args.config
    primary = placement.is_primary()
    if resuming is None:
        resuming = args.resume and (run_dir / "config.json").exists()
    total = device_columns(run_dir, args, jax.device_count(), resuming)  # args.columns, padded for the devices
    trainer = api.make_trainer(cfg, host_teacher=bool(args.host_teacher), columns=-(-total // jax.device_count()))
    # The human teacher's page and renderer start first: a machine that cannot render fails now.
    host = HostTeacher(trainer, args.host_teacher, run_dir, args.human, args.resume) if args.host_teacher else None
    sharding = placement.seed_sharding(total)
    init, round_fn, evaluate = compiled(trainer, sharding)
    keys = column_keys(args, sharding, total)
    shapes = jax.eval_shape(init, keys)  # nothing allocated yet
    devices = sharding.mesh.devices.ravel().tolist() if sharding else jax.devices()[:1]
    rundir.check_memory(rundir.tree_bytes(shapes), devices, STATE_FLAGS, memory_of=jax.local_devices()[0])
    round_fn, ahead = _compiled_beside_kernels(trainer, round_fn, shapes, sharding is None)
    state = initial_state(args, init, keys, sharding, trainer)
    grid = args.grid()
    use_ckpt = args.checkpoint_every or args.resume or args.time_limit
    checksums = not resuming or bool(json.loads((run_dir / "meta.json").read_text()).get(rundir.CHECKSUMS_FIELD))
    ckpt = Checkpointer(run_dir / "checkpoints", require_checksums=checksums) if use_ckpt else None
    start = 0
    if resuming:
        start, state = _restore(run_dir, ckpt, state, sharding)
        if primary:
            keep_rounds_before(run_dir / "metrics.jsonl", start)
            _record_resume(run_dir, args, command, start)
    elif primary:
        if args.resume:
            print(f"note: --resume: no run in {run_dir} yet; starting the run from scratch", file=sys.stderr)
        keep_rounds_before(run_dir / "metrics.jsonl", 0)
        _write_meta(run_dir, args, command, total)
    names = args.column_names()

    def real_columns(tree):  # the run's columns, without the padding
        return jax.tree.map(lambda x: x[: args.columns], tree)

    per_round = cfg.train.steps_per_round
    logger = None
    if primary:
        logger = RunLogger(run_dir, cfg.train.total_steps, start * per_round, args.progress, args.tensorboard, names)
    if primary and not args.progress and start < cfg.train.num_rounds:  # A plain log says what its first wait is.
        print(
            f"{start * per_round:,}/{cfg.train.total_steps:,} steps: "
            f"{'' if ahead else 'compiling the round program, then '}round {start + 1} of {cfg.train.num_rounds}"
            f"{'' if ahead else ' (minutes for a large preset on a CPU)'}",
            flush=True,
        )
    final_evaluation = functools.cache(lambda: _final_evaluation(evaluate, trainer, shapes, keys))
    started, slowest = time.perf_counter() - ahead, 0.0  # --time-limit counts the compile ahead too
    ever_diverged = np.zeros(args.columns, bool)
    slow_save_noted = False
    try:
        for r in range(start, cfg.train.num_rounds):
            # Process 0's clock decides for all (every process must run the same rounds).
            out_of_time = time.perf_counter() - started + 1.2 * slowest > args.time_limit
            if args.time_limit and r > start and placement.from_primary(int(out_of_time)):
                if ckpt is not None and ckpt.latest() != r:
                    ckpt.save(r, state)
                if primary:
                    print(f"--time-limit {args.time_limit:g} s: stopped after round {r - 1}; continue with --resume")
                return {"stopped_at_round": r}
            session = {}
            if host is not None:  # The human or replay teacher's session, between rounds.
                state, session = host.before_round(state, r)
            t0 = time.perf_counter()
            state, metrics = round_fn(state, jnp.int32(r))
            if r == start:
                final_evaluation()  # compiled while the round runs
            metrics = {**real_columns(placement.to_host(metrics)), **session}
            seconds = time.perf_counter() - t0 + (ahead if r == start else 0.0)  # the first round with its compile
            slowest = max(slowest, seconds) if r > start else 0.0
            env_steps = (r + 1) * per_round
            if env_steps % cfg.train.eval_every and r + 1 < cfg.train.num_rounds:
                metrics.pop("eval_return")
                metrics.pop("eval_success", None)
            diverged = np.asarray(metrics["diverged"], float).reshape(-1) > 0
            extra = {"round": r, "seconds": seconds, "env_steps_per_s": per_round * args.columns / seconds}
            if logger is not None:
                logger.write(env_steps, metrics, extra)
            if diverged.any():
                which = ", ".join(names[i] for i in np.flatnonzero(diverged & ~ever_diverged))
                ever_diverged |= diverged
                if args.on_divergence == "stop":
                    nan = np.full(args.columns, np.nan)
                    result = {**_final_result(nan, nan, ever_diverged, names), "round": r}
                    if primary:
                        write_json(run_dir / "final.json", result)
                    last = ckpt.latest() if ckpt is not None else None
                    kept = f"its checkpoints resume at round {last}" if last is not None else "no checkpoint"
                    print(
                        f"error: round {r}: {', '.join(result['diverged'])} diverged (NaN or inf in losses, "
                        f"parameters or returns); the run stopped ({kept}). "
                        "--on-divergence continue runs the other seeds on.",
                        file=sys.stderr,
                    )
                    raise SystemExit(EXIT_DIVERGED)
                if which:
                    print(f"warning: round {r}: {which} diverged; going on (--on-divergence continue)", file=sys.stderr)
            if args.checkpoint_every and ((r + 1) % args.checkpoint_every == 0 or r + 1 == cfg.train.num_rounds):
                t0 = time.perf_counter()  # The wait for the previous save and this one's copy to the host; its
                ckpt.save(r + 1, state, wait=r + 1 == cfg.train.num_rounds)  # files are written during the next round.
                saving = time.perf_counter() - t0
                if primary and not slow_save_noted and saving > seconds and r + 1 < cfg.train.num_rounds:
                    slow_save_noted = True
                    print(_slow_checkpoint_note(r, saving, seconds, args.checkpoint_every), file=sys.stderr)
        policy = trainer.policy_params(state)
        final, random = real_columns(np.asarray(placement.to_host(final_evaluation()(policy)))).T
        result = _final_result(final, random, ever_diverged, names)
        files = []
        if primary:
            own = method_metrics(run_dir, args.columns)
            if own:  # the method's own metrics, their last logged values
                result["method_metrics"] = own
            write_json(run_dir / "final.json", result)
            if host is not None:
                host.finish(result)  # The labelling page says the run has finished, and where its files are.
            files.append(_learning_curve(args, run_dir, random))
        if args.video_steps > 0 and hasattr(trainer.env, "mj_model"):
            policy = placement.to_host(policy)  # Every process: a collective with several.
            if primary:
                files.append(_eval_clip(args, trainer, policy, run_dir))
    finally:
        rundir.close_all((ckpt, logger, host))  # each one, even if another fails: orbax's threads end
    if not primary:
        return result
    print(
        f"\n{cfg.algo} on {cfg.env.task}: evaluation returns ({cfg.train.eval_episodes} episodes of "
        f"{cfg.env.episode_length} steps per seed, the same initial states for the random policy)"
    )
    print(summary_table(names, random, final, last_logged(run_dir, args.columns)))
    for path in files:
        if path is not None:
            print(f"wrote {path}")
    for i in range(0, args.columns, args.seeds):
        part = final[i : i + args.seeds]
        lam, teacher = grid[i]
        which = ([f"lambda {lam:g}"] if swept_knob(cfg) else []) + ([f"teacher {teacher}"] if teacher else [])
        which = f" ({', '.join(which)})" if which else ""
        spread = f" +- {sample_std(part):.1f} (sample std)" if part.size > 1 else ""
        print(f"final evaluation return over {args.seeds} seed(s){which}: {part.mean():.1f}{spread}")
    if ever_diverged.any():
        print(f"warning: diverged during the run: {', '.join(result['diverged'])}", file=sys.stderr)
    print(f"run directory: {run_dir}")
    return result


def main(argv: list[str] | None = None) -> dict:
    """The command line: parse and check everything, then prepare the run directory, then train.

    The persistent compilation cache is set up first (:func:`rebel_jax.run.compile_cache.configure`): in JAX's
    configuration, for the whole process.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    avoid_cpu_deadlock()
    args = parse(argv)
    previous = rundir.terminate_as_interrupt()
    try:
        return _checked_main(argv, args)
    finally:
        rundir.restore_sigterm(previous)


def _checked_main(argv: list[str], args) -> dict:
    """:func:`main` once the flags are parsed: the compilation cache, the run directory, the run."""
    try:
        compile_cache.configure(args.compile_cache, args.no_compile_cache)
    except ConfigError as err:
        raise usage_error(err) from err
    if args.distributed:
        try:
            placement.initialize()
        except ValueError as err:
            raise usage_error(err) from err
    # Process 0 checks, locks and prepares the run directory, then tells the others what it found.
    status, resuming = 0, 0
    run_dir = None if args.run_dir is None else pathlib.Path(args.run_dir)  # Set with --distributed.
    with rundir.RunLock() as lock:
        try:
            if placement.is_primary():
                try:
                    check_devices(args, jax.device_count())
                    if args.host_teacher == "human":  # the labelling page's address, before anything is written
                        rundir.check_listen_address(args.human.host, args.human.port)
                    run_dir = prepare_run_dir(args, lock)
                    resuming = int(args.resume and (run_dir / "config.json").exists())
                except ConfigError as err:
                    print(f"error: {err}", file=sys.stderr)
                    status = EXIT_USAGE
            status, resuming = placement.from_primary((status, resuming))
            if status:
                raise SystemExit(status)
            result = run(args, run_dir, command_line(argv), bool(resuming))
            if args.distributed:  # Leave together: process 0 hosts the coordinator the others still watch.
                jax.distributed.shutdown()
            return result
        except (*HumanError, ConfigError) as err:  # No OpenGL for the clips, a checkpoint of other code, ...
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(EXIT_USAGE) from None
        except OSError as err:  # Disk full, a checkpoint that could not be saved, a permission changed meanwhile.
            if placement.is_primary():
                print(rundir.io_error_line(err, run_dir), file=sys.stderr)
            raise SystemExit(rundir.EXIT_IO) from None
        except KeyboardInterrupt as stop:
            terminated = isinstance(stop, rundir.Terminated)
            if placement.is_primary():
                print(rundir.interrupted_line(run_dir, "terminated" if terminated else "interrupted"), file=sys.stderr)
            raise SystemExit(rundir.EXIT_TERMINATED if terminated else rundir.EXIT_INTERRUPTED) from None
