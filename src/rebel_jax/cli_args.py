"""The command line's argument model: the flags, their presets and the checks of their combinations.

    python -m rebel_jax.train METHOD [--preset P] [--obs state|pixels] [--teacher T] [FLAGS]

METHOD is an agent alone on the true reward (``sac`` on state tasks, ``drqv2`` on pixel tasks) or a preference
method of :data:`rebel_jax.methods.REGISTRY` (``pebble``, ``surf``, ``rebel``, ...); left out, the preset's. The
older ``--algo METHOD`` still works. ``METHOD --help`` lists the flags that apply to that method on that kind of
observation (``--obs pixels`` or a pixel ``--task`` for the pixel ones), its common ones only; ``--help-all``
lists every one. Each part of the config is set with its own prefix (``--sac.hidden``, ``--feedback.labels``,
``--reward.lr``); the run's schedule (``--task``, ``--total-steps``, ``--seed``, ...) and the run's own options
(``--seeds``, ``--run-dir``, ``--resume``, ...) carry none.

:func:`parse` reads them into :class:`Args` (a :class:`rebel_jax.config.Config` and the run's own options),
refusing a bad value or combination with one line (:func:`usage_error`) before anything is written.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import difflib
import gc
import io
import math
import sys
import typing
from typing import Annotated, Any, Literal

import tyro

from rebel_jax import methods, rundir, sweep, teachers
from rebel_jax.budget import session_due
from rebel_jax.config import AGENTS, PRESETS, Config, ConfigError, method_sections
from rebel_jax.envs.pixels import SUFFIX as PIXEL_SUFFIX
from rebel_jax.human import HOST_TEACHERS, HumanOptions, is_loopback
from rebel_jax.pixel_feedback import check_config
from rebel_jax.ranges import check_ranges

PROG = "python -m rebel_jax.train"
EXIT_USAGE = rundir.EXIT_USAGE
MAX_STEPS = 2**31 - 1
"""The largest ``--total-steps`` and ``--buffer-capacity``: the rounds count steps and index the buffer in int32."""
OBS = ("state", "pixels")
"""``--obs``: what the agent observes; ``pixels`` runs the task's pixel version (``<task>_pixels``)."""
UNPREFIXED = ("env", "train")
"""Config sections whose flags carry no prefix (``--task``, ``--total-steps``): the run's task and schedule."""
BRIEF: dict[str, tuple[str, ...]] = {
    "run": ("seeds", "run_dir", "resume", "overwrite", "time_limit", "lam_grid", "teacher_grid", "human"),
    "human": ("host", "port", "labels"),
    "env": ("task", "num_envs", "episode_length"),
    "train": ("total_steps", "seed_steps", "eval_episodes", "seed"),
    "sac": ("hidden", "batch_size", "utd", "precision"),
    "drqv2": ("feature_dim", "hidden", "batch_size", "nstep", "precision"),
    "feedback": ("labels", "per_session", "interval"),
    "query": ("segment_length", "sampling"),
    "teacher": (),
    "reward": ("ensemble_size", "hidden", "lr"),
    "pixel_reward": ("ensemble_size", "hidden", "lr"),
    "pretrain": ("steps",),
    "rebel": ("lam", "estimator", "source", "episodes", "num_segments", "segment_length"),
    "rime": ("alpha", "beta_init", "beta_min", "decay_epochs", "flip_tau", "warmup_epochs"),
    "mrn": ("meta_period", "outer_weight"),
}
"""The flags ``--help`` lists of each part (``run``: the run's own options); ``--help-all`` lists the others too. A
part missing here (a new method's section) shows all its flags. Every flag is accepted either way."""
HELP_ALL = "--help-all"
CORE_PARTS = tuple(f.name for f in dataclasses.fields(Config) if f.name not in ("algo", "method_settings"))
"""The config's own sections, each a group of flags."""


def parts() -> tuple[str, ...]:
    """Every section of the config, each a group of flags: its own, then each registered method's settings
    (``--NAME.*``, from the method's config dataclass)."""
    return (*CORE_PARTS, *method_sections())


@dataclasses.dataclass(frozen=True)
class RunOptions:
    """The run's own flags (beside its config's)."""

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
    """Rounds between checkpoints; 0 disables them (``--resume`` still reads existing ones). A save's files are
    written during the next round (the last round's before the final evaluation); a save that still holds up the
    run longer than its round (a large pixel replay on a GPU) prints a note with an interval that keeps saving
    under a fifth of the time."""
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
    """``rebel`` only: run every seed with each of these lambdas in one vmapped program
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


@dataclasses.dataclass(frozen=True)
class Args(RunOptions):
    """Train one configuration on several seeds."""

    config: Config = Config()
    """The run's configuration (every section's flags)."""
    host_teacher: str = ""
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


def swept_knob(cfg) -> bool:
    """Whether the run's method has a traced knob (REBEL's lambda), which ``--lam-grid`` sweeps as columns."""
    return cfg.method is not None and cfg.method.knob(cfg) is not None


def usage_error(err: Exception) -> SystemExit:
    print(f"error: {err}", file=sys.stderr)
    return SystemExit(EXIT_USAGE)


def feedback_sessions(cfg: Config) -> int:
    """Feedback sessions in a run (:func:`rebel_jax.budget.session_due`)."""
    return sum(bool(session_due(cfg, r)[0]) for r in range(cfg.train.num_rounds))


def check_args(args: Args, preset: Config) -> None:
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
        raise ConfigError(
            f"lam_grid={args.lam_grid!r} is invalid: allowed only with a method that has a knob to sweep (rebel)"
        )
    if not all(math.isfinite(lam) for lam in args.lam_grid):
        raise ConfigError(f"lam_grid={args.lam_grid!r} is invalid: allowed finite numbers")
    if args.teacher_grid and not cfg.preference:
        raise ConfigError(f"teacher_grid={args.teacher_grid!r} is invalid: allowed only with a preference method")
    unknown = [t for t in args.teacher_grid if t not in teachers.PRESETS]
    if unknown:
        raise ConfigError(f"teacher_grid={unknown!r} is invalid: allowed {', '.join(teachers.PRESETS)}")
    changed = {part: where for part, where in cfg.unused_parts().items() if getattr(cfg, part) != getattr(preset, part)}
    if changed:
        _refuse_unused(cfg, changed)
    capacity = cfg.reward.label_capacity
    if cfg.preference and capacity != preset.reward.label_capacity and capacity < cfg.feedback.labels:
        raise ConfigError(
            f"reward.label_capacity={capacity!r} is invalid: allowed >= feedback.labels={cfg.feedback.labels}"
            " (the label store holds the whole budget)"
        )


def _refuse_unused(cfg: Config, parts: dict[str, str], flag: str = "") -> None:
    """Refuses settings of the config's ``parts`` that ``cfg``'s run never reads (each with where it is read)."""
    allowed = "; ".join(f"{part} only with {where}" for part, where in parts.items())
    raise ConfigError(
        f"{flag + ': ' if flag else ''}{', '.join(parts)} settings are invalid with {cfg.algo} on {cfg.env.task!r}"
        f" (the run would ignore them): allowed {allowed}"
    )


def flag_names(cfg: Config, host_teacher: str, every: bool = False) -> dict[str, str]:
    """The command line's flags (``--sac.hidden``, ``--total-steps``, ``--no-progress``), each with its part (a
    config section, or ``run`` for the run's own options).

    Args:
      cfg: the run's config (its method and task say which parts apply).
      host_teacher: ``human``, ``replay`` or empty.
      every: every flag of every part, not only those that apply to ``cfg``'s run.
    """
    chosen = parts() if every else sections(cfg)
    own = [f.name for f in dataclasses.fields(RunOptions)] if every else run_options(cfg, host_teacher)
    names = {flag: "run" for flag in ("--preset", "--teacher", "--obs", "--algo", HELP_ALL, "--help")}

    def add(obj: Any, prefix: str, part: str) -> None:
        for field in dataclasses.fields(obj):
            value = getattr(obj, field.name)
            dashed = field.name.replace("_", "-")
            if dataclasses.is_dataclass(value):
                add(value, f"{prefix}{dashed}.", part)
                continue
            names[f"--{prefix}{dashed}"] = part
            if isinstance(value, bool):
                names[f"--{prefix}no-{dashed}"] = part

    run = RunOptions()
    for name in own:
        value = getattr(run, name)
        if dataclasses.is_dataclass(value):
            add(value, f"{name.replace('_', '-')}.", "run")
        else:
            dashed = name.replace("_", "-")
            names[f"--{dashed}"] = "run"
            if isinstance(value, bool) and not name.startswith("no_"):
                names[f"--no-{dashed}"] = "run"
    for part in chosen:
        add(getattr(cfg, part), "" if part in UNPREFIXED else f"{part.replace('_', '-')}.", part)
    return names


def _given(flags: list[str]) -> list[str]:
    """The flag names on a command line (``--sac.hidden=64`` and ``--sac.hidden 64`` both give ``--sac.hidden``)."""
    return [flag.split("=", 1)[0].replace("_", "-") for flag in flags if flag.startswith("--")]


def check_flags(given: list[str], cfg: Config, host_teacher: str) -> None:
    """Refuses a flag the run does not use (whatever its value, the preset's too) and a flag that does not exist,
    suggesting the nearest of the method's flags (raises ConfigError)."""
    every, applies = flag_names(cfg, host_teacher, every=True), flag_names(cfg, host_teacher)
    unused, ignored = cfg.unused_parts(), {}
    for flag in given:
        if flag in applies or flag == "-h":
            continue
        part = every.get(flag)
        if part in unused:
            ignored.setdefault(part, flag)
        elif part is not None:  # a run option of another method or teacher (--lam-grid, --human.*)
            where = {"--lam-grid": "a method with a knob to sweep (rebel)", "--teacher-grid": "a preference method"}
            human = flag.startswith("--human.")
            allowed = where.get(flag, "--teacher human or --teacher replay" if human else "another method")
            raise ConfigError(
                f"{flag} is invalid with {cfg.algo} (the run would ignore it): allowed only with {allowed}"
            )
        else:
            close = difflib.get_close_matches(flag, list(applies), n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]}?" if close else ""
            raise ConfigError(
                f"unrecognized flag {flag}{hint} ({PROG} {cfg.algo} --help lists the flags, {HELP_ALL} all)"
            )
    if ignored:
        _refuse_unused(cfg, {part: unused[part] for part in ignored}, ", ".join(ignored.values()))


def _warn_about(args: Args) -> None:
    cfg = args.config
    if not cfg.pixels:
        per_step = cfg.sac.utd * cfg.env.num_envs
        used = max(1, round(per_step))
        if not math.isclose(per_step, used):
            print(
                f"note: sac.utd={cfg.sac.utd:g} with env.num_envs={cfg.env.num_envs} runs {used} update(s) per vector"
                f" step (utd x num_envs rounded), so the utd used is {used / cfg.env.num_envs:g}",
                file=sys.stderr,
            )
    if cfg.preference:
        sessions = feedback_sessions(cfg)
        most = sessions * cfg.feedback.queries
        if cfg.feedback.labels > most:
            print(
                f"warning: feedback.labels={cfg.feedback.labels} is more than this run can ask: {sessions} "
                f"session(s) x {cfg.feedback.queries} pairs = {most} (raise --total-steps or --feedback.per-session)",
                file=sys.stderr,
            )


def check_devices(args: Args, devices: int) -> None:
    """Columns (seeds x lambdas x teachers) that do not split evenly over the devices are padded
    (``sweep.padded_columns``), said in a note; a host teacher's one column needs one device (raises ConfigError)."""
    if args.host_teacher and devices > 1:
        raise ConfigError(
            f"--teacher {args.host_teacher} labels one column on one device, and {devices} are visible: "
            "make one visible (e.g. CUDA_VISIBLE_DEVICES=0)"
        )
    total = sweep.padded_columns(args.columns, devices)
    if total != args.columns:
        what = f"{args.columns} columns" if args.columns != args.seeds else f"seeds={args.seeds}"
        print(
            f"note: {what} on {devices} devices: each runs {total // devices}, so {total - args.columns} column(s) "
            f"repeat the last one and are dropped (a multiple of {devices} wastes none)",
            file=sys.stderr,
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


def sections(cfg: Config) -> list[str]:
    """The config's parts that ``cfg``'s run reads, in :class:`Config`'s order (``--help`` lists their flags)."""
    unused = cfg.unused_parts()
    return [name for name in parts() if name not in unused]


def run_options(cfg: Config, host_teacher: str) -> list[str]:
    """The run's own options that apply to ``cfg`` (the grids to the methods they sweep, ``human`` to a person)."""
    names = [f.name for f in dataclasses.fields(RunOptions)]
    applies = {
        "lam_grid": swept_knob(cfg) and not host_teacher,
        "teacher_grid": cfg.preference and not host_teacher,
        "human": bool(host_teacher),
    }
    return [name for name in names if applies.get(name, True)]


def _hiding(cls: type, hidden: set[str]) -> type:
    """``cls`` with the fields ``hidden`` left out of the help (a subclass; tyro reads the others' docstrings)."""
    if not hidden:
        return cls
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = [(f.name, tyro.conf.Suppress[hints[f.name]], f) for f in dataclasses.fields(cls) if f.name in hidden]
    return dataclasses.make_dataclass(cls.__name__, fields, bases=(cls,), frozen=True)


def _shown(part: str, name: str, help_mode: str) -> bool:
    """Whether ``--help`` (``help_mode`` ``brief``) or ``--help-all`` (``all``) lists the flag ``name`` of ``part``."""
    return help_mode == "all" or part not in BRIEF or name in BRIEF[part]


def _values(obj: Any) -> dict[str, Any]:
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}


def flags_type(cfg: Config, host_teacher: str, help_mode: str | None = None) -> tuple[type, Any]:
    """The dataclass tyro reads the flags into (the run's options, then one field per config section), and its
    default.

    Args:
      cfg: the preset with the run's method, task and teacher: the defaults.
      host_teacher: ``human``, ``replay`` or empty.
      help_mode: None to parse: every flag of every part, so that a flag of a part the run ignores is refused by
        name in :func:`check_args`. ``brief`` or ``all`` for ``--help`` and ``--help-all``: only the parts and
        options that apply to the run, and with ``brief`` only :data:`BRIEF`'s.
    """
    own = _values(RunOptions())
    applies = {*sections(cfg), *run_options(cfg, host_teacher)}
    conditions = {**cfg.unused_parts(), **OPTION_CONDITIONS}
    hints = typing.get_type_hints(RunOptions, include_extras=True)
    fields, values = [], {}
    given = [(n, cfg.section(n) if n in method_sections() else getattr(cfg, n)) for n in parts()]
    for name, default in [*own.items(), *given]:
        hint = hints.get(name, type(default))
        if help_mode == "all" and name not in applies:  # listed in its own group, naming when it applies
            where = f"Only with {conditions.get(name, 'another method')}: {cfg.algo} on {cfg.env.task} ignores"
            hint = Annotated[
                hint, tyro.conf.arg(help=f"{where} {'these flags' if name in parts() or name == 'human' else 'it'}.")
            ]
        elif help_mode is not None and (name not in applies or (name in own and not _shown("run", name, help_mode))):
            hint = tyro.conf.Suppress[hint]
        elif help_mode is not None and dataclasses.is_dataclass(default):
            hint = _hiding(hint, {g for g in _values(default) if not _shown(name, g, help_mode)})
            default = hint(**_values(default))
        if name in UNPREFIXED:
            hint = Annotated[hint, tyro.conf.OmitArgPrefixes]
        if name not in own or hint is not hints[name]:  # RunOptions's own fields are inherited as they are
            fields.append((name, hint, dataclasses.field(default=default)))
        values[name] = default
    target = dataclasses.make_dataclass("Flags", fields, bases=(RunOptions,), frozen=True)
    return target, target(**values)


METHOD_LINES = {
    "sac": "SAC alone, on the task's true reward (state tasks)",
    "drqv2": "DrQ-v2 alone, on the task's true reward (pixel tasks)",
    "pebble": "PEBBLE: SAC on a reward model learnt from preferences, after unsupervised pre-training",
    "surf": "PEBBLE with SURF's pseudo-labelled pairs and temporal crops",
    "rebel": "PEBBLE with REBEL's agent-preference term, weighted by --rebel.lam",
    "qpa": "QPA: queries from the policy's recent episodes, hybrid replay batches and crops",
    "rune": "PEBBLE with RUNE's exploration bonus from the reward ensemble's disagreement",
}
"""``--help`` without a method: one line per method (a method registered elsewhere: its ``summary`` attribute, else
its class's first docstring line)."""


def method_list() -> str:
    """What ``--help`` without a method prints: the usage and one line per method."""
    import inspect

    lines = [f"usage: {PROG} METHOD [--preset P] [--obs state|pixels] [--teacher T] [FLAGS]", "", "METHOD:"]
    for name in (*AGENTS, *methods.REGISTRY):
        method = methods.REGISTRY.get(name)
        doc = (inspect.getdoc(type(method)) or "").splitlines() if method is not None else []
        line = METHOD_LINES.get(name) or getattr(method, "summary", "") or (doc[0] if doc else "")
        lines.append(f"  {name:<8} {line}")
    lines += ["", f"{PROG} METHOD --help lists a method's common flags, METHOD {HELP_ALL} all of them."]
    return "\n".join(lines)


OPTION_CONDITIONS = {
    "lam_grid": "a method with a knob to sweep (rebel), and a scripted teacher",
    "teacher_grid": "a preference method and a scripted teacher",
    "human": "--teacher human or --teacher replay",
}
"""When the run's own options that apply to some runs only apply (``--help-all`` names it)."""


RENAMED = {
    **{f"--{f.name.replace('_', '-')}": f"--sac.{f.name.replace('_', '-')}" for f in dataclasses.fields(Config().sac)},
    **{
        f"--{f.name.replace('_', '-')}": f"--feedback.{f.name.replace('_', '-')}"
        for f in dataclasses.fields(Config().feedback)
    },
}
"""Flags that were spelt without their part's prefix before, and their spelling now."""


def _check_spellings(flags: list[str]) -> None:
    """Refuses the older spellings of :data:`RENAMED`, naming the new one (raises ConfigError)."""
    for flag in flags:
        name = flag.split("=", 1)[0].replace("_", "-")
        if name in RENAMED:
            pixels = " (on a pixel task the agent's flags are --drqv2.*)" if RENAMED[name].startswith("--sac") else ""
            raise ConfigError(f"{flag.split('=', 1)[0]} is now {RENAMED[name]}{pixels}")


def _method_first(argv: list[str]) -> tuple[str | None, list[str]]:
    """The METHOD word before the flags (None if the command starts with a flag), and the flags."""
    if not argv or argv[0].startswith("-"):
        return None, argv
    names = (*AGENTS, *methods.REGISTRY)
    if argv[0] not in names:
        raise ConfigError(f"method {argv[0]!r} is invalid: allowed {', '.join(names)} ({PROG} METHOD [FLAGS])")
    return argv[0], argv[1:]


def _description(cfg: Config, preset: str, help_all: bool) -> str:
    """``--help``'s text above the flags: the method, the flags read first, and where the others are."""
    names = ", ".join((*AGENTS, *methods.REGISTRY))
    kind = "pixels" if cfg.pixels else "state"
    return (
        f"Train {cfg.algo} on {cfg.env.task} ({kind} observations) on several seeds. METHOD: {names}.\n"
        f"  --preset NAME  the defaults: {', '.join(sorted(PRESETS))} (now {preset}; default paper, on a pixel task "
        "its SURF protocol, on a quadruped task paper_quadruped)\n"
        "  --obs {state,pixels}  pixels: the task's pixel version (<task>_pixels)\n"
        f"  --teacher NAME  {', '.join(teachers.PRESETS)} (default: the preset's; --teacher.* override it), human"
        " (a person on a web page, --human.*) or replay (--human.labels FILE: a human run's answers)\n"
        f"  {HELP_ALL}  "
        + ("every flag of this method, as below" if help_all else "every flag of this method (below: the common ones)")
    )


def _one_line(framed: str) -> str:
    """The first paragraph of a message tyro prints in a frame (``Error parsing --seeds: ...``), on one line."""
    words = []
    for line in framed.strip().splitlines()[1:]:  # the first line is the frame's top and title
        text = line.strip().strip("│").strip()
        if not text or set(text) <= set("─╰╯"):
            break
        words.append(text)
    return " ".join(words) or "a flag's value cannot be read"


def parse(argv: list[str] | None = None) -> Args:
    """Reads METHOD (or ``--algo``), ``--preset``, ``--teacher``, ``--obs`` and ``--task`` first, then every other flag
    as an override of the preset."""
    try:
        methods.load_entry_points()  # the installed packages' own methods, before their names are read
    except ValueError as err:
        raise usage_error(ConfigError(str(err))) from err
    pre = _FirstFlags(prog=PROG, add_help=False, allow_abbrev=False)
    pre.add_argument("--preset", choices=sorted(PRESETS), default=None)
    pre.add_argument("--teacher", choices=[*teachers.PRESETS, *HOST_TEACHERS], default=None)
    pre.add_argument("--obs", choices=OBS, default=None)
    pre.add_argument("--task", default=None)
    pre.add_argument("--algo", choices=[*AGENTS, *methods.REGISTRY], default=None)
    pre.add_argument(HELP_ALL, action="store_true")
    try:
        method, argv = _method_first(list(sys.argv[1:] if argv is None else argv))
        known, rest = pre.parse_known_args(argv)
        if method and known.algo and method != known.algo:
            raise ConfigError(f"algo={known.algo!r} is invalid after the method {method}: allowed one of the two")
        if known.task == "":
            raise ConfigError("task='' is invalid: allowed a task's name (--help lists them)")
        task = observed_task(known.task or PRESETS[known.preset or "paper"].env.task, known.obs)
        _check_spellings(rest)
    except ConfigError as err:
        raise usage_error(err) from err
    if method is None and known.algo is None and not known.help_all and any(f in ("-h", "--help") for f in rest):
        print(method_list())
        raise SystemExit(0)
    preset = known.preset or default_preset(task)
    host_teacher = known.teacher if known.teacher in HOST_TEACHERS else ""
    base = PRESETS[preset]
    config = dataclasses.replace(
        base,
        algo=method or known.algo or base.algo,
        env=dataclasses.replace(base.env, task=task),
        # The preset's teacher unless --teacher names one; a human's answers are compared with the oracle's.
        teacher=base.teacher
        if known.teacher is None
        else teachers.PRESETS["oracle" if host_teacher else known.teacher],
    )
    helping = known.help_all or any(flag in ("-h", "--help") for flag in rest)
    mode = ("all" if known.help_all else "brief") if helping else None
    if mode is None:
        try:
            check_flags(_given(rest), config, host_teacher)
        except ConfigError as err:
            raise usage_error(err) from err
    target, default = flags_type(config, host_teacher, mode)
    prog = f"{PROG} {config.algo}"
    said, failure = io.StringIO(), None
    with collector_paused(), contextlib.redirect_stderr(said):
        try:
            flags, unknown = tyro.cli(
                target,
                prog=prog,
                default=default,
                args=[*rest, "--help"] if known.help_all else rest,
                description=_description(config, preset, known.help_all),
                return_unknown_args=True,
            )
        except SystemExit as end:
            if end.code in (0, None):
                raise
            failure = end
    if failure is not None:  # a value tyro cannot read: its framed message as one line
        raise usage_error(ConfigError(f"{_one_line(said.getvalue())} ({prog} --help lists the flags)")) from failure
    print(said.getvalue(), end="", file=sys.stderr)
    values = _values(flags)
    run = {name: values.pop(name) for name in _values(RunOptions())}
    args = Args(**run, config=Config(algo=config.algo, **values), host_teacher=host_teacher)
    try:
        if unknown:
            raise ConfigError(f"unrecognized flag {unknown[0]} ({prog} --help lists the flags, {HELP_ALL} all)")
        check_all(args, PRESETS[preset])
    except ConfigError as err:
        raise usage_error(err) from err
    _warn_about(args)
    return args


def check_all(args: Args, preset: Config) -> None:
    """Every check of a parsed command line, in order: each value in its range (:mod:`rebel_jax.ranges`), then
    the config's own checks, the pixel trainer's, the combinations the CLI makes, and a host teacher's (raises
    ConfigError)."""
    check_ranges(args, skip=("config",))  # the run's own options; the config's in its validate
    args.config.validate()
    if args.config.pixels:
        check_config(args.config)  # the pixel trainer's checks, in agent steps
    check_args(args, preset)
    if args.host_teacher:
        _check_host_teacher(args)


def _check_host_teacher(args: Args) -> None:
    """``--teacher human|replay``: one column of a preference method; ``--human.*`` in range."""
    teacher = f"--teacher {args.host_teacher}"
    if not args.config.preference:
        raise ConfigError(f"{teacher} is invalid with {args.config.algo}: allowed only with a preference method")
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
