"""REBEL's agent-preference term: the learned reward's value of the current policy.

REBEL adds ``lambda * V(pi_theta)`` to the Bradley-Terry loss of the reward ensemble (the
paper's eq. "mle_new"), V being the learned reward's discounted return of the current policy.
The term is one more loss term of :mod:`rebel_jax.reward_model` (``(params, batch, key) ->
(loss, metrics)``), passed to ``reward_model.train`` beside ``bt_loss``. Which trajectories V
is computed on (``rebel.source``) is the trainer's choice; this module takes them as arrays.

References:
  REBEL: Reward Regularization-Based Approach for Robotic Reinforcement Learning from Human
  Feedback (AAAI 2025); REFERENCE.md section 1.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal

import jax
import jax.numpy as jnp

from rebel_jax.errors import check as _check
from rebel_jax.reward_model import LossTerm, PrefBatch, RewardConfig, network, predict


@dataclasses.dataclass(frozen=True)
class AgentPreferenceConfig:
    """REBEL's agent-preference term ``lambda * V`` added to the reward loss (REFERENCE section 1)."""

    lam: float = 0.0
    """Weight lambda, signed; the paper's equation adds ``+lambda * V`` to the minimised loss,
    its prose says the term raises the current policy's value, which needs ``lambda < 0``
    here. 0 turns the term off."""
    estimator: Literal["discounted", "mean"] = "discounted"
    """How V is estimated from the segments: ``discounted`` is the paper's
    ``sum_h gamma^h r(s_h, a_h)`` over a segment, averaged over segments; ``mean`` is the
    per-step mean reward over all their steps times the horizon ``1 / (1 - gamma)``, a
    stationary estimate of the infinite-horizon value."""
    source: Literal["onpolicy", "replay"] = "onpolicy"
    """Where V's trajectories come from. ``onpolicy``, the paper's ``V = E[sum_h gamma^h
    r(s_h, a_h) | s_0, a_h ~ pi]`` (eq. "mle_new"): the last complete episodes of the in-batch
    evaluation environments, which start at the task's reset and follow the current policy
    (its mean action, frozen at the episode start), over their whole length, at no extra env
    cost. ``replay``, this project's earlier estimate: ``num_segments`` segments of
    ``segment_length`` steps from the replay buffer (older policies' states, mid-episode starts)
    with actions redrawn from the current policy."""
    num_segments: int = 64
    """``source='replay'``: segments N of recent agent experience, drawn once per feedback session,
    over which V is averaged (their actions redrawn from the current policy)."""
    segment_length: int = 50
    """``source='replay'``: steps H per segment."""
    gamma: float = 0.99
    """Discount of V; in [0, 1] for ``discounted``, in [0, 1) for ``mean``."""
    normalize: bool = False
    """The scale-free form: V divided by each member's spread (std) of the per-step reward on
    the labelled segments of the minibatch, so that one lambda means the same on walker and
    cheetah (see ``agent_value_term``). Off: the paper's literal ``lambda * V``."""

    def validate(self) -> None:
        _check(math.isfinite(self.lam), "rebel.lam", self.lam, "a finite float")
        _check(self.estimator in ("discounted", "mean"), "rebel.estimator", self.estimator, "discounted, mean")
        _check(self.source in ("onpolicy", "replay"), "rebel.source", self.source, "onpolicy, replay")
        for name in ("num_segments", "segment_length"):
            _check(getattr(self, name) >= 1, f"rebel.{name}", getattr(self, name), ">= 1")
        if self.estimator == "mean":
            _check(0 <= self.gamma < 1, "rebel.gamma", self.gamma, "[0, 1) with estimator 'mean'")
        else:
            _check(0 <= self.gamma <= 1, "rebel.gamma", self.gamma, "[0, 1]")


def agent_value(
    cfg: RewardConfig, params: Any, obs: jax.Array, action: jax.Array, gamma: float | jax.Array, estimator: str
) -> jax.Array:
    """Each member's value V_m of the current policy under its learned reward.

    Args:
      cfg: the reward settings.
      params: ensemble parameters.
      obs: (N, H, obs_size) states of N segments of H consecutive steps visited by the agent.
      action: (N, H, act_size) actions drawn in them from the current policy.
      gamma: discount (a float or a traced scalar).
      estimator: ``"discounted"``: ``mean_n sum_h gamma^h r_m(s_nh, a_nh)``; ``"mean"``:
        ``mean_{n,h} r_m(s_nh, a_nh) / (1 - gamma)``.

    Returns:
      (M,) values ``V_m``.
    """
    _check(estimator in ("discounted", "mean"), "rebel.estimator", estimator, "discounted, mean")
    rewards = predict(cfg, params, obs, action)  # (M, N, H)
    if estimator == "mean":
        return jnp.mean(rewards, axis=(1, 2)) / (1.0 - gamma)
    discounts = jnp.asarray(gamma, rewards.dtype) ** jnp.arange(rewards.shape[-1], dtype=rewards.dtype)
    return jnp.mean(jnp.sum(rewards * discounts, axis=-1), axis=1)


def _labelled_spread(cfg: RewardConfig, params: Any, batch: PrefBatch) -> jax.Array:
    """(M,) each member's std of the per-step reward over its minibatch's labelled steps (>= 1e-6)."""

    def one(member_params, obs_a, act_a, obs_b, act_b, weight):
        apply = network(cfg).apply
        rewards = jnp.concatenate([apply(member_params, obs_a, act_a), apply(member_params, obs_b, act_b)], axis=0)
        w = jnp.broadcast_to(jnp.concatenate([weight, weight])[:, None], rewards.shape)
        mean = jnp.sum(rewards * w) / jnp.maximum(jnp.sum(w), 1.0)
        var = jnp.sum(w * (rewards - mean) ** 2) / jnp.maximum(jnp.sum(w), 1.0)
        return jnp.maximum(jnp.sqrt(var), 1e-6)

    return jax.vmap(one)(params, batch.obs_a, batch.act_a, batch.obs_b, batch.act_b, batch.weight)


def agent_value_term(
    cfg: RewardConfig,
    lam: float | jax.Array,
    obs: jax.Array,
    action: jax.Array,
    gamma: float | jax.Array,
    estimator: str = "discounted",
    normalize: bool = False,
) -> LossTerm:
    """REBEL's agent-preference term ``lambda * sum_m V_m`` (the paper's eq. "mle_new").

    The term closes over N segments of states recently visited by the agent with actions
    already drawn by the caller from the current policy ``pi_theta``, which is held fixed:
    ``obs`` and ``action`` pass through ``stop_gradient``, so only the reward parameters get
    gradients. The members' values are summed, as ``bt_loss`` sums the members' losses. The
    equation is implemented literally: the loss adds ``+lambda * V``, so minimising it with
    ``lambda > 0`` lowers the current policy's value and ``lambda < 0`` raises it.

    Args:
      cfg: the reward settings.
      lam: signed weight lambda, a float or a traced scalar (e.g. ``vmap``-ed over).
      obs: (N, H, obs_size) states.
      action: (N, H, act_size) actions from the current policy.
      gamma: discount of V.
      estimator: ``"discounted"`` or ``"mean"``, see ``agent_value``.
      normalize: the scale-free form ``lambda * sum_m V_m / s_m`` (``rebel.normalize``): ``s_m``
        is member m's standard deviation of the per-step reward over the steps of the batch's
        labelled segments (both of each pair, padding excluded), held fixed (no gradient). The
        BT loss fixes the reward's scale only up to what the labels demand, so with it one
        lambda weighs V alike on tasks whose learned rewards spread differently.

    Returns:
      ``(params, batch, key) -> (loss, metrics)`` with metrics ``agent_value`` (the members'
      mean V, unscaled) and ``agent_term`` (the loss).

    References:
      REBEL (AAAI 2025), the reward loss "mle_new" (REFERENCE section 1).
    """
    _check(estimator in ("discounted", "mean"), "rebel.estimator", estimator, "discounted, mean")

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        del key  # Unused.
        values = agent_value(cfg, params, jax.lax.stop_gradient(obs), jax.lax.stop_gradient(action), gamma, estimator)
        if normalize:
            values = values / jax.lax.stop_gradient(_labelled_spread(cfg, params, batch))
        loss = lam * jnp.sum(values)
        return loss, {"agent_value": jnp.mean(values), "agent_term": loss}

    return loss_fn
