"""Success rates of a task whose steps report ``success`` (Meta-World's): B-Pref's rule, an episode succeeding if any
of its steps does and the rate the fraction of the last finished episodes that did
(rll-research/BPref@f3ece2e:train_PEBBLE.py:92-114), against a loop of that rule; and the trainer's metrics."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.config import Config, EnvConfig, SACConfig, TrainConfig
from rebel_jax.envs import make_env
from rebel_jax.train import Trainer, compiled, seed_keys
from rebel_jax.train import trainer as trainer_module
from rebel_jax.train.episodes import EpisodeStats


def bpref_rates(success: np.ndarray, done: np.ndarray, n: int) -> list[tuple[float, float]]:
    """(train rate, eval rate) after each step, by B-Pref's loop: ``episode_success = max(episode_success,
    success)`` at each step, the rate over the episodes that end at a step, NaN before any has ended."""
    episode_success = np.zeros(success.shape[1])
    rates, last = [], [np.nan, np.nan]
    for s, d in zip(success, done, strict=True):
        episode_success = np.maximum(episode_success, s)
        for i, part in enumerate((slice(0, n), slice(n, None))):
            ended = d[part] > 0
            if ended.any():
                last[i] = float(np.mean(episode_success[part][ended]))
        episode_success = np.where(d > 0, 0.0, episode_success)
        rates.append(tuple(last))
    return rates


def test_episode_success_is_bprefs_rate_over_the_finished_episodes():
    rng = np.random.default_rng(0)
    steps, envs, n = 60, 7, 4
    success = (rng.random((steps, envs)) < 0.04).astype(np.float32)
    done = np.zeros((steps, envs), np.float32)
    done[9::10] = 1.0  # every episode of every env ends together, as the trainer's do
    done[24, 2] = 1.0  # and one that ends alone
    stats = EpisodeStats.init(envs, success=True)
    step = jax.jit(lambda st, r, d, s: st.after_step(r, d, n, s))
    expected = bpref_rates(success, done, n)
    for t in range(steps):
        stats = step(stats, jnp.zeros(envs), jnp.asarray(done[t]), jnp.asarray(success[t]))
        np.testing.assert_allclose([stats.train_success, stats.eval_success], expected[t], rtol=1e-6)
    assert 0 < expected[-1][0] < 1 or 0 < expected[-1][1] < 1  # the draw has some of both


def test_a_task_without_success_keeps_the_state_s_leaves():
    plain, with_success = EpisodeStats.init(5), EpisodeStats.init(5, success=True)
    assert len(jax.tree.leaves(plain)) == 3 and len(jax.tree.leaves(with_success)) == 6


class SucceedingProbe:
    """The probe task whose steps report ``success`` (``rule(state)``), as Meta-World's do."""

    reports_success = True

    def __init__(self, env, rule):
        self._env, self._rule = env, rule

    def __getattr__(self, name):
        return getattr(self._env, name)

    def reset(self, key):
        state = self._env.reset(key)
        return state.replace(info=dict(state.info, success=jnp.zeros(())))

    def step(self, state, action):
        plain = state.replace(info={k: v for k, v in state.info.items() if k != "success"})
        nxt = self._env.step(plain, action)
        return nxt.replace(info=dict(nxt.info, success=self._rule(nxt)))


MICRO = Config(
    algo="sac",
    env=EnvConfig(task="probe_point", num_envs=2, episode_length=10),
    sac=SACConfig(hidden=16, batch_size=16, utd=0.5),
    train=TrainConfig(total_steps=40, seed_steps=10, steps_per_round=20, eval_every=20, eval_episodes=2),
)


@pytest.mark.parametrize(("rule", "rate"), [(lambda s: jnp.ones(()), 1.0), (lambda s: jnp.zeros(()), 0.0)])
def test_the_round_logs_the_success_rates_of_a_task_that_reports_success(monkeypatch, rule, rate):
    monkeypatch.setattr(trainer_module, "make_env", lambda *a, **k: SucceedingProbe(make_env(*a, **k), rule))
    trainer = Trainer(MICRO)
    init, round_fn, _ = compiled(trainer)
    state = init(seed_keys(0, 2))
    state, metrics = round_fn(state, jnp.int32(0))
    np.testing.assert_array_equal(metrics["eval_success"], [rate, rate])
    np.testing.assert_array_equal(metrics["train_success"], [rate, rate])


def test_a_task_without_success_logs_no_success_rate():
    trainer = Trainer(dataclasses.replace(MICRO))
    assert not trainer.reports_success
    shapes = jax.eval_shape(trainer.round, jax.eval_shape(trainer.init, jax.random.PRNGKey(0)), jnp.int32(0))[1]
    assert "eval_success" not in shapes and "eval_return" in shapes


def test_evaluate_refuses_a_success_rate_on_a_task_without_success():
    with pytest.raises(ValueError, match="does not report success"):
        Trainer(MICRO).evaluate(None, jax.random.PRNGKey(0), success=True)


# A CLI run of one round whose steps succeed where the point is at positive x, at odd steps only (a success that does
# not last, as a Meta-World object can slip out of place): some episodes succeed, some do not (asserted below).
CLI_FLAGS = (
    "--preset tiny --algo sac --task probe_point --num-envs 2 --episode-length 10 --sac.hidden 16 --sac.batch-size 16"
    " --sac.utd 0.5 --total-steps 20 --seed-steps 10 --steps-per-round 20 --eval-every 20 --eval-episodes 4"
    " --seeds 2 --seed 7 --no-tensorboard --no-progress"
).split()


def _loop_flags(trainer: Trainer, params, key: jax.Array) -> np.ndarray:
    """(steps, episodes) success flags of the policy's evaluation episodes stepped one by one in Python, on
    ``Trainer.evaluate``'s initial states (the reference)."""
    key_reset, _ = jax.random.split(key)
    reset, step = jax.jit(trainer.env.reset), jax.jit(trainer.env.step)
    act = jax.jit(trainer.mean_action)
    states = [reset(k) for k in jax.random.split(key_reset, trainer.cfg.train.eval_episodes)]
    flags = []
    for _ in range(trainer.episode_length):
        states = [step(s, act(params, s.obs[None])[0]) for s in states]
        flags.append([float(s.info["success"]) for s in states])
    return np.array(flags)


def test_final_json_gives_the_success_rate_of_the_final_evaluation(monkeypatch, tmp_path, capsys):
    from rebel_jax.run import cli, loop

    def reached(state):
        return ((state.obs[0] > 0) & (state.info["steps"] % 2 == 1)).astype(jnp.float32)

    monkeypatch.setattr(trainer_module, "make_env", lambda *a, **k: SucceedingProbe(make_env(*a, **k), reached))
    seen = {}
    final_evaluation = loop._final_evaluation

    def spy(evaluate, trainer, shapes, keys):  # the final policy and the keys of its episodes, for the reference
        run = final_evaluation(evaluate, trainer, shapes, keys)

        def evaluated(policy):
            seen.update(trainer=trainer, policy=policy, keys=keys)
            return run(policy)

        return evaluated

    monkeypatch.setattr(loop, "_final_evaluation", spy)
    run_dir = tmp_path / "run"
    final = cli.main([*CLI_FLAGS, "--run-dir", str(run_dir)])
    written = json.loads((run_dir / "final.json").read_text())
    assert written["final_eval_success"] == pytest.approx(final["final_eval_success"].tolist())
    # The reference: B-Pref's rule (rll-research/BPref@f3ece2e:train_PEBBLE.py:92-114) by a loop over the
    # episodes' steps, an episode succeeding if any step does, the rate the fraction of the episodes that did.
    trainer, policy, keys = seen["trainer"], seen["policy"], seen["keys"]
    expected = []
    for c in range(2):
        flags = _loop_flags(trainer, jax.tree.map(lambda x, c=c: x[c], policy), keys[c])
        episode_success = np.zeros(flags.shape[1])
        for s in flags:
            episode_success = np.maximum(episode_success, s)
        expected.append(float(np.mean(episode_success)))
    np.testing.assert_array_equal(written["final_eval_success"], expected)
    assert written["success_mean"] == pytest.approx(np.mean(expected))
    assert any(0 < e < 1 for e in expected)  # some episodes succeed and some do not
    line = f"success rate {np.mean(expected):.2f} +- {np.std(expected, ddof=1):.2f} (sample std)"
    assert line in capsys.readouterr().out
