"""The command line's help: one method's flags for one kind of observation, at most 40, each with its section's prefix;
``--help-all`` lists every flag that applies, and a flag ``--help`` leaves out can still be set.

Everything here parses flags and prints help, nothing is compiled, so it runs ``cli.parse`` in this process.
"""

from __future__ import annotations

import dataclasses
import difflib
import re

import pytest

from rebel_jax import methods
from rebel_jax.config import AGENTS, Config
from rebel_jax.run import cli, cli_args
from rebel_jax.run.human import HumanOptions

MOST_FLAGS = 40
TINY = ["--preset", "tiny", "--task", "probe_point"]
KINDS = [
    (method, obs)
    for method in (*AGENTS, *methods.REGISTRY)
    for obs in ("state", "pixels")
    if (method, obs) not in (("sac", "pixels"), ("drqv2", "state"))
    and (obs == "state" or method not in methods.REGISTRY or methods.REGISTRY[method].pixels)
]
BOX = re.compile(r"^(?:╭─ | )(?:(\S+) )?options(?: ─|\s*$)")  # a terminal's box, or plain text
OPTION = re.compile(r"^(?:│ |  )(?:-h, )?(--[a-z][a-z0-9.-]*)")
FIRST = re.compile(r"^  (--[a-z][a-z0-9.-]*) ")
"""The flags read before the others (``--preset``, ``--obs``, ...), listed in the description."""


def _help(argv: list[str], capsys, monkeypatch) -> str:
    monkeypatch.setenv("COLUMNS", "100")
    with pytest.raises(SystemExit) as exit_info:
        cli.parse(argv)
    assert exit_info.value.code == 0
    return capsys.readouterr().out


def _flags(text: str) -> dict[str, list[str]]:
    """Group title (``options`` for the run's own, ``description`` for the flags read first) -> its flags."""
    groups: dict[str, list[str]] = {"description": []}
    group = None
    for line in text.splitlines():
        if box := BOX.match(line):
            group = box.group(1) or "options"
            groups.setdefault(group, [])
        elif group is not None and (option := OPTION.match(line)):
            groups[group].append(option.group(1))
        elif group is None and (first := FIRST.match(line)):
            groups["description"].append(first.group(1))
    return groups


def _field_flags(cls) -> set[str]:
    return {f.name.replace("_", "-") for f in dataclasses.fields(cls)}


def _check_prefixes(groups: dict[str, list[str]]) -> None:
    """Every section's flags carry its prefix; the run's own options, the task and the schedule carry none."""
    sections = {name.replace("_", "-"): type(getattr(Config(), name)) for name in cli_args.parts()}
    sections["human"] = HumanOptions
    for group, flags in groups.items():
        if group in ("description", "options"):
            assert all("." not in flag for flag in flags), (group, flags)
        elif group in cli_args.UNPREFIXED:
            assert {flag[2:] for flag in flags} <= _field_flags(sections[group]), (group, flags)
        else:
            prefix = f"--{group}."
            assert all(flag.startswith(prefix) for flag in flags), (group, flags)
            assert {flag.removeprefix(prefix) for flag in flags} <= _field_flags(sections[group]), (group, flags)


@pytest.mark.parametrize("method,obs", KINDS)
def test_a_method_s_help_lists_at_most_40_flags_each_with_its_section_s_prefix(method, obs, capsys, monkeypatch):
    groups = _flags(_help([method, "--obs", obs, "--help"], capsys, monkeypatch))
    flags = [flag for group in groups.values() for flag in group]
    assert len(flags) == len(set(flags)), flags
    assert len(flags) <= MOST_FLAGS, (len(flags), flags)
    assert {"--preset", "--obs", "--teacher", "--help-all", "--help", "--seeds", "--task"} <= set(flags)
    _check_prefixes(groups)


@pytest.mark.parametrize("method,obs", KINDS)
def test_help_all_lists_every_flag_the_conditional_ones_in_groups_naming_their_condition(
    method, obs, capsys, monkeypatch
):
    text = _help([method, "--obs", obs, "--help-all"], capsys, monkeypatch)
    groups = _flags(text)
    _check_prefixes(groups)
    cfg = cli.parse([method, "--obs", obs]).config
    capsys.readouterr()
    expected = {name.replace("_", "-") for name in cli_args.parts()} | {"human"}
    listed = {group for group in groups if group not in ("description", "options")}
    assert listed == expected
    for name in cli_args.parts():
        group = name.replace("_", "-")
        prefix = "--" if name in cli_args.UNPREFIXED else f"--{group}."
        assert {flag.removeprefix(prefix) for flag in groups[group]} == _field_flags(type(getattr(cfg, name)))
    unused = {
        **{k.replace("_", "-"): v for k, v in cfg.unused_parts().items()},
        "human": "--teacher human or --teacher replay",
    }
    for name, where in unused.items():  # each such group's first line names when its flags apply
        lines = text.splitlines()
        [title] = [i for i, line in enumerate(lines) if (box := BOX.match(line)) and box.group(1) == name]
        first = next(t for line in lines[title + 1 :] if (t := line.strip("│ ")) and set(t) - set("─-"))
        assert first.startswith(f"Only with {where.split(' (')[0]}"), (name, first)
    own = {flag[2:] for flag in groups["options"]} - {"help"}
    assert own == _field_flags(cli_args.RunOptions) - {"human"}


def test_help_without_a_method_lists_the_methods_one_line_each(capsys):
    with pytest.raises(SystemExit) as end:
        cli.parse(["--help"])
    assert end.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    said = {}
    for name in (*AGENTS, *methods.REGISTRY):
        [line] = [line for line in lines if line.split()[:1] == [name]]
        assert len(line.split()) > 3, line
        said[name] = line.removeprefix(f"  {name}").strip()
    # Each its own: a method without a line of its own would show the line it inherits from its parent's docstring.
    assert len(set(said.values())) == len(said), said
    assert not any("``" in line for line in said.values()), said


@pytest.mark.parametrize(
    "typed,meant",
    [
        ("--feedback.label", "--feedback.labels"),
        ("--total-step", "--total-steps"),
        ("--sac.precison", "--sac.precision"),
    ],
)
def test_a_mistyped_flag_gets_the_nearest_of_the_method_s_flags(typed, meant, capsys):
    with pytest.raises(SystemExit) as end:
        cli.parse(["pebble", *TINY, typed, "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert end.value.code == 2 and len(err) == 1, err
    assert f"unrecognized flag {typed}; did you mean {meant}?" in err[0], err
    # The nearest is found among every flag this method reads (difflib), not among a fixed list.
    nearest = difflib.get_close_matches(typed, list(cli_args.flag_names(cli.parse(["pebble", *TINY]).config, "")), 1)
    assert nearest == [meant]


UNUSED_AT_DEFAULT = [
    (["sac", *TINY], "--feedback.labels", "feedback"),  # the preset's own value: still refused
    (["sac", *TINY], "--reward.lr", "reward"),
    (["pebble", *TINY], "--rebel.lam", "rebel"),
    (["pebble", *TINY], "--drqv2.nstep", "drqv2"),
    (["drqv2", "--task", "probe_point_pixels"], "--sac.hidden", "sac"),
    (["pebble", *TINY], "--human.port", "human"),
]


@pytest.mark.parametrize("argv,flag,part", UNUSED_AT_DEFAULT, ids=[f for _, f, _ in UNUSED_AT_DEFAULT])
def test_a_flag_the_method_does_not_use_is_refused_even_at_its_default_value(argv, flag, part, capsys):
    args = cli.parse(argv)
    capsys.readouterr()
    section = args if part == "human" else args.config
    default = getattr(getattr(section, part), flag.split(".", 1)[1].replace("-", "_"))
    with pytest.raises(SystemExit) as end:
        cli.parse([*argv, flag, str(default)])
    err = capsys.readouterr().err.strip().splitlines()
    assert end.value.code == 2 and len(err) == 1 and flag in err[0] and "ignore" in err[0], err


def test_the_human_teacher_s_flags_are_listed_with_it_only(capsys, monkeypatch):
    plain = _flags(_help(["pebble", "--help"], capsys, monkeypatch))
    human = _flags(_help(["pebble", "--teacher", "human", "--help"], capsys, monkeypatch))
    assert "human" not in plain and {"--human.host", "--human.port", "--human.labels"} <= set(human["human"])
    assert "--teacher-grid" in plain["options"] and "--teacher-grid" not in human["options"]
    assert len([flag for group in human.values() for flag in group]) <= MOST_FLAGS


def test_a_flag_help_leaves_out_is_still_set(capsys, monkeypatch):
    brief = _flags(_help(["sac", *TINY, "--help"], capsys, monkeypatch))
    assert "--sac.gamma" not in brief["sac"] and "--solver" not in brief["env"]
    args = cli.parse(["sac", *TINY, "--sac.gamma", "0.9", "--solver", "dm_control", "--video-steps", "0"])
    assert (args.config.sac.gamma, args.config.env.solver, args.video_steps) == (0.9, "dm_control", 0)


def test_the_method_word_and_algo_give_the_same_run():
    word = cli.parse(["rebel", *TINY, "--rebel.lam", "0.1", "--seeds", "2"])
    flag = cli.parse([*TINY, "--algo", "rebel", "--rebel.lam", "0.1", "--seeds", "2"])
    assert word == flag and word.config.algo == "rebel"
    assert cli.parse(TINY).config.algo == "sac"  # no method: the preset's


@pytest.mark.parametrize(
    "old,new,field", [("--hidden", "--sac.hidden", "sac"), ("--labels", "--feedback.labels", "feedback")]
)
def test_a_flag_of_the_older_spelling_is_refused_naming_the_new_one(old, new, field, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.parse(["pebble", *TINY, old, "16"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1 and err[0].startswith(f"error: {old} is now {new}"), err
    cfg = cli.parse(["pebble", *TINY, new, "16"]).config
    assert getattr(getattr(cfg, field), old[2:]) == 16


@pytest.mark.parametrize("task", ["walker_walk", "cheetah_run", "metaworld_drawer-open", "quadruped_run"])
def test_a_mistyped_task_gets_the_task_it_misspells(task, capsys):
    typed = task[:3] + task[4:]  # one letter dropped
    with pytest.raises(SystemExit) as end:
        cli.parse(["pebble", *TINY, "--task", typed])
    err = capsys.readouterr().err.strip().splitlines()
    assert end.value.code == 2 and len(err) == 1, err
    assert f"env.task={typed!r} is invalid (did you mean {task}?)" in err[0], err


def test_the_task_flag_s_help_names_every_registered_task_family(capsys, monkeypatch):
    """``--task``'s help names each dm_control task and each Meta-World task the registry builds."""
    from rebel_jax import envs  # noqa: PLC0415

    text = " ".join(_help(["sac", "--help"], capsys, monkeypatch).replace("│", " ").split())
    for task in (*envs.TASKS, *envs.METAWORLD_TASKS):
        assert task.removeprefix("metaworld_") in text, task
    assert "metaworld_<name>" in text
