"""A user's method in a package of its own: found through a ``rebel_jax.methods`` entry point, given ``--NAME.*`` flags
from its config dataclass, its state carried per seed through checkpoints and ``--resume``, its metrics logged.

The package is written to a temporary directory the way pip installs one (the module and a ``.dist-info`` folder
with its ``entry_points.txt``), and the training command runs in a fresh process with that directory on its path.
Its method counts, in its own state, the feedback sessions (adding ``--counting.step`` each) and the pre-training
steps, and logs both: the logged counts are checked against the schedule's own count of sessions and steps.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from rebel_jax import api
from rebel_jax.preference import budget
from rebel_jax.run import cli_args

PACKAGE = '''
import dataclasses

import jax.numpy as jnp

from rebel_jax.methods import Method


@dataclasses.dataclass(frozen=True)
class CountingConfig:
    """The counting method's settings."""

    step: float = 1.0
    """What each feedback session adds to the count."""

    def validate(self) -> None:
        if not self.step > 0:
            raise ValueError("counting.step must be > 0")


class Counting(Method):
    """PEBBLE, counting its sessions and its pre-training steps in a state of its own."""

    name = "counting"
    config = CountingConfig

    def init_state(self, trainer, key):
        del trainer, key
        return {"sessions": jnp.zeros(()), "pretrain": jnp.zeros(())}

    def pretrain_step(self, trainer, ts, batches, key):
        del trainer, key
        state = dict(ts.method, pretrain=ts.method["pretrain"] + 1)
        return batches, ts.reward, state, {"pretrain_steps": state["pretrain"]}

    def train_reward(self, trainer, ts, stored, keys, kept, agent_step, first):
        reward, state, metrics = super().train_reward(trainer, ts, stored, keys, kept, agent_step, first)
        state = dict(state, sessions=state["sessions"] + self.settings(trainer.cfg).step)
        return reward, state, dict(metrics, sessions=state["sessions"], first=first, pretrain=state["pretrain"])
'''

FLAGS = (
    "--preset tiny --task probe_point --num-envs 2 --episode-length 40 --sac.hidden 16 --sac.batch-size 16"
    " --sac.utd 0.5 --seed-steps 20 --steps-per-round 40 --eval-every 40 --eval-episodes 1"
    " --feedback.labels 12 --feedback.per-session 4 --feedback.interval 40 --reward.hidden 32 --reward.batch-size 16"
    " --query.segment-length 8 --pretrain.steps 60 --pretrain.chunk-size 64 --seeds 2 --no-tensorboard --no-progress"
    " --video-steps 0"
).split()


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A directory holding the installed package ``counting_method`` with its entry point."""
    root = tmp_path_factory.mktemp("site")
    (root / "counting_method").mkdir()
    (root / "counting_method" / "__init__.py").write_text(textwrap.dedent(PACKAGE))
    info = root / "counting_method-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: counting-method\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[rebel_jax.methods]\ncounting = counting_method:Counting\n")
    return root


def _train(site, *args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]))
    command = [sys.executable, "-m", "rebel_jax.train", *args]
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)


def _rounds(run_dir):
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_a_packaged_method_runs_resumes_and_logs_its_state(site, tmp_path):
    run_dir = tmp_path / "run"
    first = _train(site, "counting", *FLAGS, "--counting.step", "2", "--total-steps", "120", "--run-dir", str(run_dir))
    assert first.returncode == 0, first.stderr
    assert json.loads((run_dir / "config.json").read_text())["counting"] == {"step": 2.0}

    changed = _train(
        site, "counting", *FLAGS, "--counting.step", "3", "--total-steps", "200", "--run-dir", str(run_dir), "--resume"
    )
    assert changed.returncode == 2 and "counting.step" in changed.stderr, changed.stderr

    resumed = _train(
        site, "counting", *FLAGS, "--counting.step", "2", "--total-steps", "200", "--run-dir", str(run_dir), "--resume"
    )
    assert resumed.returncode == 0, resumed.stderr

    cfg = cli_args.parse(["pebble", *FLAGS, "--total-steps", "200"]).config
    rounds = _rounds(run_dir)
    assert [r["round"] for r in rounds] == list(range(cfg.train.num_rounds))
    sessions = 0
    for r in rounds:  # the state's count goes on across the resume: 2 a session, by the schedule's own count
        due, first_session = (bool(x) for x in budget.session_due(cfg, np.int32(r["round"])))
        if not due:
            assert r["counting/sessions"] == [None, None], r["round"]
            continue
        sessions += 2
        assert r["counting/sessions"] == [sessions, sessions]
        assert r["counting/sessions_mean"] == sessions
        assert r["counting/first"] == [float(first_session)] * 2
    assert sessions > 2
    final = json.loads((run_dir / "final.json").read_text())  # the run's summary: their last values
    assert final["method_metrics"]["counting/sessions"] == {"last": [sessions, sessions], "mean": sessions}
    # Pre-training: the hook ran once per vector step of the phase with updates, by the trainer's schedule.
    trainer = api.make_trainer(cfg)
    expected = sum(
        bool(trainer.schedule.learning(t, trainer.num_train, cfg.train.seed_steps))
        for t in range(trainer.pretrain_steps)
    )
    counted = [r["counting/pretrain"] for r in rounds if r["counting/pretrain"][0] is not None]
    assert expected > 0 and all(c == [expected, expected] for c in counted)
    assert any(r["counting/pretrain_steps"][0] is not None for r in rounds)
