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

import importlib.metadata
import importlib.util
import os
import pathlib
import pkgutil
import sys

import jax

from rebel_jax.config import ConfigError
from rebel_jax.run import compile_cache, rundir
from rebel_jax.run.cli_args import (  # noqa: F401 - re-exported: the command line's parts, as callers import them
    MAX_STEPS,
    Args,
    check_devices,
    collector_paused,
    default_preset,
    engine_note,
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
    report,
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
from rebel_jax.run.human import HumanError
from rebel_jax.run.loop import (  # noqa: F401 - re-exported: the run's parts, as callers import them
    EXIT_DIVERGED,
    Run,
    _compiled_beside_kernels,
    _final_evaluation,
    _restore,
    column_keys,
    initial_state,
)
from rebel_jax.train import compiled, placement, seed_keys  # noqa: F401 - re-exported

EXIT_USAGE = rundir.EXIT_USAGE
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


def run(args: Args, run_dir: pathlib.Path, command: str, resuming: bool | None = None) -> dict:
    """Trains ``args.config`` on ``args.seeds`` seeds in ``run_dir`` (see :func:`prepare_run_dir`): one
    :class:`rebel_jax.run.loop.Run` trains and saves, then process 0 prints what it returns (:func:`report`).

    With several processes (``--distributed``) every process calls it; process 0 alone writes the run's files
    and prints.

    Args:
      resuming: whether ``run_dir`` holds a run to resume; default ``--resume`` and a saved
        ``config.json`` (with several processes, :func:`main` decides on process 0 and tells all).

    Returns:
      ``final.json``'s content, or ``{"stopped_at_round": r}`` after ``--time-limit``.

    Raises:
      SystemExit: with :data:`EXIT_DIVERGED` if a seed diverged and ``--on-divergence stop``.
    """
    with Run(args, run_dir, command, resuming) as loop:
        stopped = loop.rounds()
        if stopped is not None:
            return stopped
        result, files = loop.finish()
    if placement.is_primary():
        report(args, run_dir, result, files, loop.final, loop.random)
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
                    if note := engine_note(args, jax.default_backend()):
                        print(note, file=sys.stderr)
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
