"""The worked extension (examples/l2_reward.py): a new method in one file, trained on state and pixel tasks.

Its penalty is checked against a NumPy loop; trained with a large weight, the learned reward it leaves is
smaller than PEBBLE's from the same keys (the only difference between the two runs is the method).
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_pixel_preference import MICRO as PIXEL_MICRO
from test_preference_train import MICRO_PEBBLE

from rebel_jax import api, methods, train

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "examples"))
from l2_reward import L2Reward, l2_penalty  # noqa: E402


@pytest.fixture(scope="module")
def strong_l2():
    """The example registered as ``l2_reward`` with a weight that dominates the Bradley-Terry loss."""
    method = methods.register(L2Reward(weight=50.0))
    yield method
    del methods.REGISTRY[method.name]


def test_l2_penalty_is_the_weighted_mean_square_per_member_summed():
    rng = np.random.default_rng(0)
    rewards_a, rewards_b = rng.normal(size=(2, 3, 5, 4)).astype(np.float32)
    mask = np.array([[1, 1, 0, 1, 0], [1, 0, 0, 0, 0], [0, 0, 0, 0, 0]], np.float32)
    expected = 0.0
    for m in range(3):
        real = [b for b in range(5) if mask[m, b]]
        squares = [np.mean(np.concatenate([rewards_a[m, b], rewards_b[m, b]]) ** 2) for b in real]
        expected += np.mean(squares) if real else 0.0
    got = l2_penalty(0.3, jnp.asarray(rewards_a), jnp.asarray(rewards_b), jnp.asarray(mask))
    np.testing.assert_allclose(got, 0.3 * expected, rtol=1e-6)


def test_a_registered_name_is_refused():
    with pytest.raises(ValueError, match="exists already"):
        methods.register(methods.get("pebble"))


def _learned_square(cfg, rounds: int) -> float:
    trainer = api.make_trainer(cfg)
    init, round_fn, _ = train.compiled(trainer)
    state = init(train.seed_keys(0, 2))
    for r in range(rounds):
        state, metrics = round_fn(state, jnp.int32(r))
    assert np.isfinite(np.asarray(metrics["eval_return"])).all()
    buffer = jax.device_get(state.buffer)
    rows = int(np.max(buffer.size))
    reward = buffer.learned_reward  # the same name on the state and the frame replay
    return float(np.mean(np.asarray(reward)[:, :rows] ** 2))


def test_the_example_trains_on_a_state_task_and_shrinks_the_reward(strong_l2):
    rounds = 3  # two feedback sessions
    pebble = _learned_square(MICRO_PEBBLE, rounds)
    l2 = _learned_square(dataclasses.replace(MICRO_PEBBLE, algo=strong_l2.name), rounds)
    assert l2 < pebble / 2


@pytest.mark.heavy  # make test-heavy: the pixel agent's compile is about a minute on 2 cores
def test_the_example_trains_on_a_pixel_task_and_shrinks_the_reward(strong_l2):
    rounds = 3
    pebble = _learned_square(PIXEL_MICRO, rounds)
    l2 = _learned_square(dataclasses.replace(PIXEL_MICRO, algo=strong_l2.name), rounds)
    assert l2 < pebble / 2
