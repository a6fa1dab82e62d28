"""``python -m rebel_jax.train``: the host loop over jitted rounds, and its command line.

    python -m rebel_jax.train --preset paper --algo sac --task walker_walk --seeds 5
    python -m rebel_jax.train --preset paper --algo pebble --labels 100 --teacher noisy

``--preset`` (``paper``, ``tiny``, ``demo``, the last ``make train``'s, or SURF's pixel protocols
``surf_pixels_walker`` and ``surf_pixels_cheetah``, the defaults on those pixel tasks) picks the defaults,
``--obs pixels`` runs the task's pixel version (``walker_walk`` -> ``walker_walk_pixels``) and
``--teacher`` (a B-Pref teacher: oracle, noisy, mistake, skip, equal, myopic) the teacher; every
other flag overrides one field of :class:`rebel_jax.config.Config` (``--help`` lists them with
their docs).

A finished run evaluates its final policy and uniform random actions on the same episodes
(``final.json``), draws ``learning_curve.png`` (:mod:`rebel_jax.plots`) and ``eval.gif``, and
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
human run's answers from its ``labels.jsonl`` (:mod:`rebel_jax.human`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import functools
import gc
import importlib.metadata
import importlib.util
import json
import math
import os
import pathlib
import pkgutil
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Annotated, Literal

import jax
import jax.numpy as jnp
import numpy as np
import tyro
from jax.sharding import NamedSharding

from rebel_jax import api, compile_cache, plots, rundir, sweep, teachers, video
from rebel_jax.budget import session_due
from rebel_jax.checkpoint import Checkpointer, CheckpointMismatch
from rebel_jax.config import PRESETS, Config, ConfigError
from rebel_jax.envs.pixels import SUFFIX as PIXEL_SUFFIX
from rebel_jax.human import HOST_TEACHERS, HostTeacher, HumanError, HumanOptions, is_loopback, redact_token
from rebel_jax.logging import RunLogger, write_json
from rebel_jax.pixel_feedback import check_config
from rebel_jax.train import Trainer, compiled, grow_replay, replay_rows, seed_keys

RUN_FILES = (
    "config.json",
    "meta.json",
    "metrics.jsonl",
    "final.json",
    "checkpoints",
    "checkpoints_damaged",
    "tb",
    "learning_curve.png",
    "eval.gif",
)
"""What a run writes in its directory (other files there, such as a caller's log, are left alone)."""
EXIT_USAGE = rundir.EXIT_USAGE
EXIT_DIVERGED = 3
STATE_FLAGS = {
    "buffer": "--buffer-capacity (0: --total-steps)",
    "agent": "--hidden / --depth (pixels: --drqv2.hidden, --drqv2.feature-dim)",
    "reward": "--reward.hidden, --reward.label-capacity (pixels: --pixel-reward.*)",
    "env": "--num-envs / --eval-episodes",
    "eval_trajectory": "--rebel.horizon / --rebel.episodes",
}
"""The flags that drive the size of each part of the run's state (for ``rundir.check_memory``)."""
MAX_STEPS = 2**31 - 1
"""The largest ``--total-steps`` and ``--buffer-capacity``: the rounds count steps and index the buffer in int32."""
OBS = ("state", "pixels")
"""``--obs``: what the agent observes; ``pixels`` runs the task's pixel version (``<task>_pixels``)."""
NO_CPU_DEADLOCK = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
"""jaxlib 0.10.2's CPU runtime at times deadlocks (every thread idle in ``device_get``) unless
this scheduler is off; the CLI sets it on CPU before the backend starts (as tests/conftest.py)."""


@dataclasses.dataclass(frozen=True)
class Args:
    """Train one configuration on several seeds."""

    config: Annotated[Config, tyro.conf.arg(name="")]
    seeds: int = 1
    """Seeds run together (vmapped; sharded over all devices when there are several)."""
    run_dir: str | None = None
    """The run's directory; default ``runs/<algo>_<task>_<time>``. It must not hold another run
    (see ``--resume`` and ``--overwrite``)."""
    resume: bool = False
    """Continue the run in ``run_dir`` from its latest readable checkpoint (from scratch, with a
    notice, if it has none). The configuration must equal the saved one, except a larger
    ``--total-steps``, which extends the run."""
    overwrite: bool = False
    """Replace the run in ``run_dir``: its config, logs, checkpoints and TensorBoard files are deleted first."""
    checkpoint_every: int = 1
    """Rounds between checkpoints; 0 disables them (``--resume`` still reads existing ones). A save is
    synchronous: the first one that takes longer than its round (a large replay on a GPU) prints a note
    with an interval that keeps saving under a fifth of the time."""
    time_limit: float = 0.0
    """Seconds of wall time: stop after the last round that ends within it (checkpointing that
    round) and continue later with ``--resume``. For calls with a wall-clock limit; 0: none."""
    on_divergence: Literal["stop", "continue"] = "stop"
    """When a seed's losses, parameters or returns become NaN or infinite: ``stop`` the run after
    that round (exit status 3, the round is not checkpointed) or ``continue`` with the other seeds."""
    progress: bool = True
    """Show a progress bar."""
    tensorboard: bool = True
    """Write TensorBoard event files."""
    compile_cache: str | None = None
    """The persistent compilation cache's directory: a later run that compiles the same programs loads them from
    there. Default: ``JAX_COMPILATION_CACHE_DIR`` where set, else ``$REBEL_JAX_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/rebel_jax/jax``, else ``~/.cache/rebel_jax/jax`` (:mod:`rebel_jax.compile_cache`)."""
    no_compile_cache: Annotated[bool, tyro.conf.FlagCreatePairsOff] = False
    """No persistent compilation cache: compile every program in this process."""
    distributed: bool = False
    """Several processes (hosts, or one per GPU) run this same command: each calls
    ``jax.distributed.initialize`` first, with ``JAX_COORDINATOR_ADDRESS`` (host:port of process 0),
    ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID`` from the environment, or what JAX detects (SLURM).
    The seeds are sharded over every process's devices; process 0 writes the logs, all write the
    checkpoints (orbax), so ``--run-dir`` must be given and be on a file system they share."""
    lam_grid: tuple[float, ...] = ()
    """``--algo rebel`` only: run every seed with each of these lambdas in one vmapped program
    (columns are lambda-major: lambda 0 seed 0, lambda 0 seed 1, ...; seed i uses the same key
    for every lambda). Empty: ``rebel.lam`` only."""

    video_steps: int = 250
    """Agent steps of the evaluation clip written at the end of the run (``eval.gif``: the first
    column's deterministic policy, 120x120, camera 0; the quadruped's by MuJoCo's renderer, skipped without OpenGL);
    0: none. Only for MuJoCo tasks (state or pixel), and not
    under ``--time-limit`` (``python -m rebel_jax.video RUN_DIR`` renders one later)."""

    teacher_grid: tuple[str, ...] = ()
    """Preference methods only: run every seed (and lambda) with each of these B-Pref teachers
    in one vmapped program (columns: lambda, then teacher, then seed). Empty: ``--teacher``."""
    human: HumanOptions = HumanOptions()
    """``--teacher human`` (the labelling page) and ``--teacher replay`` (its saved answers)."""
    host_teacher: tyro.conf.Suppress[str] = ""
    """``human`` or ``replay`` (set from ``--teacher``), or empty for a scripted teacher."""

    @property
    def lams(self) -> tuple[float, ...]:
        return self.lam_grid or (self.config.rebel.lam,)

    @property
    def teachers(self) -> tuple[str | None, ...]:
        return self.teacher_grid or (None,)

    def grid(self) -> list[tuple[float, str | None]]:
        """(lambda, teacher preset or None for ``config.teacher``) of each column, seeds innermost."""
        return [(lam, t) for lam in self.lams for t in self.teachers for _ in range(self.seeds)]

    @property
    def columns(self) -> int:
        """Runs vmapped together: seeds x lambdas x teachers."""
        return self.seeds * len(self.lams) * len(self.teachers)

    def column_names(self) -> list[str]:
        """``seed i`` for each column, with its lambda (of a grid) and teacher (of a grid)."""
        names = []
        for i, (lam, teacher) in enumerate(self.grid()):
            which = ([f"lambda {lam:g}"] if self.lam_grid else []) + ([f"teacher {teacher}"] if teacher else [])
            names.append(f"seed {i % self.seeds}" + (f" ({', '.join(which)})" if which else ""))
        return names


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


def swept_knob(cfg) -> bool:
    """Whether the run's method has a traced knob (REBEL's lambda), which ``--lam-grid`` sweeps as columns."""
    return cfg.method is not None and cfg.method.knob(cfg) is not None


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


# -- the run directory ---------------------------------------------------------------------
def _usage_error(err: Exception) -> SystemExit:
    print(f"error: {err}", file=sys.stderr)
    return SystemExit(EXIT_USAGE)


def _git_commit() -> str | None:
    """The checkout's commit; ``REBEL_JAX_GIT_COMMIT`` names it where the tree was copied without its history."""
    if os.environ.get("REBEL_JAX_GIT_COMMIT"):
        return os.environ["REBEL_JAX_GIT_COMMIT"]
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        return out.stdout.strip() if out.returncode == 0 else None
    except OSError:
        return None


def command_line(argv: list[str]) -> str:
    """The command as typed, independent of where the package lives: ``python -m rebel_jax.train ARGS``
    (the labelling page's token, a secret, written ``...``)."""
    return shlex.join(["python", "-m", "rebel_jax.train", *redact_token(argv)])


def flatten(tree: dict, prefix: str = "") -> dict:
    """A nested dict's leaves keyed by their dotted paths: ``{"a": {"b": 1}}`` gives ``{"a.b": 1}``."""
    out = {}
    for k, v in tree.items():
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def _run_fields(args: Args) -> dict:
    """What fixes a run besides its config: the columns (as meta.json records them)."""
    return {
        "seeds": args.seeds,
        "lams": [lam for lam, _ in args.grid()] if swept_knob(args.config) else None,
        "teachers": [t for _, t in args.grid()] if args.teacher_grid else None,
    }


def resume_changes(run_dir: pathlib.Path, args: Args) -> list[str]:
    """The fields in which ``args`` differ from the run saved in ``run_dir``, but a larger ``train.total_steps``.

    A field the saved config lacks (added to :class:`Config` since) counts as unchanged at its default.

    Raises:
      ConfigError: if ``config.json`` or ``meta.json`` cannot be read.
    """
    try:
        saved = json.loads((run_dir / "config.json").read_text())
        meta = json.loads((run_dir / "meta.json").read_text())
    except (OSError, ValueError) as err:
        raise ConfigError(f"--resume: cannot read the saved run's config.json / meta.json ({err})") from err
    now = json.loads(json.dumps(dataclasses.asdict(args.config)))  # tuples as lists, like the saved file
    old, new = flatten(saved), flatten(now)
    for name, value in _run_fields(args).items():
        old[name], new[name] = meta.get(name), json.loads(json.dumps(value))
    defaults = flatten(json.loads(json.dumps(dataclasses.asdict(Config()))))
    changes = []
    for name in sorted(old.keys() | new.keys()):
        before, after = old.get(name, "<absent>"), new.get(name, "<absent>")
        if before == after or (name == "train.total_steps" and isinstance(before, int) and after > before):
            continue
        if name not in old and name in defaults and after == defaults[name]:
            continue
        changes.append(f"{name} (saved {before!r}, now {after!r})")
    return changes


def prepare_run_dir(args: Args, lock: rundir.RunLock | None = None) -> pathlib.Path:
    """Checks ``args.run_dir`` for this run, then creates it; nothing is written before every check passed.

    With ``lock``, the directory is created first and locked (:class:`rundir.RunLock`) before its content is read;
    the lock stays held (the caller releases it).

    Raises:
      ConfigError: an empty path, a path that is not a writable directory, a directory that holds
        another run (without ``--resume`` or ``--overwrite``), or ``--resume`` with a changed configuration.
    """
    cfg = args.config
    if args.run_dir is None:
        run_dir = pathlib.Path("runs") / f"{cfg.algo}_{cfg.env.task}_{time.strftime('%Y%m%d-%H%M%S')}"
    elif not args.run_dir.strip():
        raise ConfigError(
            f"run_dir={args.run_dir!r} is invalid: allowed a directory path"
            " (leave --run-dir out for runs/<algo>_<task>_<time>)"
        )
    else:
        run_dir = pathlib.Path(args.run_dir)
    if args.resume and args.overwrite:
        raise ConfigError("overwrite=True is invalid with --resume: allowed one of --resume (continue) or --overwrite")
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"run_dir={str(run_dir)!r} is invalid: allowed a directory (it is an existing file)")
    if lock is not None:
        _writable_dir(run_dir)
        lock.acquire(run_dir)
    existing = [name for name in RUN_FILES if (run_dir / name).exists() or (run_dir / name).is_symlink()]
    if existing and not (args.resume or args.overwrite):
        raise ConfigError(
            f"run_dir={str(run_dir)!r} is invalid: it holds a run ({', '.join(existing)}); "
            "allowed --resume to continue it, --overwrite to replace it, or a new --run-dir"
        )
    if args.resume:
        rundir.check_resumable(run_dir)
    if args.resume and (run_dir / "config.json").exists():
        changes = resume_changes(run_dir, args)
        if changes:
            raise ConfigError(
                f"--resume: the flags differ from the saved run in {'; '.join(changes)}. "
                "Allowed: the saved values, except a larger --total-steps to extend the run "
                "(or start a new run with another --run-dir)"
            )
    _writable_dir(run_dir)
    if args.overwrite and existing:
        for name in existing:
            path = run_dir / name
            try:
                shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
            except OSError as err:
                raise ConfigError(
                    f"--overwrite: cannot delete {path} ({err.strerror or err}); fix it, or remove it"
                ) from err
        print(f"--overwrite: deleted the previous run's {', '.join(existing)} in {run_dir}", file=sys.stderr)
    return run_dir


def _writable_dir(run_dir: pathlib.Path) -> None:
    """Creates ``run_dir`` and checks that files can be written in it (raises ConfigError)."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        with open(run_dir / ".write-test", "w"):
            pass
        (run_dir / ".write-test").unlink()
    except OSError as err:
        raise ConfigError(f"run_dir={str(run_dir)!r} is invalid: allowed a writable directory ({err})") from err


def _write_config(run_dir: pathlib.Path, args: Args) -> None:
    write_json(run_dir / "config.json", dataclasses.asdict(args.config), strict_json=False)  # keeps beta = inf


def _write_meta(run_dir: pathlib.Path, args: Args, command: str) -> None:
    meta = {
        "jax": jax.__version__,
        "devices": [d.device_kind for d in jax.devices()],
        "processes": jax.process_count(),
        "backend": jax.default_backend(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "git_commit": _git_commit(),
        "compile_cache": compile_cache.in_use(),
        "command": command,
        **_run_fields(args),
        "columns": args.columns,
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
    }
    write_json(run_dir / "meta.json", meta)
    _write_config(run_dir, args)  # last: a run counts as saved (for --resume) once config.json exists


def _record_resume(run_dir: pathlib.Path, args: Args, command: str, start: int) -> None:
    """Appends this call to meta.json's ``resumed`` list; saves the config (a larger total_steps)."""
    meta = json.loads((run_dir / "meta.json").read_text())
    resumed = {"command": command, "started": datetime.datetime.now().isoformat(timespec="seconds")}
    resumed["compile_cache"] = compile_cache.in_use()
    meta["resumed"] = [*meta.get("resumed", []), {**resumed, "from_round": start}]
    write_json(run_dir / "meta.json", meta)
    _write_config(run_dir, args)


def keep_rounds_before(metrics: pathlib.Path, rounds: int) -> None:
    """Keeps the first ``rounds`` rounds of a resumed run's log: later ones are run (and logged) again.

    A last line cut mid-write (the process was killed while writing it) is dropped with a notice;
    an unreadable line before the last is an error, as the log would otherwise lose a round.
    """
    if not metrics.exists():
        return
    records, cut = rundir.log_records(metrics)
    if cut is not None:
        print(f"note: {metrics}: dropped its last line, cut mid-write ({len(cut)} chars)", file=sys.stderr)
    kept = [line + "\n" for line, record in records if record["round"] < rounds]
    tmp = metrics.with_name(metrics.name + ".tmp")
    tmp.write_text("".join(kept))
    os.replace(tmp, metrics)


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

    if ckpt.latest() is None:
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
        print(f"note: --resume: {err}; starting the run from scratch", file=sys.stderr)
        return 0, state
    if replay_rows(restored) != rows:
        restored = sweep.shard_seeds(grow_replay(restored, state), sharding)
    return start, restored


def _slow_checkpoint_note(r: int, saving: float, seconds: float, every: int) -> str:
    """Said once per run when a checkpoint takes longer than the round it follows (e.g. a large replay on a GPU)."""
    suggested = every * math.ceil(4 * saving / max(seconds, 1e-9))  # saves then take at most a fifth of the time
    return (
        f"note: round {r}'s checkpoint took {saving:.1f} s, longer than the round ({seconds:.1f} s): "
        f"--checkpoint-every {suggested} would spend at most a fifth of the time saving "
        f"(a kill then loses up to {suggested} rounds; 0 saves none)"
    )


def _final_result(final: np.ndarray, random: np.ndarray, ever_diverged: np.ndarray, names: list[str]) -> dict:
    return {
        "status": "diverged" if ever_diverged.any() else "completed",
        "diverged": [names[i] for i in np.flatnonzero(ever_diverged)],
        "final_eval_return": final,
        "mean": float(final.mean()),  # NaN (written as null) if any seed's is: no silent nanmean
        "std": float(final.std()),
        "random_return": random,
        "random_mean": float(random.mean()),
    }


SUMMARY_METRICS = ("labels_used", "reward_correlation", "reward_correlation_return")
"""Logged per-column metrics whose last finite value the summary table shows (preference methods)."""


def last_logged(run_dir: pathlib.Path, columns: int) -> dict[str, np.ndarray]:
    """Per column, the last finite value of each of :data:`SUMMARY_METRICS` in ``metrics.jsonl`` (NaN if none)."""
    last = {name: np.full(columns, np.nan) for name in SUMMARY_METRICS}
    for record in plots.records(run_dir):
        for name in SUMMARY_METRICS:
            if name in record:
                values = np.asarray(plots.per_seed(record[name]), float)
                last[name] = np.where(np.isfinite(values), values, last[name])
    return last


def summary_table(names: list[str], random: np.ndarray, final: np.ndarray, logged: dict[str, np.ndarray]) -> str:
    """The table printed at the end of a run: one row per column and their mean.

    Columns: the random policy's and the trained policy's evaluation return (the same initial
    states), the labels used, and the learned reward's Pearson correlation with the true one
    at the last feedback session, per step and over segment returns (``-`` for ``sac``).
    """
    header = ("", "random-policy return", "final return", "labels used", "reward corr. per step", "per segment")
    rows = [header]
    cells = [random, final, *(logged[k] for k in SUMMARY_METRICS)]
    formats = ("{:.1f}", "{:.1f}", "{:.0f}", "{:.2f}", "{:.2f}")

    def fmt(values, i):
        return [f.format(v[i]) if np.isfinite(v[i]) else "-" for f, v in zip(formats, values, strict=True)]

    rows += [(name, *fmt(cells, i)) for i, name in enumerate(names)]
    means = [np.array([np.mean(v)]) for v in cells]  # NaN where any column's is undefined
    rows.append(("mean", *fmt(means, 0)))
    widths = [max(len(row[j]) for row in rows) for j in range(len(header))]
    lines = [
        "  ".join(
            cell.ljust(w) if j == 0 else cell.rjust(w) for j, (cell, w) in enumerate(zip(row, widths, strict=True))
        )
        for row in rows
    ]
    return "\n".join(lines)


def _eval_clip(args: Args, trainer: Trainer, policy, run_dir: pathlib.Path) -> pathlib.Path | None:
    """Writes ``eval.gif``: ``args.video_steps`` steps of the first column's deterministic policy; its path.

    ``policy``: ``trainer.policy_params`` of every column, on the host. A pixel run's policy sees its own 84x84
    frame stacks; the clip is drawn by a camera of its own, as a state run's.
    """
    if args.time_limit:
        # Runs split over time-limited calls have no time budgeted for compiling the clip.
        print(f"eval.gif skipped under --time-limit; render it with: python -m rebel_jax.video {run_dir}")
        return None
    try:
        import imageio  # noqa: F401
    except ImportError:
        print(f"eval.gif skipped: imageio is not installed; later: python -m rebel_jax.video {run_dir}")
        return None
    params = jax.tree.map(lambda x: jnp.asarray(x[0]), policy)
    key = seed_keys(args.config.train.seed, 1)[0]  # any seed (PRNGKey keeps 32 bits)
    path = run_dir / "eval.gif"
    try:
        act = functools.partial(trainer.mean_action, params)
        video.policy_video(trainer.env, act, key, path, args.video_steps, 120)
    except HumanError as err:  # the quadruped's clip needs MuJoCo's renderer, which found no OpenGL context
        print(f"eval.gif skipped: {err}")
        return None
    return path


def _learning_curve(args: Args, run_dir: pathlib.Path, random: np.ndarray) -> pathlib.Path | None:
    """Writes ``learning_curve.png``: the evaluation return of each group of seeds (lambda, teacher), and random's.

    A failure here is a warning, not the run's: it comes after ``final.json``, and the figure can be drawn again
    from ``metrics.jsonl`` (``python experiments/curves.py RUN_DIR --name NAME``).
    """
    try:
        return _draw_learning_curve(args, run_dir, random)
    except Exception as error:  # Any plotting failure: the run's results are already on disk.
        print(
            f"warning: learning_curve.png not written ({type(error).__name__}: {error}); final.json and "
            f"metrics.jsonl are (experiments/curves.py {run_dir} --name NAME draws it)",
            file=sys.stderr,
        )
        return None


def _draw_learning_curve(args: Args, run_dir: pathlib.Path, random: np.ndarray) -> pathlib.Path:
    """:func:`_learning_curve`'s figure."""
    cfg = args.config
    steps, returns = plots.load_runs(run_dir)
    runs = {}
    for i in range(0, args.columns, args.seeds):
        lam, teacher = args.grid()[i]
        which = ([f"lambda {lam:g}"] if args.lam_grid else []) + ([f"teacher {teacher}"] if teacher else [])
        runs[", ".join(which) or cfg.algo] = (steps, returns[:, i : i + args.seeds])
    labels = f", {cfg.feedback.labels} labels" if cfg.preference and not args.host_teacher else ""
    title = f"{cfg.algo} on {cfg.env.task} ({cfg.env.episode_length}-step episodes{labels})"
    return plots.write_learning_curve(run_dir / "learning_curve.png", runs, title, float(np.mean(random)))


def column_keys(args: Args, sharding: NamedSharding | None = None) -> jax.Array:
    """One key per column: the seed keys tiled over the grid (each lambda's and teacher's seed i uses key i)."""
    keys = jnp.tile(seed_keys(args.config.train.seed, args.seeds), (args.columns // args.seeds, 1))
    return sweep.shard_seeds(keys, sharding)


def initial_state(args: Args, init: Callable, keys: jax.Array, sharding: NamedSharding | None = None, trainer=None):
    """The run's first state: ``init`` (of ``train.compiled``) of the :func:`column_keys`, with each column's
    lambda and teacher knobs set by the trainer (``Trainer.with_knobs``; ``api.make_trainer(args.config)`` unless
    given)."""
    trainer = trainer or api.make_trainer(args.config)
    grid = args.grid()
    lams = [lam for lam, _ in grid] if swept_knob(args.config) else None
    teacher_cfgs = [teachers.PRESETS[t] for _, t in grid] if args.teacher_grid else None
    return sweep.shard_seeds(trainer.with_knobs(init(keys), lams, teacher_cfgs), sharding)


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
    primary = sweep.is_primary()
    if resuming is None:
        resuming = args.resume and (run_dir / "config.json").exists()
    trainer = api.make_trainer(cfg, host_teacher=bool(args.host_teacher))
    # The human teacher's page and renderer start first: a machine that cannot render fails now.
    host = HostTeacher(trainer, args.host_teacher, run_dir, args.human, args.resume) if args.host_teacher else None
    sharding = sweep.seed_sharding(args.columns)
    init, round_fn, evaluate = compiled(trainer, sharding)
    keys = column_keys(args, sharding)
    sizes = rundir.tree_bytes(jax.eval_shape(init, keys))  # nothing allocated yet
    rundir.check_memory(sizes, sharding.mesh.devices.ravel().tolist() if sharding else jax.devices()[:1], STATE_FLAGS)
    state = initial_state(args, init, keys, sharding, trainer)
    grid = args.grid()
    use_ckpt = args.checkpoint_every or args.resume or args.time_limit
    ckpt = Checkpointer(run_dir / "checkpoints") if use_ckpt else None
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
        _write_meta(run_dir, args, command)
    names = args.column_names()
    per_round = cfg.train.steps_per_round
    logger = None
    if primary:
        logger = RunLogger(run_dir, cfg.train.total_steps, start * per_round, args.progress, args.tensorboard, names)
    if primary and not args.progress and start < cfg.train.num_rounds:  # A plain log says what its first wait is.
        print(
            f"{start * per_round:,}/{cfg.train.total_steps:,} steps: compiling the round program, then round "
            f"{start + 1} of {cfg.train.num_rounds} (minutes for a large preset on a CPU)",
            flush=True,
        )
    started, slowest = time.perf_counter(), 0.0
    ever_diverged = np.zeros(args.columns, bool)
    slow_save_noted = False
    try:
        for r in range(start, cfg.train.num_rounds):
            # Process 0's clock decides for all (every process must run the same rounds).
            out_of_time = time.perf_counter() - started + 1.2 * slowest > args.time_limit
            if args.time_limit and r > start and sweep.from_primary(int(out_of_time)):
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
            metrics = {**sweep.to_host(metrics), **session}
            seconds = time.perf_counter() - t0
            slowest = max(slowest, seconds) if r > start else 0.0
            env_steps = (r + 1) * per_round
            if env_steps % cfg.train.eval_every and r + 1 < cfg.train.num_rounds:
                metrics.pop("eval_return")
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
                t0 = time.perf_counter()
                ckpt.save(r + 1, state)
                saving = time.perf_counter() - t0
                if primary and not slow_save_noted and saving > seconds and r + 1 < cfg.train.num_rounds:
                    slow_save_noted = True
                    print(_slow_checkpoint_note(r, saving, seconds, args.checkpoint_every), file=sys.stderr)
        policy = trainer.policy_params(state)
        final = np.asarray(sweep.to_host(evaluate(policy, keys)))
        random = np.asarray(sweep.to_host(evaluate(policy, keys, True)))  # The same initial states.
        result = _final_result(final, random, ever_diverged, names)
        files = []
        if primary:
            write_json(run_dir / "final.json", result)
            if host is not None:
                host.finish(result)  # The labelling page says the run has finished, and where its files are.
            files.append(_learning_curve(args, run_dir, random))
        if args.video_steps > 0 and hasattr(trainer.env, "mj_model"):
            policy = sweep.to_host(policy)  # Every process: a collective with several.
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
        print(f"final evaluation return over {args.seeds} seed(s){which}: {part.mean():.1f} +- {part.std():.1f}")
    if ever_diverged.any():
        print(f"warning: diverged during the run: {', '.join(result['diverged'])}", file=sys.stderr)
    print(f"run directory: {run_dir}")
    return result


# -- the command line ------------------------------------------------------------------------
def feedback_sessions(cfg: Config) -> int:
    """Feedback sessions in a run (:func:`rebel_jax.train.session_due`)."""
    return sum(bool(session_due(cfg, r)[0]) for r in range(cfg.train.num_rounds))


def _check_args(args: Args, preset: Config) -> None:
    """The CLI's own fields, and the config's fields that the CLI combines (raises ConfigError)."""
    cfg = args.config
    if args.seeds < 1:
        raise ConfigError(f"seeds={args.seeds!r} is invalid: allowed >= 1")
    if args.distributed and args.run_dir is None:
        raise ConfigError(
            "run_dir=None is invalid with --distributed: allowed a directory on a file system every process"
            " shares (the default name holds each process's own clock time)"
        )
    if args.checkpoint_every < 0:
        raise ConfigError(f"checkpoint_every={args.checkpoint_every!r} is invalid: allowed >= 0")
    if args.video_steps < 0:
        raise ConfigError(f"video_steps={args.video_steps!r} is invalid: allowed >= 0 (0: no clip)")
    for name in ("total_steps", "buffer_capacity"):  # counted in int32 by the jitted rounds
        if getattr(cfg.train, name) > MAX_STEPS:
            raise ConfigError(
                f"train.{name}={getattr(cfg.train, name)!r} is invalid: allowed <= {MAX_STEPS} (2**31 - 1)"
            )
    if not (math.isfinite(args.time_limit) and args.time_limit >= 0):
        raise ConfigError(f"time_limit={args.time_limit!r} is invalid: allowed a finite number >= 0")
    if args.lam_grid and not swept_knob(cfg):
        raise ConfigError(f"lam_grid={args.lam_grid!r} is invalid: allowed only with --algo rebel")
    if not all(math.isfinite(lam) for lam in args.lam_grid):
        raise ConfigError(f"lam_grid={args.lam_grid!r} is invalid: allowed finite numbers")
    if args.teacher_grid and not cfg.preference:
        raise ConfigError(f"teacher_grid={args.teacher_grid!r} is invalid: allowed only with a preference algo")
    unknown = [t for t in args.teacher_grid if t not in teachers.PRESETS]
    if unknown:
        raise ConfigError(f"teacher_grid={unknown!r} is invalid: allowed {', '.join(teachers.PRESETS)}")
    changed = {part: where for part, where in cfg.unused_parts().items() if getattr(cfg, part) != getattr(preset, part)}
    if changed:
        allowed = "; ".join(f"{part} only with {where}" for part, where in changed.items())
        raise ConfigError(
            f"{', '.join(changed)} settings are invalid with --algo {cfg.algo} on {cfg.env.task!r} (the run would"
            f" ignore them): allowed {allowed}"
        )
    capacity = cfg.reward.label_capacity
    if cfg.preference and capacity != preset.reward.label_capacity and capacity < cfg.feedback.labels:
        raise ConfigError(
            f"reward.label_capacity={capacity!r} is invalid: allowed >= feedback.labels={cfg.feedback.labels}"
            " (the label store holds the whole budget)"
        )


def _warn_about(args: Args) -> None:
    cfg = args.config
    if cfg.preference:
        sessions = feedback_sessions(cfg)
        most = sessions * cfg.feedback.queries
        if cfg.feedback.labels > most:
            print(
                f"warning: feedback.labels={cfg.feedback.labels} is more than this run can ask: {sessions} "
                f"session(s) x {cfg.feedback.queries} pairs = {most} (raise --total-steps or --per-session)",
                file=sys.stderr,
            )


def check_devices(args: Args, devices: int) -> None:
    """The columns (seeds x lambdas x teachers) must split evenly over the devices (raises ConfigError)."""
    if args.columns % devices:
        grids = ""
        if args.columns != args.seeds:
            sizes = [f"{len(args.lam_grid)} lambdas"] if args.lam_grid else []
            sizes += [f"{len(args.teacher_grid)} teachers"] if args.teacher_grid else []
            grids = f" x {' x '.join(sizes)} = {args.columns} columns"
        raise ConfigError(
            f"seeds={args.seeds}{grids} is invalid: allowed a multiple of the {devices} devices to shard over, in all"
        )


class _FirstFlags(argparse.ArgumentParser):
    """The flags read before the preset's: a bad one raises ConfigError (one line, exit status 2), as a bad
    config value does, instead of argparse's usage text."""

    def error(self, message: str):
        raise ConfigError(message)


def observed_task(task: str, obs: str | None) -> str:
    """The task ``--obs`` asks for: ``pixels`` names the task's pixel version (``walker_walk`` ->
    ``walker_walk_pixels``), ``state`` refuses a pixel task, and None keeps the task (raises ConfigError)."""
    pixel = task.endswith(PIXEL_SUFFIX)
    if obs == "state" and pixel:
        state = task.removesuffix(PIXEL_SUFFIX)
        raise ConfigError(
            f"obs='state' is invalid with the pixel task {task!r}: allowed --obs pixels, or --task {state}"
        )
    return f"{task}{PIXEL_SUFFIX}" if obs == "pixels" and not pixel else task


def default_preset(task: str) -> str:
    """``--preset`` when none is given: SURF's pixel protocol (``surf_pixels_walker`` or ``surf_pixels_cheetah``)
    for a walker or cheetah pixel task, whose agent steps, rounds and sessions the ``paper`` preset does not fit;
    B-Pref's quadruped settings (``paper_quadruped``) on a quadruped task; ``paper`` otherwise."""
    domain = task.split("_", 1)[0]
    pixel_preset, state_preset = f"surf_pixels_{domain}", f"paper_{domain}"
    if task.endswith(PIXEL_SUFFIX):
        return pixel_preset if pixel_preset in PRESETS else "paper"
    return state_preset if state_preset in PRESETS else "paper"


@contextlib.contextmanager
def collector_paused():
    """No cyclic garbage collection inside the block (it runs before and after as usual).

    CPython 3.11 keeps the AST constructor's recursion count in state that every ``ast.parse`` shares
    (python/cpython gh-106905): a parse nested inside another one, from a finalizer that a collection in the middle
    of the outer parse runs, leaves the outer one failing with "SystemError: AST constructor recursion depth
    mismatch". tyro parses the config classes' source for their docstrings, and such finalizers exist: an asyncio
    Task that orbax leaves behind after a failed restore logs "Task exception was never retrieved" when collected,
    and formatting that traceback parses source (CPython 3.11's caret anchors). It broke ``parse`` once in CI, in a
    test process that had restored a damaged checkpoint earlier.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def parse(argv: list[str] | None = None) -> Args:
    """Reads ``--preset``, ``--teacher``, ``--obs`` and ``--task`` first, then every other flag as an override of
    the preset."""
    pre = _FirstFlags(prog="python -m rebel_jax.train", add_help=False, allow_abbrev=False)
    pre.add_argument("--preset", choices=sorted(PRESETS), default=None)
    pre.add_argument("--teacher", choices=[*teachers.PRESETS, *HOST_TEACHERS], default="oracle")
    pre.add_argument("--obs", choices=OBS, default=None)
    pre.add_argument("--task", default=None)
    try:
        known, rest = pre.parse_known_args(argv)
        task = observed_task(known.task or PRESETS[known.preset or "paper"].env.task, known.obs)
    except ConfigError as err:
        raise _usage_error(err) from err
    preset = known.preset or default_preset(task)
    rest = [*rest, "--task", task]
    host_teacher = known.teacher if known.teacher in HOST_TEACHERS else ""
    scripted = "oracle" if host_teacher else known.teacher  # The human's answers are compared with the oracle's.
    description = (
        f"{__doc__}\nPreset: --preset {{{','.join(sorted(PRESETS))}}} (default paper; on a walker or cheetah pixel"
        " task surf_pixels_walker or surf_pixels_cheetah; on a quadruped task paper_quadruped)."
        "\nObservations: --obs {state,pixels} (default: the task's;"
        " pixels: the task's pixel version, <task>_pixels)."
        f"\nTeacher: --teacher {{{','.join(teachers.PRESETS)}}} (default oracle); --teacher.* flags override it;"
        " --teacher human asks a person on a web page (--human.*), --teacher replay --human.labels FILE"
        " re-runs a human run's answers."
    )
    config = dataclasses.replace(PRESETS[preset], teacher=teachers.PRESETS[scripted])
    with collector_paused():
        args = tyro.cli(Args, prog=pre.prog, default=Args(config=config), args=rest, description=description)
    args = dataclasses.replace(args, host_teacher=host_teacher)
    try:
        args.config.validate()
        if args.config.pixels:
            check_config(args.config)  # the pixel trainer's checks, in agent steps
        _check_args(args, PRESETS[preset])
        if host_teacher:
            _check_host_teacher(args)
    except ConfigError as err:
        raise _usage_error(err) from err
    _warn_about(args)
    return args


def _check_host_teacher(args: Args) -> None:
    """``--teacher human|replay``: one column of a preference method; ``--human.*`` in range."""
    teacher = f"--teacher {args.host_teacher}"
    if not args.config.preference:
        raise ConfigError(f"{teacher} is invalid with --algo {args.config.algo}: allowed only with a preference algo")
    if args.config.pixels:
        raise ConfigError(f"{teacher} is invalid on the pixel task {args.config.env.task!r}: allowed on state tasks")
    if args.columns != 1:
        raise ConfigError(f"{teacher} labels one run: seeds={args.seeds}, lam_grid and teacher_grid must give 1 column")
    if not 0 <= args.human.port < 65536:
        raise ConfigError(f"human.port={args.human.port!r} is invalid: allowed 0 to 65535 (0: any free port)")
    if args.human.timeout < 0:
        raise ConfigError(f"human.timeout={args.human.timeout!r} is invalid: allowed >= 0 (0: no limit)")
    if args.human.clip_size < 16:
        raise ConfigError(f"human.clip_size={args.human.clip_size!r} is invalid: allowed >= 16")
    if args.host_teacher == "replay" and (args.human.labels is None or not args.human.labels.is_file()):
        raise ConfigError(f"human.labels={args.human.labels!r} is invalid: --teacher replay needs an existing file")
    if args.host_teacher == "human" and args.human.labels is not None:
        raise ConfigError("human.labels is only for --teacher replay (a human run writes RUN_DIR/labels.jsonl)")
    if args.host_teacher == "human" and args.human.token == "" and not is_loopback(args.human.host):
        raise ConfigError(
            f"human.token='' is invalid with --human.host {args.human.host} (not loopback): anyone on the network "
            "could label; leave --human.token out for a random one, or give one"
        )


def main(argv: list[str] | None = None) -> dict:
    """The command line: parse and check everything, then prepare the run directory, then train.

    The persistent compilation cache is set up first (:func:`rebel_jax.compile_cache.configure`): in JAX's
    configuration, for the whole process.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    avoid_cpu_deadlock()
    args = parse(argv)
    try:
        compile_cache.configure(args.compile_cache, args.no_compile_cache)
    except ConfigError as err:
        raise _usage_error(err) from err
    if args.distributed:
        try:
            sweep.initialize()
        except ValueError as err:
            raise _usage_error(err) from err
    # Process 0 checks, locks and prepares the run directory, then tells the others what it found.
    status, resuming = 0, 0
    run_dir = None if args.run_dir is None else pathlib.Path(args.run_dir)  # Set with --distributed.
    with rundir.RunLock() as lock:
        try:
            if sweep.is_primary():
                try:
                    check_devices(args, jax.device_count())
                    if args.host_teacher == "human":  # the labelling page's address, before anything is written
                        rundir.check_listen_address(args.human.host, args.human.port)
                    run_dir = prepare_run_dir(args, lock)
                    resuming = int(args.resume and (run_dir / "config.json").exists())
                except ConfigError as err:
                    print(f"error: {err}", file=sys.stderr)
                    status = EXIT_USAGE
            status, resuming = sweep.from_primary((status, resuming))
            if status:
                raise SystemExit(status)
            return run(args, run_dir, command_line(argv), bool(resuming))
        except (*HumanError, ConfigError) as err:  # No OpenGL for the clips, a checkpoint of other code, ...
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(EXIT_USAGE) from None
        except OSError as err:  # Disk full, a checkpoint that could not be saved, a permission changed meanwhile.
            if sweep.is_primary():
                print(rundir.io_error_line(err), file=sys.stderr)
            raise SystemExit(rundir.EXIT_IO) from None
        except KeyboardInterrupt:
            if sweep.is_primary():
                print(rundir.interrupted_line(run_dir), file=sys.stderr)
            raise SystemExit(rundir.EXIT_INTERRUPTED) from None
