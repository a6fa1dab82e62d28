"""Every numeric flag of every method, fed its edge values, is refused in one line that names it and its range, or
gives a value the program runs with; nothing is written before (``rebel_jax.core.ranges``)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from rebel_jax.config import PRESETS, ConfigError
from rebel_jax.core.ranges import FLOAT_MAX, INT_MAX, field_ranges
from rebel_jax.run import cli_args

EDGES = (-1, 0, 2**31, 2**63, math.nan, math.inf, 1e300)
TINY = ["--preset", "tiny", "--task", "probe_point", "--no-progress", "--no-tensorboard"]
RUNS = {
    "sac": ["sac", *TINY],
    "pebble": ["pebble", *TINY],
    "surf": ["surf", *TINY],
    "rebel": ["rebel", *TINY],
    "qpa": ["qpa", *TINY],
    "rune": ["rune", *TINY],
    "human": ["pebble", *TINY, "--teacher", "human"],
    "drqv2-pixels": ["drqv2", "--task", "probe_point_pixels", "--no-progress"],
    "pebble-pixels": ["pebble", "--preset", "surf_pixels_walker", "--task", "probe_point_pixels", "--no-progress"],
}
"""Each method on state, on pixels and with the human teacher."""


def _numeric_flags(args: cli_args.Args) -> list[tuple[str, tuple[str, ...], type]]:
    """(flag, path of the field in ``args``, int or float) of every numeric flag that applies to ``args``'s run."""
    cfg, out = args.config, []

    def walk(obj, path: tuple[str, ...], prefix: str) -> None:
        ranges = field_ranges(type(obj))
        for field in dataclasses.fields(obj):
            value = getattr(obj, field.name)
            if dataclasses.is_dataclass(value):
                walk(value, (*path, field.name), f"{prefix}{field.name.replace('_', '-')}.")
            elif field.name in ranges and not isinstance(value, bool):
                out.append((f"--{prefix}{field.name.replace('_', '-')}", (*path, field.name), ranges[field.name][0]))

    for name in cli_args.run_options(cfg, args.host_teacher):
        value = getattr(args, name)
        if dataclasses.is_dataclass(value):
            walk(value, (name,), f"{name}.")
        elif name in field_ranges(cli_args.RunOptions):
            out.append((f"--{name.replace('_', '-')}", (name,), field_ranges(cli_args.RunOptions)[name][0]))
    for part in cli_args.sections(cfg):
        walk(getattr(cfg, part), ("config", part), "" if part in cli_args.UNPREFIXED else f"{part}.")
    return out


def _replace(obj, path: tuple[str, ...], value):
    if len(path) == 1:
        return dataclasses.replace(obj, **{path[0]: value})
    return dataclasses.replace(obj, **{path[0]: _replace(getattr(obj, path[0]), path[1:], value)})


def _preset(argv: list[str]):
    return PRESETS[argv[argv.index("--preset") + 1]] if "--preset" in argv else PRESETS["paper"]


@pytest.fixture(scope="module", params=list(RUNS))
def run(request):
    argv = RUNS[request.param]
    return argv, cli_args.parse(argv)


def test_every_numeric_flag_at_its_edges_is_refused_by_name_or_usable(run):
    """The config's checks (those ``parse`` runs after reading the flags) on every edge value of every numeric field:
    a refusal is one line naming the field; an accepted value is finite (or a declared inf) and within int32."""
    argv, args = run
    flags = _numeric_flags(args)
    assert len(flags) > 10
    for flag, path, kind in flags:
        name = ".".join(p for p in path if p != "config")
        for edge in EDGES:
            if kind is int and not (isinstance(edge, int) or edge.is_integer()):
                continue  # the parser refuses nan, inf and 1e300 for an integer (test below)
            value = int(edge) if kind is int else float(edge)
            if isinstance(_get(args, path), tuple):  # --lam-grid: one value
                value = (value,)
            try:
                cli_args.check_all(_replace(args, path, value), _preset(argv))
            except ConfigError as err:
                text = str(err)
                assert "\n" not in text and "is invalid" in text, (flag, edge, text)
                assert name in text or flag in text, (flag, edge, text)
                continue
            values = value if isinstance(value, tuple) else (value,)
            for v in values:
                if v == math.inf and name == "teacher.beta":
                    continue  # a rational teacher
                if name == "train.seed":
                    continue  # any integer: train.seed_keys spells it whole into the keys
                assert math.isfinite(v) and abs(v) <= (INT_MAX if kind is int else FLOAT_MAX), (flag, edge)


def _get(obj, path):
    for p in path:
        obj = getattr(obj, p)
    return obj


def test_the_parser_refuses_huge_values_in_one_line_naming_the_flag(capsys, tmp_path):
    """The command line itself: each numeric flag (in the first run of :data:`RUNS` it applies to) given 2**63 (an
    integer) or 1e300 (a float): exit status 2, one line naming the flag, and the run directory not created. The
    other edge values take the same checks (the test above); nan for an integer is the parser's refusal."""
    run_dir, seen = tmp_path / "run", set()
    for argv in RUNS.values():
        args = cli_args.parse(argv)
        capsys.readouterr()
        cases = [(f, p, k, str(2**63) if k is int else "1e300") for f, p, k in _numeric_flags(args) if f not in seen]
        cases += [] if seen else [(f, p, k, "nan") for f, p, k in _numeric_flags(args)[:1]]
        for flag, path, _, text in cases:
            seen.add(flag)
            name = ".".join(p for p in path if p != "config")
            if name == "train.seed":  # any integer, kept whole
                assert cli_args.parse([*argv, flag, text]).config.train.seed == int(text)
                capsys.readouterr()
                continue
            with pytest.raises(SystemExit) as end:
                cli_args.parse([*argv, "--run-dir", str(run_dir), flag, text])
            assert end.value.code == 2, (flag, text)
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith("error: "), (flag, text, err)
            assert name in err[0] or flag in err[0], (flag, text, err)
            assert not run_dir.exists()
    assert len(seen) > 80
