"""What the command line offers a method: its flags as a type for tyro, grouped by part and shown briefly or all
(``--help``, ``--help-all``), and the text around them."""

from __future__ import annotations

import dataclasses
import typing
from typing import Annotated, Any

import tyro

from rebel_jax import methods
from rebel_jax.config import AGENTS, PRESETS, Config, method_sections
from rebel_jax.preference import teachers
from rebel_jax.run.options import HELP_ALL, PROG, UNPREFIXED, RunOptions, parts, swept_knob

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
