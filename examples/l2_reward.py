"""A new preference method in one file: PEBBLE with an L2 penalty on the learned reward.

The penalty ``weight * mean(r(s, a)^2)`` over the steps of each minibatch's labelled segments, summed over
the ensemble's members, is added to the Bradley-Terry loss. It keeps the learned reward small, away from the
bounds of its ``tanh`` output, where it has no room left to rank a good behaviour above a better one.

Use it from Python (``docs/adding_a_method.md`` walks through this file)::

    import dataclasses
    from rebel_jax import api, config, methods
    from l2_reward import L2Reward

    methods.register(L2Reward(weight=0.1))
    cfg = dataclasses.replace(config.PRESETS["tiny"], algo="l2_reward")
    trainer = api.make_trainer(cfg)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rebel_jax.methods import Method
from rebel_jax.preference import reward_model


def l2_penalty(weight: float, rewards_a: jax.Array, rewards_b: jax.Array, mask: jax.Array) -> jax.Array:
    """``weight`` times the sum over members of the mean squared reward of the minibatch's real pairs.

    Args:
      rewards_a, rewards_b: (M, B, H) each member's per-step rewards of the pairs' two segments.
      mask: (M, B) 1 for a real pair, 0 for padding.
    """
    squares = jnp.mean(rewards_a**2 + rewards_b**2, axis=-1) / 2 * mask  # (M, B)
    return weight * jnp.sum(jnp.sum(squares, axis=1) / jnp.maximum(jnp.sum(mask, axis=1), 1.0))


class L2Reward(Method):
    """PEBBLE plus :func:`l2_penalty`, on state and pixel tasks alike."""

    name = "l2_reward"

    def __init__(self, weight: float = 0.1):
        self.weight = weight

    def reward_terms(self, trainer, ts, key, agent_step):
        def term(params, batch: reward_model.PrefBatch, key):
            del params, key  # Unused: the training step computed the members' rewards on the batch already.
            loss = l2_penalty(self.weight, batch.rewards_a, batch.rewards_b, batch.weight)
            return loss, {"l2_penalty": loss}

        return [*super().reward_terms(trainer, ts, key, agent_step), term]
