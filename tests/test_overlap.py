"""``train.overlap``: the updates of a vector step sample the replay as it was before the step's transitions."""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.config import Config, ConfigError, EnvConfig, SACConfig, TrainConfig
from rebel_jax.run.cli import parse
from rebel_jax.train import Trainer, compiled, placement, seed_keys

MICRO = Config(
    env=EnvConfig(task="probe_point", num_envs=2, episode_length=20),
    sac=SACConfig(hidden=16, batch_size=16, utd=1.0),
    train=TrainConfig(total_steps=80, seed_steps=20, steps_per_round=40, eval_every=40, eval_episodes=1),
)


OVERLAP = dataclasses.replace(MICRO, train=dataclasses.replace(MICRO.train, overlap=True))


def _two_rounds(cfg: Config, spy_on_replay: bool = False):
    """Two rounds of one seed: the final state, the round's lowered text and, with ``spy_on_replay``, the
    replay's filled rows at every update (a debug callback in ``Trainer.sample``)."""
    trainer = Trainer(cfg)
    seen: list[int] = []
    if spy_on_replay:
        sample = trainer.sample

        def spy(buffer, key, learned_reward):
            jax.debug.callback(lambda size: seen.extend(np.asarray(size).ravel().tolist()), buffer.size, ordered=True)
            return sample(buffer, key, learned_reward)

        trainer.sample = spy
    init, round_fn, _ = compiled(trainer)
    state = init(seed_keys(0, 1))
    text = round_fn.lower(state, jnp.int32(0)).as_text()
    for r in range(2):
        state, _ = round_fn(state, jnp.int32(r))
    jax.effects_barrier()
    return state, text, seen


@pytest.fixture(scope="module")
def behind():
    """:func:`_two_rounds` of the overlapping run, its replay watched."""
    return _two_rounds(OVERLAP, spy_on_replay=True)


def test_overlapping_updates_sample_the_replay_one_vector_step_behind(behind):
    state, _, plain = _two_rounds(MICRO, spy_on_replay=True)
    # Updates (2: utd 1, 2 envs) at every vector step from the one whose transitions reach seed_steps (row 10 of
    # 40 vector steps), the step's minibatches drawn together (one draw a step): the same draws, each on a replay of
    # one row (one vector step) fewer.
    assert len(plain) == 40 - 9 and plain[0] == 10 and plain[-1] == 40
    assert behind[2] == [rows - 1 for rows in plain]
    critic, critic_behind = jax.tree.leaves(state.agent.critic_params), jax.tree.leaves(behind[0].agent.critic_params)
    assert not all(np.array_equal(a, b) for a, b in zip(critic, critic_behind, strict=True))


def test_overlap_needs_transitions_before_the_first_update(capsys):
    with pytest.raises(SystemExit):
        parse(["--preset", "tiny", "--overlap", "--seed-steps", "10", "--num-envs", "10"])
    assert "train.seed_steps=10" in capsys.readouterr().err
    assert parse(["--preset", "tiny", "--overlap", "--seed-steps", "11", "--num-envs", "10"]).config.train.overlap


@pytest.mark.parametrize("api", ["compute_on2", "compute_on"])
def test_on_a_gpu_the_env_step_is_annotated_for_a_second_stream_and_computes_the_same(behind, monkeypatch, api):
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")  # the trace as on a GPU; it still runs here
    if api == "compute_on":  # as on JAX 0.11: the keyword form named compute_on, no compute_on2
        monkeypatch.setattr(placement.jax_compute_on, "compute_on", placement.jax_compute_on.compute_on2)
        monkeypatch.delattr(placement.jax_compute_on, "compute_on2")
    streamed, text, _ = _two_rounds(OVERLAP)
    assert "_xla_stream_annotation" in text and "_xla_stream_annotation" not in behind[1]
    chex.assert_trees_all_equal(behind[0], streamed)


def test_on_a_gpu_with_jax_0_11_overlap_is_refused_in_one_line(monkeypatch):
    """XLA aborted the second-stream program on an H200 with JAX 0.11.2 (both the trainer and
    benchmarks/overlap.py's stream modes); such a run stops at once with a one-line error instead."""
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(jax, "__version_info__", (0, 11, 2))
    with pytest.raises(ConfigError, match=r"^--overlap is refused on GPUs with JAX >= 0\.11: XLA aborted") as err:
        Trainer(OVERLAP)
    assert "\n" not in str(err.value)
    monkeypatch.setattr(jax, "__version_info__", (0, 10, 2))
    assert Trainer(OVERLAP).cfg.train.overlap  # JAX 0.10 builds it (its GPU behaviour unmeasured)
