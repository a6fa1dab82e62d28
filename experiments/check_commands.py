"""Check that every training command of ``experiments/README.md`` reproduces the runs it names.

Usage:
  python experiments/check_commands.py [README]      # exit status 1 and one line per mismatch, else "ok"

In the README, a code block names its runs on a comment line ``# logs: results/runs/A results/runs/B ...`` and
then gives one ``python -m rebel_jax.train`` command (backslash continuations joined); ``for k in 1 2 3; do``
before it repeats the command with ``$k`` replaced by each value, one program per value. Each named run must
then be a run of that command, read from its ``config.json`` and ``meta.json``:

- every config field equal to the command's (a larger ``train.total_steps`` in the command is allowed, as
  ``--resume`` allows it), but ``rebel.lam`` where the command runs a ``--lam-grid`` and the parts of the config
  the run ignores (``Config.unused_parts``: SURF's settings in a PEBBLE run, the reward model's in SAC's);
- the run's lambdas among the command's, its teachers, seeds and base seed equal.

A field the run's ``config.json`` lacks (added since) must have the value that gives the code's behaviour before
the field existed: ``BEFORE``'s, else its default in ``Config()`` (as ``--resume`` assumes), or ``EQUIVALENT``'s.
"""

from __future__ import annotations

import functools
import json
import pathlib
import re
import shlex
import sys
from unittest import mock

from rebel_jax.config import Config, to_dict
from rebel_jax.envs import dmc
from rebel_jax.run import cli

ROOT = pathlib.Path(__file__).parents[1]
BEFORE = {
    "query.pool": "rows",
    "reward.init": "lecun",
    "pretrain.reset_updates": 0,
    "pretrain.running_std": "exact",
    "rebel.source": "replay",
    "feedback.budget": "answered",
}
"""What the code did before each of these settings existed (git history): a run whose ``config.json`` lacks one
ran with this value."""
EQUIVALENT = {
    "feedback.budget": "asked",
}
"""Values that give the same run as ``BEFORE``'s for every run here: the oracle and B-Pref's teachers of these runs
skipped no query (``session_skipped`` 0 in their logs), so counting the pairs asked or answered is the same."""


def blocks(text: str) -> list[tuple[list[str], list[list[str]]]]:
    """(run directories, argument lists of the commands) of each block that names its logs.

    Args:
      text: the README's Markdown.

    Returns:
      One entry per ``# logs:`` line: the run directories it names, and the flags of each program its command
      runs (one per value of a ``for k in ...; do`` loop, else one).
    """
    joined = re.sub(r"\\\n\s*", " ", text)
    out = []
    for match in re.finditer(
        r"^\s*# logs: (.+)\n((?:\s*for k in [^;\n]+; do\n)?)\s*(.*python -m rebel_jax\.train .*)$", joined, re.M
    ):
        logs = match.group(1).split()
        values = match.group(2).split("in", 1)[1].split(";")[0].split() if match.group(2) else [None]
        command = match.group(3).split("python -m rebel_jax.train", 1)[1].split(";")[0].split("#")[0]
        programs = [shlex.split(command.replace("$k", v) if v else command) for v in values]
        out.append((logs, programs))
    return out


def _impl_named(impl: str, check=dmc.check_impl) -> None:
    """``dmc.check_impl`` without its installed-package check: a command is checked for its settings, not for
    whether this machine has MuJoCo Warp to run it."""
    check("jax" if impl == "warp" else impl)


@functools.cache
def _parsed(flags: tuple[str, ...]):
    """``cli.parse`` of one program's flags, once: a block's programs are compared with each of its runs."""
    with mock.patch.object(dmc, "check_impl", _impl_named):
        return cli.parse([*flags, "--run-dir", "unused"])


def mismatches(run_dir: pathlib.Path, programs: list[list[str]]) -> list[str]:
    """What keeps ``run_dir`` from being a run of one of ``programs`` (empty: it is one).

    Args:
      run_dir: a run directory with ``config.json`` and ``meta.json``.
      programs: the flags of each program of a README command.

    Returns:
      The differences to the closest program (the one with the fewest), as ``field (run X, command Y)``.
    """
    saved = cli.flatten(json.loads((run_dir / "config.json").read_text()))
    meta = json.loads((run_dir / "meta.json").read_text())
    defaults = cli.flatten(json.loads(json.dumps(to_dict(Config()))))
    best = None
    for flags in programs:
        args = _parsed(tuple(flags))
        now = cli.flatten(json.loads(json.dumps(to_dict(args.config))))
        unused = tuple(f"{part}." for part in args.config.unused_parts())
        diffs = []
        for name in sorted(saved.keys() | now.keys()):
            before, after = saved.get(name, "<absent>"), now.get(name, "<absent>")
            if before == after or name.startswith(unused) or (name == "rebel.lam" and args.lam_grid):
                continue
            if name == "train.total_steps" and isinstance(before, int) and after > before:
                continue
            if name not in saved and after in (BEFORE.get(name, defaults.get(name)), EQUIVALENT.get(name)):
                continue
            diffs.append(f"{name} (run {before!r}, command {after!r})")
        lams = sorted(set(meta.get("lams") or []))
        if lams and not set(lams) <= set(args.lams):
            diffs.append(f"lambdas (run {lams}, command {list(args.lams)})")
        teachers = sorted({t for t in meta.get("teachers") or [] if t})
        if teachers != sorted(args.teacher_grid):
            diffs.append(f"teachers (run {teachers}, command {list(args.teacher_grid)})")
        if meta.get("seeds") != args.seeds:
            diffs.append(f"seeds (run {meta.get('seeds')}, command {args.seeds})")
        if best is None or len(diffs) < len(best):
            best = diffs
    return best or []


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    readme = pathlib.Path(argv[0]) if argv else ROOT / "experiments" / "README.md"
    failures, checked = [], 0
    for logs, programs in blocks(readme.read_text()):
        for log in logs:
            checked += 1
            for diff in mismatches(ROOT / log, programs):
                failures.append(f"{log}: {diff}")
    print("\n".join(failures) if failures else f"ok: {checked} runs match their commands")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
