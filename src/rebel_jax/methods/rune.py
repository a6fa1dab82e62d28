"""RUNE (Liang et al., ICLR 2022): an exploration bonus from the reward ensemble's disagreement.

SAC learns from ``r_hat(s, a) + beta_t * std_m r_m(s, a)``: the ensemble-mean learned reward plus the standard
deviation over the members of their rewards for the same transition, weighted by ``beta_t = beta_0 (1 - rho)^t``
with t the environment steps taken so far (rll-research/rune@8b3c77a:agent/sac_explore.py:128-132, :157, called
with ``self.step``, train_PEBBLE_explore.py:286). RUNE stores the bonus beside the learned reward and relabels
both after every session (replay_buffer_explore.py:75-94), so it is always the current ensemble's, as computed
here on each minibatch. The reward itself is learnt as PEBBLE's. State tasks only: the pixel trainer has no
hook for the agent's reward.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from rebel_jax import replay, reward_model
from rebel_jax.errors import check
from rebel_jax.methods.base import Method


@dataclasses.dataclass(frozen=True)
class RUNEConfig:
    """RUNE's bonus weight ``beta_t = beta_0 (1 - rho)^t`` (rll-research/rune@8b3c77a:config/agent/sac_explore.yaml,
    ``beta_init`` and ``beta_decay``, which its scripts keep but for drawer_open at 5,000 labels, rho 1e-3)."""

    beta_0: float = 0.05
    """The bonus weight at step 0 (``beta_init``); 0 turns the bonus off (PEBBLE)."""
    rho: float = 1e-5
    """Decay per environment step (``beta_decay``); RIME's runs of RUNE use 1e-3
    (CJReinforce/RIME_ICML2024@4ad03f4:run_parallel.sh:19)."""

    def validate(self) -> None:
        check(self.beta_0 >= 0, "rune.beta_0", self.beta_0, ">= 0")
        check(0 <= self.rho < 1, "rune.rho", self.rho, "[0, 1)")


def bonus_weight(rune: RUNEConfig, env_step: jax.Array) -> jax.Array:
    """``beta_0 (1 - rho)^t`` at environment step ``t``, as ``beta_0 exp(t log(1 - rho))`` (float32 stays exact
    where ``1 - rho`` would round). () float32."""
    return rune.beta_0 * jnp.exp(jnp.asarray(env_step, jnp.float32) * math.log1p(-rune.rho))


def disagreement(cfg: reward_model.RewardConfig, params, obs: jax.Array, action: jax.Array) -> jax.Array:
    """The members' standard deviation (NumPy's, over M) of their rewards of (obs, action): (...,) for (..., size)."""
    return jnp.std(reward_model.predict(cfg, params, obs, action), axis=0)


class RUNE(Method):
    name = "rune"
    config_field = "rune"

    def validate(self, cfg):
        check(not cfg.pixels, "env.task", cfg.env.task, "a state task with --algo rune (no pixel reward hook)")
        cfg.rune.validate()
        size = cfg.reward.ensemble_size
        check(size >= 2, "reward.ensemble_size", size, ">= 2 with --algo rune (its bonus is the members' spread)")

    def batch_reward(self, trainer, ts, batch: replay.Transition, t: jax.Array) -> replay.Transition:
        """The learned reward plus ``beta_t`` times the ensemble's disagreement, t = ``t * num_envs`` env steps."""
        bonus = disagreement(trainer.reward_cfg, ts.reward.params, batch.obs, batch.action)
        weight = bonus_weight(trainer.cfg.rune, t * trainer.cfg.env.num_envs)
        return batch.replace(reward=batch.reward + weight * bonus)
