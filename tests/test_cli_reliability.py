"""Run directories, resumes and divergence of ``python -m rebel_jax.train``, on 3-round probe runs.

Most runs call ``cli.main`` in this process (their rounds load from the compilation cache the
other CLI tests fill: the same micro flags). Runs that must be killed are subprocesses that
SIGKILL themselves at a chosen point. Every resumed run is compared with one whole run.
"""

from __future__ import annotations

import json
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_cli_runs import MICRO_FLAGS as MICRO  # The same compiled round (test_train.MICRO, two seeds).
from test_cli_runs import ROUNDS, _metrics, _saved_arrays

from rebel_jax.run import cli, cli_outputs, loop, video
from rebel_jax.train import Trainer, seed_keys

ROOT = pathlib.Path(__file__).parents[1]

# ``python -m rebel_jax.train`` that SIGKILLs itself at KILL_AT: ``log:<env steps>`` right after
# logging that round, or ``save:<step>`` while orbax writes that checkpoint in the background.
KILLED_TRAIN = textwrap.dedent(
    """
    import os, runpy, signal, sys, time
    from rebel_jax.run.checkpoint import Checkpointer
    from rebel_jax.run.logging import RunLogger

    where, at = os.environ["KILL_AT"].split(":")

    def kill():
        os.kill(os.getpid(), signal.SIGKILL)

    def kill_once_writing(directory):
        # Orbax writes a step into <step>.orbax-checkpoint-tmp-* and renames it when complete.
        deadline = time.monotonic() + 2
        while time.monotonic() < deadline and not any(".orbax-checkpoint-tmp" in p.name for p in directory.iterdir()):
            time.sleep(0.0005)
        kill()

    write, save = RunLogger.write, Checkpointer.save

    def write_then_kill(self, env_steps, *args, **kwargs):
        write(self, env_steps, *args, **kwargs)
        if where == "log" and env_steps == int(at):
            kill()

    def save_killed(self, step, state, wait=True):
        if where == "save" and step == int(at):
            start_saving = self.manager.save

            def start_saving_then_kill(*args, **kwargs):
                start_saving(*args, **kwargs)  # returns with the write under way in orbax's background thread
                kill_once_writing(self.directory)

            self.manager.save = start_saving_then_kill
        save(self, step, state, wait)

    RunLogger.write, Checkpointer.save = write_then_kill, save_killed
    sys.argv[0] = "rebel_jax.train"
    runpy.run_module("rebel_jax.train", run_name="__main__")
    """
)


def _main(run_dir: pathlib.Path, *flags: str) -> dict:
    return cli.main([*MICRO, "--run-dir", str(run_dir), *flags])


def _final(run_dir: pathlib.Path) -> dict:
    return json.loads((run_dir / "final.json").read_text())


def _steps_on_disk(run_dir: pathlib.Path) -> list[int]:
    return sorted(int(p.name) for p in (run_dir / "checkpoints").iterdir() if p.name.isdigit())


@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> pathlib.Path:
    """One uninterrupted 3-round run."""
    run_dir = tmp_path_factory.mktemp("whole") / "run"
    _main(run_dir)
    return run_dir


def _same_run(a: pathlib.Path, b: pathlib.Path, rounded: tuple[str, ...] = ()) -> None:
    """The same metrics, bit for bit but those named in ``rounded`` (within float32 rounding), and final results."""
    rows_a, rows_b = _metrics(a), _metrics(b)
    for row_a, row_b in zip(rows_a, rows_b, strict=True):
        for key in rounded:
            if key in row_a or key in row_b:
                got, want = (np.asarray(row.pop(key), float) for row in (row_a, row_b))  # null: NaN
                np.testing.assert_allclose(got, want, rtol=1e-6, err_msg=key)
    assert rows_a == rows_b
    assert [row["round"] for row in _metrics(b)] == list(range(ROUNDS))
    assert _final(a) == _final(b) and _final(b)["status"] == "completed"


def _same_checkpoint(a: pathlib.Path, b: pathlib.Path) -> None:
    """The two runs' last checkpoints hold the same leaves, bit for bit (replay buffer, networks, keys)."""
    saved_a, saved_b = _saved_arrays(a, ROUNDS), _saved_arrays(b, ROUNDS)
    assert saved_a.keys() == saved_b.keys() and len(saved_a) > 50
    for k in saved_a:
        np.testing.assert_array_equal(saved_a[k], saved_b[k], err_msg=f"leaf {k}")


def test_overwrite_replaces_a_run_and_the_record_is_portable(whole, tmp_path):
    again = tmp_path / "again"
    shutil.copytree(whole, again)
    (again / "metrics.jsonl").write_text('{"round": 0, "env_steps": 40, "stale": true}\n')
    _main(again, "--overwrite")
    _same_run(whole, again)
    assert _steps_on_disk(again) == [ROUNDS - 1, ROUNDS]
    command = json.loads((again / "meta.json").read_text())["command"]
    assert command.startswith("python -m rebel_jax.train --preset tiny") and command.endswith("--overwrite")


def test_a_task_without_success_keeps_final_json_s_keys(whole):
    # Only a task that reports success (Meta-World's) adds final_eval_success and success_mean.
    keys = ["status", "diverged", "final_eval_return", "mean", "std", "random_return", "random_mean"]
    assert list(_final(whole)) == keys


def test_a_failing_learning_curve_is_a_warning_after_the_runs_results(whole, tmp_path, monkeypatch, capsys):
    # The 5-seed DrQ-v2 run of 2026-11-25 ended with a traceback in its plot, 30 minutes in; the figure is a
    # convenience drawn after final.json, so its failure must not fail the run.
    def broken(run_dir, metric="eval_return"):
        raise ValueError("cannot reshape")

    monkeypatch.setattr(cli_outputs.plots, "load_runs", broken)
    _main(tmp_path / "run", "--checkpoint-every", "0")
    out = capsys.readouterr()
    assert "warning: learning_curve.png not written (ValueError: cannot reshape)" in out.err, out.err
    assert "final evaluation return over 2 seed(s)" in out.out  # the summary is still printed
    final = _final(whole)  # its spread is the sample std (ddof 1), as every results table gives it
    assert final["std"] == pytest.approx(np.std(final["final_eval_return"], ddof=1))
    assert f"{np.mean(final['final_eval_return']):.1f} +- {final['std']:.1f} (sample std)" in out.out
    assert "success rate" not in out.out  # the task reports no success
    assert not (tmp_path / "run" / "learning_curve.png").exists()
    _same_run(whole, tmp_path / "run")  # final.json and metrics.jsonl as a run without the failure


def test_resume_refuses_changed_fields_naming_them(whole, tmp_path, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(whole, run_dir)
    before = {name: (run_dir / name).read_bytes() for name in ("config.json", "meta.json", "metrics.jsonl")}
    with pytest.raises(SystemExit) as exit_info:
        _main(run_dir, "--resume", "--sac.actor-lr", "0.001", "--sac.gamma", "0.9", "--seed", "3", "--seeds", "4")
    assert exit_info.value.code == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line
    for field in ("sac.actor_lr (saved 0.0005, now 0.001)", "sac.gamma", "train.seed", "seeds (saved 2, now 4)"):
        assert field in line, line
    assert {name: (run_dir / name).read_bytes() for name in before} == before

    # A run saved before a config field existed resumes if the field is at its default, not otherwise.
    saved = json.loads((run_dir / "config.json").read_text())
    del saved["sac"]["precision"], saved["sac"]["hidden"]  # tf32 is the default; the flags give hidden 16
    (run_dir / "config.json").write_text(json.dumps(saved))
    args = cli.parse([*MICRO, "--run-dir", str(run_dir), "--resume"])
    assert cli.resume_changes(run_dir, args) == ["sac.hidden (saved '<absent>', now 16)"]


def test_resume_with_checkpoint_every_0_extends_a_run_to_more_steps(whole, tmp_path, capsys):
    short = tmp_path / "short"
    _main(short, "--total-steps", str(40 * (ROUNDS - 1)))
    assert _steps_on_disk(short) == [ROUNDS - 2, ROUNDS - 1] and _final(short)["status"] == "completed"
    damaged = tmp_path / "damaged"
    shutil.copytree(short, damaged)

    _main(short, "--resume", "--checkpoint-every", "0", "--total-steps", str(40 * ROUNDS))
    _same_run(whole, short)  # bit for bit: the replay buffer grew, nothing else changed
    assert _steps_on_disk(short) == [ROUNDS - 2, ROUNDS - 1]  # found the checkpoints, wrote none
    assert json.loads((short / "config.json").read_text())["train"]["total_steps"] == 40 * ROUNDS
    assert json.loads((short / "meta.json").read_text())["resumed"][0]["from_round"] == ROUNDS - 1
    capsys.readouterr()

    # The latest checkpoint damaged, and the last log line cut mid-write: back to the one before.
    for data in (damaged / "checkpoints" / str(ROUNDS - 1)).rglob("d/*"):
        data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    lines = (damaged / "metrics.jsonl").read_text().splitlines(keepends=True)
    (damaged / "metrics.jsonl").write_text("".join(lines[:-1]) + lines[-1][:50])
    _main(damaged, "--resume", "--total-steps", str(40 * ROUNDS))
    err = capsys.readouterr().err
    assert f"checkpoint {ROUNDS - 1} in" in err and "unreadable" in err and "cut mid-write" in err, err
    assert "differ from their checksums" in err, err  # found before orbax read anything of it
    _same_run(whole, damaged)
    assert [p.name.split("-")[0] for p in (damaged / "checkpoints_damaged").iterdir()] == [str(ROUNDS - 1)]


def test_resume_refuses_a_checkpoint_of_another_state_and_keeps_the_run(whole, tmp_path, capsys):
    """A checkpoint that reads but holds other leaves (written by other code) is not "damaged": nothing is
    moved aside, the log is not cut back to round 0, and the error says which code wrote it."""
    from rebel_jax.run.checkpoint import Checkpointer

    run_dir = tmp_path / "run"
    shutil.copytree(whole, run_dir)
    shutil.rmtree(run_dir / "checkpoints")
    other = Checkpointer(run_dir / "checkpoints")
    other.save(ROUNDS, {"params": jnp.zeros(3), "buffer": jnp.ones((2, 5))})
    other.close()
    before = {name: (run_dir / name).read_bytes() for name in ("config.json", "meta.json", "metrics.jsonl")}
    with pytest.raises(SystemExit) as exit_info:
        _main(run_dir, "--resume", "--total-steps", str(40 * (ROUNDS + 1)))
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    commit = json.loads(before["meta.json"])["git_commit"]
    assert f"checkpoint {ROUNDS} in" in err and "holds another state (" in err and f"git_commit {commit}" in err, err
    assert {name: (run_dir / name).read_bytes() for name in before} == before
    assert _steps_on_disk(run_dir) == [ROUNDS] and not (tmp_path / "run" / "checkpoints_damaged").exists()


def test_checkpoint_of_other_shapes_is_a_mismatch_not_damage(tmp_path):
    from rebel_jax.run.checkpoint import Checkpointer, CheckpointMismatch

    ckpt = Checkpointer(tmp_path / "checkpoints")
    ckpt.save(1, {"a": jnp.zeros(3), "b": jnp.ones(2)})
    with pytest.raises(CheckpointMismatch, match=r"leaf 0: saved \(3,\), now \(4,\)"):
        ckpt.restore({"a": jnp.zeros(4), "b": jnp.ones(2)})
    with pytest.raises(CheckpointMismatch, match="2 leaves saved, 3 now"):
        ckpt.restore({"a": jnp.zeros(3), "b": jnp.ones(2), "c": jnp.ones(1)})
    assert ckpt.steps() == [1] and not (tmp_path / "checkpoints_damaged").exists()
    step, state = ckpt.restore({"a": jnp.ones(3), "b": jnp.zeros(2)})
    assert step == 1 and float(state["a"].sum()) == 0.0 and float(state["b"].sum()) == 2.0
    ckpt.close()


def _poison_seed_1_before_round(round_index: int):
    """A ``train.compiled`` whose round receives seed 1's actor parameters as NaN at ``round_index``."""
    from rebel_jax import train

    def compiled(trainer, sharding=None):
        init, round_fn, evaluate = train.compiled(trainer, sharding)

        def poisoned_round(state, r):
            if int(r) == round_index:
                actor = jax.tree.map(lambda x: x.at[1].set(jnp.nan), state.agent.actor_params)
                state = state.replace(agent=state.agent.replace(actor_params=actor))
            return round_fn(state, r)

        return init, poisoned_round, evaluate

    return compiled


def test_a_diverged_seed_stops_the_run_naming_it_then_continues_on_request(whole, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(loop, "compiled", _poison_seed_1_before_round(ROUNDS - 1))
    run_dir = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_info:
        _main(run_dir)
    assert exit_info.value.code == cli.EXIT_DIVERGED
    err = capsys.readouterr().err
    assert f"round {ROUNDS - 1}: seed 1 diverged" in err and "--on-divergence continue" in err, err
    last, healthy = _metrics(run_dir)[-1], _metrics(whole)[-1]
    assert last["status"] == "diverged" and last["diverged"] == [False, True]
    assert last["actor_loss"][1] is None and last["actor_loss_mean"] is None and last["eval_return_mean"] is None
    for key in ("actor_loss", "critic_loss", "q", "eval_return", "train_return"):
        assert last[key][0] == healthy[key][0], key  # seed 0 is unharmed
    assert _metrics(run_dir)[:-1] == _metrics(whole)[:-1]
    assert _final(run_dir)["status"] == "diverged" and _final(run_dir)["diverged"] == ["seed 1"]
    assert _steps_on_disk(run_dir) == [ROUNDS - 2, ROUNDS - 1]  # the diverged round is not checkpointed

    _main(run_dir, "--resume", "--on-divergence", "continue")
    final = _final(run_dir)
    assert final["status"] == "diverged" and final["diverged"] == ["seed 1"]
    assert final["final_eval_return"][0] == _final(whole)["final_eval_return"][0]
    assert final["final_eval_return"][1] is None and final["mean"] is None
    assert "warning: round 2: seed 1 diverged; going on" in capsys.readouterr().err
    for path in (run_dir / "final.json", run_dir / "metrics.jsonl"):
        assert "NaN" not in path.read_text() and "Infinity" not in path.read_text()


def _killed(run_dir: pathlib.Path, kill_at: str, *flags: str) -> str:
    """Runs the CLI in a subprocess (without conftest's deadlock workaround) until it kills itself; returns its output.

    The child keeps this process's other XLA flags and its environment (conftest's compile optimisation
    setting): its rounds must compute what this process's do, bit for bit.
    """
    env = dict(os.environ)
    env["XLA_FLAGS"] = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if f != cli.NO_CPU_DEADLOCK)
    env.update(
        PYTHONPATH=str(ROOT / "src"),
        JAX_COMPILATION_CACHE_DIR=str(jax.config.jax_compilation_cache_dir),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=str(jax.config.jax_persistent_cache_min_compile_time_secs),
        KILL_AT=kill_at,
    )
    cmd = [sys.executable, "-c", KILLED_TRAIN, *MICRO, "--run-dir", str(run_dir), *flags]
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == -signal.SIGKILL, out.stderr[-3000:]
    return out.stdout + out.stderr


@pytest.mark.parametrize(
    "kill_at,flags",
    [("log:40", ["--checkpoint-every", "2"]), ("save:2", [])],
    ids=["before-the-first-checkpoint", "during-a-checkpoint-save"],
)
def test_a_run_killed_anywhere_resumes_to_the_same_result(whole, tmp_path, capsys, kill_at, flags):
    run_dir = tmp_path / "run"
    output = _killed(run_dir, kill_at, *flags)
    assert "Failed to import" not in output  # MJX's warp messages go to logging
    meta = json.loads((run_dir / "meta.json").read_text())
    assert cli.NO_CPU_DEADLOCK in meta["xla_flags"]  # set by the CLI itself: the child's XLA_FLAGS lacked it
    assert not (run_dir / "final.json").exists()
    if kill_at.startswith("log"):
        assert _steps_on_disk(run_dir) == [] and len(_metrics(run_dir)) == 1
    else:
        # Usually a partial 2.orbax-checkpoint-tmp is left; if the write won the race, step 2 is complete.
        assert _steps_on_disk(run_dir) in ([1], [1, 2])
    _main(run_dir, "--resume", *flags)
    if kill_at.startswith("log"):
        assert "no checkpoint" in capsys.readouterr().err
    _same_run(whole, run_dir)
    assert _steps_on_disk(run_dir) == [ROUNDS - 1, ROUNDS]  # an interrupted save does not block saving that step
    _same_checkpoint(whole, run_dir)


def test_time_limit_ends_after_a_round_with_its_checkpoint_and_resume_finishes_the_same_run(whole, tmp_path, capsys):
    run_dir = tmp_path / "timed"
    _main(run_dir, "--time-limit", "1e-9")
    out = capsys.readouterr().out.splitlines()
    # --no-progress: a line before the first round's compile, one per round, then the stop.
    assert (
        out[0]
        == f"0/120 steps: compiling the round program, then round 1 of {ROUNDS} (minutes for a large preset on a CPU)"
    )
    assert out[1].startswith("40/120 steps") and "stopped after round 0" in out[2]
    assert _steps_on_disk(run_dir) == [1] and not (run_dir / "final.json").exists() and len(_metrics(run_dir)) == 1
    _main(run_dir, "--resume")
    assert capsys.readouterr().out.startswith(f"40/120 steps: compiling the round program, then round 2 of {ROUNDS}")
    _same_run(whole, run_dir)
    _same_checkpoint(whole, run_dir)


# A pixel PEBBLE run of 3 rounds (16x16 probe frames, episodes of 10 agent steps): seed steps, then a session of 4
# labels at the starts of rounds 1 and 2 (like test_pixel_preference.MICRO, through the CLI).
PIXEL = (
    "--preset tiny --obs pixels --task probe_point --algo pebble --num-envs 2 --episode-length 20"
    " --drqv2.feature-dim 8 --drqv2.hidden 16 --drqv2.batch-size 16 --drqv2.nstep 3 --drqv2.std-steps 40"
    " --total-steps 60 --seed-steps 20 --steps-per-round 20 --eval-every 20 --eval-episodes 1"
    " --feedback.labels 8 --feedback.per-session 4 --feedback.interval 20 --query.segment-length 4"
    " --pretrain.reset-updates 2"
    " --pixel-reward.hidden 8 --pixel-reward.batch-size 4 --pixel-reward.max-epochs 3 --pixel-reward.lr 1e-3"
    " --pixel-reward.chunk 3 --seeds 2 --seed 7 --no-tensorboard --no-progress"
).split()


@pytest.mark.parametrize(
    "algo",
    [
        # All three in make test-heavy (PEBBLE's alone is about 110 s on 2 cores): make test covers the CLI's resume
        # on state runs (above) and a pixel run's whole state saved and restored, leaf by leaf (test_checkpoint.py).
        pytest.param([], marks=pytest.mark.heavy),
        # SURF's unlabelled pool and REBEL's kept evaluation frames are in the checkpoint too.
        pytest.param(
            [
                "--algo",
                "surf",
                "--surf.crop",
                "1",
                "--surf.pool-size",
                "8",
                "--surf.reward-update",
                "3",
                "--surf.ratio",
                "1",
            ],
            marks=pytest.mark.heavy,
        ),
        pytest.param(
            ["--algo", "rebel", "--rebel.lam", "0.001", "--rebel.horizon", "5", "--rebel.episodes", "1"],
            marks=pytest.mark.heavy,
        ),
    ],
    ids=["pebble", "surf", "rebel"],
)
def test_a_pixel_preference_run_extended_from_its_checkpoint_is_the_same_run(tmp_path, capsys, algo):
    # Its checkpoint holds the frame replay, the reward ensemble and the label store's segment copies (4 labels).
    flags, whole, extended = [*PIXEL, *algo], tmp_path / "whole", tmp_path / "extended"
    cli.main([*flags, "--run-dir", str(whole)])
    cli.main([*flags, "--run-dir", str(extended), "--total-steps", "40"])  # rounds 0 and 1: the first feedback session
    assert _steps_on_disk(extended) == [1, 2]
    assert [row["labels_used"] for row in _metrics(extended)] == [[0.0, 0.0], [4.0, 4.0]]
    cli.main([*flags, "--run-dir", str(extended), "--resume"])  # round 2, after the checkpoint of round 1
    # The replay's reward correlation sums over the replay's capacity (the run's steps: 60 here, 40 in the first
    # part), so XLA's full optimisation may add it up in another order.
    _same_run(whole, extended, rounded=("reward_correlation_replay", "reward_correlation_replay_mean"))
    assert _metrics(extended)[-1]["labels_used"] == [8.0, 8.0]
    _same_checkpoint(whole, extended)
    # `python -m rebel_jax.run.video RUN_DIR`'s policy of each column is the one final.json evaluated.
    final = _final(whole)["final_eval_return"]
    for column in range(2):
        trainer, step, params = video.load_policy(whole, column)
        assert isinstance(trainer, Trainer) and step == 3
        key = seed_keys(7, 2)[column]
        np.testing.assert_allclose(jax.jit(trainer.evaluate)(params, key), final[column], rtol=1e-4, atol=1e-4)


def test_a_checkpoint_slower_than_its_round_is_noted_once_with_a_larger_interval(whole, tmp_path, monkeypatch, capsys):
    from rebel_jax.run.checkpoint import Checkpointer

    save = Checkpointer.save

    def slow_save(self, step, state, wait=True):  # a probe round takes milliseconds; a large replay's save, seconds
        time.sleep(0.5)
        save(self, step, state, wait)

    monkeypatch.setattr(Checkpointer, "save", slow_save)
    run_dir = tmp_path / "run"
    _main(run_dir)
    notes = [line for line in capsys.readouterr().err.splitlines() if "checkpoint took" in line]
    assert len(notes) == 1, notes
    match = re.search(r"round (\d+)'s checkpoint took ([\d.]+) s, longer than the round \(([\d.]+) s\): "
                      r"--checkpoint-every (\d+) ", notes[0])  # fmt: skip
    assert match, notes[0]
    saving, seconds, every = float(match[2]), float(match[3]), int(match[4])
    assert saving >= 0.5 and every >= 4 * saving / max(seconds, 0.05) - 1
    _same_run(whole, run_dir)  # the run itself is unchanged
    assert _steps_on_disk(run_dir) == [ROUNDS - 1, ROUNDS]
