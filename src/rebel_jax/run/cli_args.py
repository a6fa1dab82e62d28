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
from typing import Any

import tyro

from rebel_jax import methods
from rebel_jax.config import AGENTS, PRESETS, Config, ConfigError
from rebel_jax.core.ranges import check_ranges
from rebel_jax.envs.metaworld import PREFIX as METAWORLD_PREFIX
from rebel_jax.envs.pixels import SUFFIX as PIXEL_SUFFIX
from rebel_jax.preference import teachers
from rebel_jax.preference.budget import session_due
from rebel_jax.preference.pixel_feedback import check_config
from rebel_jax.run.cli_help import (  # noqa: F401 - re-exported
    BRIEF,
    METHOD_LINES,
    OPTION_CONDITIONS,
    _description,
    _hiding,
    _one_line,
    _shown,
    _values,
    flags_type,
    method_list,
    run_options,
    sections,
)
from rebel_jax.run.human import HOST_TEACHERS, is_loopback
from rebel_jax.run.options import (  # noqa: F401 - re-exported
    CORE_PARTS,
    EXIT_USAGE,
    HELP_ALL,
    MAX_STEPS,
    OBS,
    PROG,
    UNPREFIXED,
    Args,
    RunOptions,
    parts,
    swept_knob,
    usage_error,
)
from rebel_jax.train import placement


def feedback_sessions(cfg: Config) -> int:
    """Feedback sessions in a run (:func:`rebel_jax.preference.budget.session_due`)."""
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
    (``placement.padded_columns``), said in a note; a host teacher's one column needs one device (raises
    ConfigError)."""
    if args.host_teacher and devices > 1:
        raise ConfigError(
            f"--teacher {args.host_teacher} labels one column on one device, and {devices} are visible: "
            "make one visible (e.g. CUDA_VISIBLE_DEVICES=0)"
        )
    total = placement.padded_columns(args.columns, devices)
    if total != args.columns:
        what = f"{args.columns} columns" if args.columns != args.seeds else f"seeds={args.seeds}"
        print(
            f"note: {what} on {devices} devices: each runs {total // devices}, so {total - args.columns} column(s) "
            f"repeat the last one and are dropped (a multiple of {devices} wastes none)",
            file=sys.stderr,
        )


def engine_note(args: Args, backend: str) -> str | None:
    """A note where a Meta-World task runs MJX's JAX step on a GPU (``backend``: ``jax.default_backend()``): Warp's
    step is the fast one there (BENCHMARKS.md, "How fast is a Meta-World step?"); None otherwise."""
    env = args.config.env
    if not env.task.startswith(METAWORLD_PREFIX) or env.impl != "jax" or backend != "gpu":
        return None
    return (
        f"note: {env.task} runs MJX's JAX step (--impl jax), far slower on a GPU than MuJoCo Warp's: add --impl warp "
        "(pip install -e '.[warp]'; BENCHMARKS.md, \"How fast is a Meta-World step?\")"
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
    B-Pref's quadruped settings (``paper_quadruped``) on a quadruped task, its Meta-World settings
    (``paper_metaworld``) on a Meta-World task; ``paper`` otherwise."""
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
    """Every check of a parsed command line, in order: each value in its range (:mod:`rebel_jax.core.ranges`), then
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
