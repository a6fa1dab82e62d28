"""Bad command lines get one line naming the field and what is allowed, exit status 2, and no run directory.

Everything here fails before compiling anything, so it runs ``cli.main`` in this process. Also:
the CPU-deadlock flag, the label-budget warning, and strict JSON records.
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import gc
import json
import math
import pathlib
import re
import shlex
import sys

import jax
import numpy as np
import pytest
from tyro import _unsafe_cache as tyro_cache

from rebel_jax.config import PRESETS
from rebel_jax.run import cli
from rebel_jax.run.logging import RunLogger
from rebel_jax.train import Trainer

TINY = ["--preset", "tiny", "--task", "probe_point", "--no-progress", "--no-tensorboard"]


def _refused(argv: list[str], capsys) -> str:
    """Runs the CLI (a METHOD word first, then :data:`TINY`), asserts exit status 2 and a one-line error; returns
    that line."""
    method = argv[:1] if argv and not argv[0].startswith("-") else []
    with pytest.raises(SystemExit) as exit_info:
        cli.main([*method, *TINY, *argv[len(method) :]])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


BAD = {
    "utd-inf": (["--sac.utd", "inf"], ["sac.utd=inf", "allowed"]),
    "utd-absurd": (["--sac.utd", "1000000"], ["sac.utd=1000000.0", "(0, 100]"]),
    "init-temperature-inf": (["--sac.init-temperature", "inf"], ["sac.init_temperature=inf", "finite"]),
    "lam-grid-nan": (["--algo", "rebel", "--lam-grid", "0", "nan"], ["lam_grid=(0.0, nan)", "finite"]),
    "label-capacity": (
        ["--algo", "pebble", "--feedback.labels", "60", "--reward.label-capacity", "10"],
        ["reward.label_capacity=10", ">= feedback.labels=60"],
    ),
    "total-steps": (["--total-steps", "3000"], ["train.total_steps=3000", "multiple of train.steps_per_round=2000"]),
    "run-dir-empty": (["--run-dir", ""], ["run_dir=''", "allowed a directory path"]),
    "run-dir-name-too-long": (["--run-dir", "r" * 300], ["run_dir='rrr", "the file system refuses the name"]),
    "run-dir-proc": (["--run-dir", "/proc/rebel_jax_test/run"], ["run_dir='/proc/rebel_jax_test/run'", "writable"]),
    "resume-and-overwrite": (["--run-dir", "r", "--resume", "--overwrite"], ["overwrite", "--resume"]),
    "distributed-without-run-dir": (["--distributed"], ["run_dir=None", "--distributed", "share"]),
    # Settings the run would silently ignore (the tiny preset's algo is sac).
    "labels-with-sac": (
        ["--feedback.labels", "-3"],
        ["feedback settings", "with sac on", "feedback only with a preference algo"],
    ),
    "teacher-with-sac": (["--teacher", "equal"], ["teacher settings", "teacher only with a preference algo"]),
    "rebel-with-pebble": (
        ["--algo", "pebble", "--rebel.lam", "0.1"],
        ["rebel settings", "rebel only with --algo rebel"],
    ),
    "drqv2-on-a-state-task": (["--drqv2.nstep", "1"], ["drqv2 settings", "drqv2 only with a pixel task"]),
    "obs-state-on-a-pixel-task": (
        ["--obs", "state", "--task", "walker_walk_pixels"],
        ["obs='state'", "'walker_walk_pixels'", "--obs pixels, or --task walker_walk"],
    ),
    "obs-unknown": (["--obs", "depth"], ["argument --obs", "invalid choice: 'depth'", "'state', 'pixels'"]),
    "preset-unknown": (["--preset", "huge"], ["argument --preset", "invalid choice: 'huge'", "'paper'"]),
    "obs-pixels-without-a-pixel-version": (
        ["--obs", "pixels", "--task", "walker_fly"],
        ["env.task='walker_fly_pixels'"],
    ),
    "quadruped-pixels": (
        ["--task", "quadruped_walk_pixels"],
        ["env.task='quadruped_walk_pixels'", "quadruped_walk has no pixel version", "walker_walk_pixels"],
    ),
    "obs-pixels-on-the-quadruped": (
        ["--obs", "pixels", "--task", "quadruped_run"],
        ["env.task='quadruped_run_pixels'", "quadruped_run has no pixel version", "spheres and capsules only"],
    ),
    "task-unknown": (["--task", "quadruped_fly"], ["env.task='quadruped_fly'", "'quadruped_walk'", "'walker_walk'"]),
    "relabel-rows-zero": (
        ["--task", "probe_point_pixels", "--algo", "pebble", "--pixel-reward.relabel-rows", "0"],
        ["pixel_reward.relabel_rows=0 is invalid", ">= 1"],
    ),
    "old-sac-spelling": (["--hidden", "16"], ["--hidden is now --sac.hidden", "--drqv2.*"]),
    "old-feedback-spelling": (["--per-session=4"], ["--per-session is now --feedback.per-session"]),
    "method-unknown": (["pebbel"], ["method 'pebbel' is invalid", "pebble", "METHOD [FLAGS]"]),
    "method-not-first": (["--seeds", "2", "pebble"], ["unrecognized flag pebble", "--help"]),
    "value-not-a-number": (["--seeds", "two"], ["Error parsing --seeds", "'two'", "--help lists the flags"]),
    "value-not-a-choice": (["--sac.precision", "fp8"], ["'fp8'", "--sac.precision", "'bf16'"]),
    "value-missing": (["--seeds"], ["--seeds", "Expected 1 values"]),
    "flag-unknown": (["--sac.hiden", "3"], ["unrecognized flag --sac.hiden", "--help-all"]),
    "method-and-algo-differ": (["pebble", "--algo", "surf"], ["algo='surf'", "after the method pebble"]),
    "pixel-segment-longer-than-an-episode": (  # the pixel trainer's own check, before anything is written
        ["pebble", "--task", "probe_point_pixels", "--num-envs", "2", "--episode-length", "20", "--total-steps", "60"]
        + ["--seed-steps", "20", "--steps-per-round", "20", "--eval-every", "20", "--feedback.interval", "20"]
        + ["--feedback.labels", "12", "--query.segment-length", "15"],
        ["query.segment_length=15 is invalid", "one episode"],
    ),
    "precision-on-pixels": (
        ["--task", "probe_point_pixels", "--algo", "drqv2", "--sac.precision", "bf16", "--surf.crop", "2"],
        ["sac, surf settings", "'probe_point_pixels'", "sac only with a state task; surf only with --algo surf"],
    ),
}


@pytest.mark.parametrize("argv,expected", BAD.values(), ids=BAD.keys())
def test_a_bad_flag_is_one_line_naming_it_and_creates_nothing(tmp_path, monkeypatch, capsys, argv, expected):
    monkeypatch.chdir(tmp_path)
    line = _refused(argv, capsys)
    for part in expected:
        assert part in line, line
    assert list(tmp_path.iterdir()) == []


def test_distributed_with_a_process_count_that_is_no_number_is_refused(tmp_path, monkeypatch, capsys):
    # Refused before jax.distributed.initialize, which would wait for the other processes.
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "127.0.0.1:1")
    monkeypatch.setenv("JAX_NUM_PROCESSES", "two")
    monkeypatch.setenv("JAX_PROCESS_ID", "0")
    line = _refused(["--distributed", "--run-dir", str(tmp_path / "run")], capsys)
    assert "JAX_NUM_PROCESSES" in line and "'two'" in line, line
    assert list(tmp_path.iterdir()) == []


def test_a_run_dir_that_is_a_file_is_refused(tmp_path, capsys):
    path = tmp_path / "file"
    path.write_text("not a directory")
    line = _refused(["--run-dir", str(path)], capsys)
    assert f"run_dir='{path}'" in line and "existing file" in line
    assert path.read_text() == "not a directory"


def test_a_run_dir_holding_a_run_is_refused_without_resume_or_overwrite(tmp_path, capsys):
    (tmp_path / "metrics.jsonl").write_text('{"round": 0}\n')
    line = _refused(["--run-dir", str(tmp_path)], capsys)
    assert "metrics.jsonl" in line and "--resume" in line and "--overwrite" in line
    assert (tmp_path / "metrics.jsonl").read_text() == '{"round": 0}\n'


@pytest.mark.parametrize(
    "argv,what,padding",
    [
        (["--seeds", "3"], "seeds=3 on 2 devices: each runs 2", 1),
        (["--algo", "rebel", "--seeds", "1", "--lam-grid", "0", "-0.01", "-0.1"], "3 columns on 2 devices", 1),
        (["--seeds", "4"], None, 0),
    ],
    ids=["seeds", "lam-grid-columns", "even"],
)
def test_columns_that_do_not_split_over_the_devices_are_padded_with_a_note(capsys, argv, what, padding):
    cli.check_devices(cli.parse([*TINY, *argv]), 2)
    err = capsys.readouterr().err
    if what is None:
        assert err == ""
    else:
        assert what in err and f"{padding} column(s) repeat the last one" in err, err


def test_a_host_teacher_on_several_devices_is_refused(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(jax, "device_count", lambda: 2)
    line = _refused(
        ["--algo", "pebble", "--teacher", "replay", "--human.labels", __file__, "--run-dir", str(tmp_path / "r")],
        capsys,
    )
    assert "--teacher replay labels one column on one device, and 2 are visible" in line, line
    assert not (tmp_path / "r").exists()


def test_more_labels_than_the_run_can_ask_are_warned_about(capsys):
    args = cli.parse([*TINY, "--algo", "pebble", "--feedback.labels", "1000"])
    sessions = sum(bool(Trainer(args.config).session_due(r)[0]) for r in range(args.config.train.num_rounds))
    most = sessions * args.config.feedback.queries
    assert cli.feedback_sessions(args.config) == sessions and 0 < most < 1000
    err = capsys.readouterr().err
    assert "feedback.labels=1000" in err and f"= {most}" in err, err
    cli.parse([*TINY, "--algo", "pebble", "--feedback.labels", str(most)])
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "environ,expected",
    [
        ({"JAX_PLATFORMS": "cpu"}, cli.NO_CPU_DEADLOCK),
        ({"JAX_PLATFORMS": "cpu", "XLA_FLAGS": "--xla_dump_to=/tmp/x"}, f"--xla_dump_to=/tmp/x {cli.NO_CPU_DEADLOCK}"),
        ({"JAX_PLATFORMS": "cuda"}, None),
        ({"JAX_PLATFORMS": "cpu", "XLA_FLAGS": "--xla_cpu_enable_concurrency_optimized_scheduler=true"}, "unchanged"),
    ],
    ids=["cpu", "cpu-other-flags", "gpu", "user-choice"],
)
def test_the_cli_turns_off_the_deadlocking_cpu_scheduler_on_cpu_only(environ, expected):
    before = environ.get("XLA_FLAGS")
    cli.avoid_cpu_deadlock(environ)
    assert environ.get("XLA_FLAGS") == (before if expected == "unchanged" else expected)


def _strict_loads(text: str):
    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    return json.loads(text, parse_constant=refuse)


def test_without_the_bar_each_round_prints_one_plain_line(tmp_path, capsys):
    logger = RunLogger(tmp_path, 2_000, progress=False, tensorboard=False)
    for r, (eval_return, labels) in enumerate([(np.nan, 0.0), (12.5, 40.0)]):
        metrics = {"eval_return": np.array([eval_return, eval_return]), "labels_used": np.array([labels, labels])}
        logger.write(1_000 * (r + 1), metrics, {"env_steps_per_s": 250.0 * (r + 1)})
    logger.close()
    out = capsys.readouterr()
    assert out.out.splitlines() == [
        "1,000/2,000 steps  steps/s 250  labels 0",  # no evaluation yet: its mean is null, so not shown
        "2,000/2,000 steps  steps/s 500  eval 12.5  labels 40",
    ]
    assert "\r" not in out.err  # no bar


def test_metrics_are_strict_json_and_means_do_not_hide_a_diverged_seed(tmp_path, capsys):
    logger = RunLogger(tmp_path, 100, progress=True, tensorboard=False, names=["seed 0", "seed 1 (lambda 1)"])
    nan, inf = math.nan, math.inf
    # Round 1: seed 1 has no session (NaN), nothing diverged. Round 2: seed 1 diverged.
    for r, (loss, diverged) in enumerate([([1.0, 3.0], [0.0, 0.0]), ([1.0, inf], [0.0, 1.0])]):
        metrics = {"loss": np.array(loss), "reward_loss": np.array([2.0, nan]), "diverged": np.array(diverged)}
        logger.write(10 * (r + 1), metrics, {"round": r})
    logger.close()
    assert "DIVERGED=seed 1 (lambda 1)" in capsys.readouterr().err  # on the progress line
    ok, bad = (_strict_loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines())
    assert ok["status"] == "ok" and ok["loss_mean"] == 2.0 and ok["reward_loss_mean"] == 2.0
    assert ok["reward_loss"] == [2.0, None] and ok["diverged"] == [False, False]
    assert bad["status"] == "diverged" and bad["diverged"] == [False, True]
    assert bad["loss"] == [1.0, None] and bad["loss_mean"] is None and bad["reward_loss_mean"] is None


@pytest.mark.parametrize(
    "argv,same_as",
    [
        # --obs pixels names the pixel task; without --preset a walker or cheetah pixel task takes SURF's pixel preset.
        (["--obs", "pixels", "--task", "walker_walk"], ["--preset", "surf_pixels_walker"]),
        (["--task", "walker_walk_pixels"], ["--preset", "surf_pixels_walker"]),
        (["--obs", "pixels"], ["--preset", "surf_pixels_walker"]),  # the paper preset's task, walker_walk
        (
            ["--obs", "pixels", "--task", "cheetah_run", "--algo", "drqv2"],
            ["--preset", "surf_pixels_cheetah", "--algo", "drqv2"],
        ),
        (
            ["--obs", "pixels", "--task", "walker_run"],
            ["--preset", "surf_pixels_walker", "--task", "walker_run_pixels"],
        ),
        # An explicit preset stays; --obs pixels on a pixel task, and --obs state on a state task, change nothing.
        (
            ["--preset", "paper", "--obs", "pixels", "--algo", "drqv2"],
            ["--preset", "paper", "--algo", "drqv2", "--task", "walker_walk_pixels"],
        ),
        (
            ["--preset", "tiny", "--obs", "pixels", "--task", "probe_point", "--algo", "drqv2"],
            ["--preset", "tiny", "--task", "probe_point_pixels", "--algo", "drqv2"],
        ),
        (["--obs", "pixels", "--task", "cheetah_run_pixels"], ["--preset", "surf_pixels_cheetah"]),
        (["--obs", "state", "--task", "cheetah_run"], ["--preset", "paper", "--task", "cheetah_run"]),
        # A quadruped task without a preset takes B-Pref's quadruped settings.
        (["--task", "quadruped_walk"], ["--preset", "paper_quadruped"]),
    ],
    ids=[
        "walker",
        "pixel-task",
        "default-task",
        "cheetah",
        "walker-run",
        "paper",
        "tiny-probe",
        "pixels-twice",
        "state",
        "quadruped",
    ],
)
def test_obs_and_a_pixel_task_pick_the_task_and_its_preset(argv, same_as):
    config = cli.parse(argv).config
    assert config == cli.parse(same_as).config
    assert config.pixels == (config.env.task.endswith("_pixels"))


def test_a_pixel_run_without_a_preset_gets_surf_s_pixel_protocol():
    config = cli.parse(["--obs", "pixels", "--task", "walker_walk", "--algo", "surf"]).config
    assert config.env.task == "walker_walk_pixels" and config.algo == "surf"
    walker = PRESETS["surf_pixels_walker"]
    assert (config.feedback, config.train, config.surf, config.drqv2) == (
        walker.feedback,
        walker.train,
        walker.surf,
        walker.drqv2,
    )
    assert config.train != PRESETS["paper"].train


def test_the_preset_label_capacity_is_not_a_user_choice():
    # The preset's default capacity is below a large budget: not an error (the store holds the budget).
    assert PRESETS["tiny"].reward.label_capacity < 2000
    args = cli.parse([*TINY, "--algo", "pebble", "--feedback.labels", "2000", "--total-steps", "100000"])
    assert args.config.feedback.labels == 2000


def _commands(tree):
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from ([v] if k == "command" and isinstance(v, str) else _commands(v))
    elif isinstance(tree, list):
        for v in tree:
            yield from _commands(v)


def test_recorded_commands_are_portable():
    root = pathlib.Path(__file__).parents[1]
    records = [*(root / "results").rglob("*.json"), *(root / "benchmarks" / "results").rglob("*.json")]
    commands = [c for path in records for c in _commands(json.loads(path.read_text()))]
    assert len(commands) > 10
    for command in commands:
        assert command.startswith("python "), command  # as typed, not the absolute path of a file
    assert cli.command_line(["--run-dir", "a b"]) == "python -m rebel_jax.train --run-dir 'a b'"


class _ParsesWhenCollected:
    """Cyclic garbage whose finalizer parses source (as the traceback of an asyncio Task orbax leaves behind after
    a failed restore does when it is logged) and leaves another one behind, so that one is always pending."""

    live = True

    def __init__(self):
        self.cycle = self

    def __del__(self):
        if _ParsesWhenCollected.live:
            ast.parse("x = (1 + 2) * 3")
            _ParsesWhenCollected()


@contextlib.contextmanager
def _collections_that_parse_source():
    """Every allocation collects the youngest generation, and each collection runs a finalizer that parses source.
    (A context, not a fixture: a failure inside is reported after it ends, when reporting can parse source.)"""
    threshold = gc.get_threshold()
    _ParsesWhenCollected.live = True
    _ParsesWhenCollected()
    gc.set_threshold(1)
    try:
        yield
    finally:
        gc.set_threshold(*threshold)
        _ParsesWhenCollected.live = False
        gc.collect()


def test_parse_survives_collections_whose_finalizers_parse_source():
    """CI failed once in ``parse`` with CPython 3.11's "AST constructor recursion depth mismatch" (gh-106905):
    tyro reads docstrings with ``ast.parse``, and a finalizer run in the middle parsed source too."""
    tyro_cache.clear_cache()  # tyro caches the parsed docstrings; parse them again
    with _collections_that_parse_source():
        if (3, 11) <= sys.version_info[:3] <= (3, 11, 7):  # where the hazard was seen (CI's Python, this one)
            with pytest.raises(SystemError, match="recursion depth mismatch"):
                ast.parse(pathlib.Path(cli.__file__).read_text())
        args = cli.parse(["--preset", "demo", "--seed", "3"])
    assert args.config.train.seed == 3


def readme_train_commands(text: str) -> list[str]:
    """The flags of every ``python -m rebel_jax.train`` command in ``text``: in indented blocks (backslash
    continuations joined, environment variables before it and a trailing ``&`` or comment left out) and in inline
    code. Commands with ``...`` in place of flags, or ``METHOD`` in place of a method, are left out."""
    joined = re.sub(r"\\\n\s*", " ", text)
    pattern = r"(?:^ {4,}|`)(?:[A-Z_]+=\S+\s+)*python -m rebel_jax\.train((?: [^`#&\n]*)?)"
    found = [" ".join(m.group(1).split()) for m in re.finditer(pattern, joined, re.M)]
    return [flags for flags in found if "..." not in flags and "METHOD" not in flags]


def test_readme_train_commands_are_found_in_blocks_and_inline_code():
    text = (
        "Run `python -m rebel_jax.train --preset demo`, or\n\n"
        "    CUDA_VISIBLE_DEVICES=0 python -m rebel_jax.train --algo sac \\\n        --seeds 2   # two seeds\n"
        "    for i in 0 1; do\n      A=1 B=$i \\\n"
        "        python -m rebel_jax.train --seeds 2 --distributed &\n    done\n"
        "not code: python -m rebel_jax.train --nothing; `python -m rebel_jax.train ... --distributed`\n"
    )
    assert readme_train_commands(text) == ["--preset demo", "--algo sac --seeds 2", "--seeds 2 --distributed"]


def test_every_train_command_the_readme_shows_parses(capsys):
    """The README's commands stay valid as flags change (each one is parsed as the CLI would)."""
    commands = readme_train_commands((pathlib.Path(__file__).parents[1] / "README.md").read_text())
    assert len(commands) >= 10, commands
    for flags in commands:
        try:
            cli.parse(shlex.split(flags))
        except SystemExit as err:
            pytest.fail(f"README's `python -m rebel_jax.train {flags}` is refused: {capsys.readouterr().err}{err}")


@pytest.mark.parametrize("algo", ["sac", "pebble"])
def test_the_quadruped_preset_is_paper_with_b_prefs_quadruped_schedule(algo):
    """Only the task, SAC's learning rates, the run length and the label schedule differ from ``paper``; the preset
    is a valid run of both algorithms (B-Pref's quadruped scripts: run_sac.sh, 1000/oracle/run_PEBBLE.sh)."""
    quadruped, paper = PRESETS["paper_quadruped"], PRESETS["paper"]
    same = dataclasses.replace(quadruped, env=paper.env, sac=paper.sac, train=paper.train, feedback=paper.feedback)
    assert same == paper
    assert dataclasses.replace(quadruped.sac, actor_lr=paper.sac.actor_lr, critic_lr=paper.sac.critic_lr) == paper.sac
    assert dataclasses.replace(quadruped.train, total_steps=paper.train.total_steps) == paper.train
    assert quadruped.env.task == "quadruped_walk" and quadruped.sac.actor_lr < paper.sac.actor_lr
    dataclasses.replace(quadruped, algo=algo).validate()


def test_a_meta_world_task_on_a_gpu_with_the_jax_step_gets_a_note_naming_warp():
    """The note names --impl warp where a Meta-World task runs MJX's JAX step on a GPU, and only there."""
    task = ["--task", "metaworld_drawer-open"]
    note = cli.engine_note(cli.parse([*TINY, *task]), "gpu")
    assert note is not None and "--impl warp" in note and "\n" not in note
    assert cli.engine_note(cli.parse([*TINY, *task]), "cpu") is None
    assert cli.engine_note(cli.parse(TINY), "gpu") is None  # not a Meta-World task
