"""``train.overlap``: the updates of a vector step sample the replay as it was before the step's transitions."""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.cli import parse
from rebel_jax.config import Config, EnvConfig, SACConfig, TrainConfig
from rebel_jax.train import Trainer, compiled, seed_keys

MICRO = Config(
    env=EnvConfig(task="probe_point", num_envs=2, episode_length=20),
    sac=SACConfig(hidden=16, batch_size=16, utd=1.0),
    train=TrainConfig(total_steps=80, seed_steps=20, steps_per_round=40, eval_every=40, eval_episodes=1),
)


def _replay_rows_sampled(cfg: Config) -> tuple[list[int], jax.Array]:
    """The replay's filled rows at every update of two rounds (one seed), and the final agent's critic."""
    trainer = Trainer(cfg)
    seen: list[int] = []
    sample = trainer.sample

    def spy(buffer, key, learned_reward):
        jax.debug.callback(lambda size: seen.extend(np.asarray(size).ravel().tolist()), buffer.size, ordered=True)
        return sample(buffer, key, learned_reward)

    trainer.sample = spy
    init, round_fn, _ = compiled(trainer)
    state = init(seed_keys(0, 1))
    for r in range(2):
        state, _ = round_fn(state, jnp.int32(r))
    jax.effects_barrier()
    return seen, state.agent.critic_params


def test_overlapping_updates_sample_the_replay_one_vector_step_behind():
    plain, critic = _replay_rows_sampled(MICRO)
    behind, critic_behind = _replay_rows_sampled(
        dataclasses.replace(MICRO, train=dataclasses.replace(MICRO.train, overlap=True))
    )
    # 2 updates (utd 1, 2 envs) at every vector step from the one whose transitions reach seed_steps (row 10 of
    # 40 vector steps): the same updates, each on a replay of one row (one vector step) fewer.
    assert len(plain) == 2 * (40 - 9) and plain[0] == 10 and plain[-1] == 40
    assert behind == [rows - 1 for rows in plain]
    assert not all(
        np.array_equal(a, b) for a, b in zip(jax.tree.leaves(critic), jax.tree.leaves(critic_behind), strict=True)
    )


def test_overlap_needs_transitions_before_the_first_update(capsys):
    with pytest.raises(SystemExit):
        parse(["--preset", "tiny", "--overlap", "--seed-steps", "10", "--num-envs", "10"])
    assert "train.seed_steps=10" in capsys.readouterr().err
    assert parse(["--preset", "tiny", "--overlap", "--seed-steps", "11", "--num-envs", "10"]).config.train.overlap


def _two_rounds(cfg: Config):
    init, round_fn, _ = compiled(Trainer(cfg))
    state = init(seed_keys(0, 1))
    text = round_fn.lower(state, jnp.int32(0)).as_text()
    for r in range(2):
        state, _ = round_fn(state, jnp.int32(r))
    return state, text


def test_on_a_gpu_the_env_step_is_annotated_for_a_second_stream_and_computes_the_same(monkeypatch):
    cfg = dataclasses.replace(MICRO, train=dataclasses.replace(MICRO.train, overlap=True))
    plain, plain_text = _two_rounds(cfg)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")  # the trace as on a GPU; it still runs here
    streamed, text = _two_rounds(cfg)
    assert "_xla_stream_annotation" in text and "_xla_stream_annotation" not in plain_text
    chex.assert_trees_all_equal(plain, streamed)
