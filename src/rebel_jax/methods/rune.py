"""RUNE (Liang et al., ICLR 2022): an exploration bonus from the reward ensemble's disagreement.

SAC learns from ``r_hat(s, a) + beta_t * std_m r_m(s, a)``: the ensemble-mean learned reward plus the standard
deviation over the members of their rewards for the same transition, weighted by ``beta_t = beta_0 (1 - rho)^t``
with t the environment steps taken so far (rll-research/rune@8b3c77a:agent/sac_explore.py:128-132, :157, called
with ``self.step``, train_PEBBLE_explore.py:286). RUNE stores the bonus beside the learned reward and relabels
both after every session (replay_buffer_explore.py:75-94), so it is always the current ensemble's, as computed
here on each minibatch. The reward itself is learnt as PEBBLE's.

On pixel tasks (:meth:`RUNE.batch_reward`) DrQ-v2 learns from n-step transitions whose ``reward`` is the
discounted sum of the learned rewards of n steps; the bonus added to it is that of the transition's first step
``(s_t, a_t)``, the one whose Q-value the update moves, once: ``sum_i gamma^i r_hat_{t+i} + beta_t std(s_t, a_t)``.
The batch carries that step's stack and action only, so the bonus of the n - 1 later steps (their discounted sum
would be the n-step return of RUNE's per-step reward) would need n times the members' encoder passes per update,
which relabelling once per session avoids for the learned reward; URLB's n-step DDPG agents (DrQ-v2's) likewise
compute their ensemble-disagreement reward once per n-step sample (rll-research/url_benchmark@bb98f0c:
agent/disagreement.py:93-112, ``nstep: 3`` in agent/disagreement.yaml). In the value the bonus then weighs about
``(1 - gamma) / (1 - gamma^n)`` of the per-step form's (a third at n 3, gamma 0.99); ``rune.beta_0`` times n
restores its scale. On pixels the ``pretrain.reset_updates`` updates after the critic's reset carry the bonus too
(RUNE's ``update_after_reset``, agent/sac_explore.py:399-411).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from rebel_jax.core.errors import check
from rebel_jax.methods.base import Method
from rebel_jax.preference import reward_model


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


def disagreement(cfg, params, obs: jax.Array, action: jax.Array) -> jax.Array:
    """The members' standard deviation (NumPy's, over M) of their rewards of (obs, action): (...,) for (..., size)."""
    return jnp.std(reward_model.predict(cfg, params, obs, action), axis=0)


class RUNE(Method):
    name = "rune"
    config = RUNEConfig

    def validate(self, cfg):
        cfg.rune.validate()
        field = "pixel_reward" if cfg.pixels else "reward"
        size = getattr(cfg, field).ensemble_size
        check(size >= 2, f"{field}.ensemble_size", size, ">= 2 with --algo rune (its bonus is the members' spread)")

    def batch_reward(self, trainer, ts, batch, agent_step: jax.Array):
        """The learned reward plus ``beta_t`` times the members' disagreement on the batch's (first) step, t =
        ``agent_step`` (the seed's environment steps so far). On pixel tasks the learned reward is the n-step
        return (see the module docstring)."""
        members = trainer.reward_members(ts.reward.params, batch.obs, batch.action)  # (M, B)
        weight = bonus_weight(trainer.cfg.rune, agent_step)
        return batch.replace(reward=batch.reward + weight * jnp.std(members, axis=0))
