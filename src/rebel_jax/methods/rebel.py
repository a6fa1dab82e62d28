"""REBEL (Chakraborty et al., AAAI 2025): the agent-preference term ``lambda * V`` added to the reward loss.

REBEL adds ``lambda * V(pi_theta)`` to the Bradley-Terry loss of the reward ensemble (the paper's eq. "mle_new",
its lower bound "bilevel_rlhf_fo_lb": :func:`agent_value_term`), V being the learned reward's discounted return of
the current policy, differentiated with respect to the reward's parameters only. :func:`value_gap_term` is the
penalty before that relaxation, ``lambda * (V(pi*(nu)) - V(pi_theta))`` (eq. "bilevel_rlhf_fo"), with
``V(pi*(nu))`` estimated from the best labelled segments (:func:`best_segments`, :func:`optimal_value`);
``rebel.form`` picks one. ``rebel.source`` chooses where V's trajectories come from: the evaluation episodes of
the policy (``onpolicy``, the paper's) or replay segments with actions redrawn from the current policy
(``replay``). Each term is one more loss term (``(params, batch, key) -> (loss, metrics)``) beside ``bt_loss``, on
state and pixel tasks alike. Lambda is traced (``TrainState.lam``), so a sweep runs several lambdas as columns of
one program; lambda 0 is PEBBLE.

References:
  REBEL: Reward Regularization-Based Approach for Robotic Reinforcement Learning from Human
  Feedback (AAAI 2025).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any, Literal

import jax
import jax.numpy as jnp

from rebel_jax.agents import frame_replay
from rebel_jax.core.errors import check as _check
from rebel_jax.methods.base import Method
from rebel_jax.preference import pixel_reward, reward_model
from rebel_jax.preference.reward_model import LossTerm, PairStore, PrefBatch, Steps, mean_reward, predict


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
    (its mean action, frozen at the episode start), over their first ``horizon`` steps (``episodes``
    of them), at no extra env cost; on pixel tasks their newest frames are kept and the stacks
    rebuilt (``pixel_feedback``). ``replay``, this project's earlier estimate: ``num_segments`` segments of
    ``segment_length`` steps from the replay buffer (older policies' states, mid-episode starts)
    with actions redrawn from the current policy."""
    episodes: int = 0
    """``source='onpolicy'``: evaluation episodes V averages over, the first of ``train.eval_episodes``.
    0: all of them on a state task, ``PIXEL_EPISODES`` (2) on a pixel task (see ``horizon``)."""
    horizon: int = 0
    """``source='onpolicy'``: agent steps T from the reset that V sums over, the first T steps of each
    evaluation episode (at most the episode). 0: the whole episode on a state task, ``PIXEL_HORIZON``
    (100) on a pixel task. On pixels every one of the ``episodes x T`` steps is a frame stack that the 3
    encoders score with gradients in every reward step: 100 x 2 is 600 encoder passes, an eighth of the
    BT minibatch's 4,800, where a whole walker episode (500) of all 10 evaluation episodes would be
    15,000 (about 15 GB of float32 activations per seed at 84x84). The kept frames cost
    ``2 x episodes x T x 21,168`` bytes per seed at 84x84 (8.5 MB at 2 x 100; 212 MB at 10 x 500)."""
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
    form: Literal["lower_bound", "penalty"] = "lower_bound"
    """Which of the paper's objectives the term is. ``lower_bound``: eq. "bilevel_rlhf_fo_lb" as
    eq. "mle_new" writes it, ``+lambda * V(pi_theta)``, the current policy standing in for
    ``pi*(nu)``; it bounds eq. "bilevel_rlhf_fo" from below when ``V(pi_theta) >= 0``, which the
    paper gets from ``r >= 0``: ``--reward.output sigmoid`` makes that literal (tanh rewards can
    be negative). ``penalty``: the un-relaxed penalty of eq. "bilevel_rlhf_fo",
    ``+lambda * (V(pi*(nu)) - V(pi_theta))``, with ``V(pi*(nu))`` estimated from the
    ``best_segments`` labelled segments of highest learned return (``optimal_value``). In both,
    ``lambda > 0`` is the paper's ``lambda >= 0``."""
    best_segments: int = 10
    """``form='penalty'``: how many labelled segments estimate ``V(pi*(nu))``: those with the
    highest ensemble-mean learned return at the start of the session (``best_segments``)."""

    def validate(self) -> None:
        _check(math.isfinite(self.lam), "rebel.lam", self.lam, "a finite float")
        _check(self.estimator in ("discounted", "mean"), "rebel.estimator", self.estimator, "discounted, mean")
        _check(self.source in ("onpolicy", "replay"), "rebel.source", self.source, "onpolicy, replay")
        _check(self.form in ("lower_bound", "penalty"), "rebel.form", self.form, "lower_bound, penalty")
        for name in ("num_segments", "segment_length", "best_segments"):
            _check(getattr(self, name) >= 1, f"rebel.{name}", getattr(self, name), ">= 1")
        for name in ("episodes", "horizon"):
            _check(getattr(self, name) >= 0, f"rebel.{name}", getattr(self, name), ">= 0 (0: the task's default)")
        if self.estimator == "mean":
            _check(0 <= self.gamma < 1, "rebel.gamma", self.gamma, "[0, 1) with estimator 'mean'")
        else:
            _check(0 <= self.gamma <= 1, "rebel.gamma", self.gamma, "[0, 1]")

    def onpolicy_size(self, eval_episodes: int, episode_length: int, pixels: bool) -> tuple[int, int]:
        """``(episodes, horizon)`` of the on-policy trajectories: the settings, or the task's defaults for 0.

        Args:
          eval_episodes: evaluation environments of the trainer.
          episode_length: agent steps per episode.
          pixels: whether the task observes frame stacks (smaller defaults, see ``horizon``).
        """
        episodes = self.episodes or (min(PIXEL_EPISODES, eval_episodes) if pixels else eval_episodes)
        horizon = self.horizon or (min(PIXEL_HORIZON, episode_length) if pixels else episode_length)
        return episodes, horizon


PIXEL_EPISODES = 2
"""``rebel.episodes`` 0 on a pixel task: evaluation episodes of the on-policy V."""
PIXEL_HORIZON = 100
"""``rebel.horizon`` 0 on a pixel task: agent steps of the on-policy V (with gamma 0.99, 64% of the
discount weight of a 500-step walker episode)."""


def agent_value(
    cfg: Any,
    params: Any,
    obs: jax.Array,
    action: jax.Array,
    gamma: float | jax.Array,
    estimator: str,
    predict_fn: Callable | None = None,
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
      predict_fn: ``(params, obs, action) -> (M, N, H)`` members' rewards; default the state ensemble's
        ``predict(cfg, ...)``. The pixel trainer passes one whose ``obs`` are the on-policy episodes'
        kept frames, or replay places (row, env), that it turns into frame stacks (``pixel_feedback``).

    Returns:
      (M,) values ``V_m``.
    """
    _check(estimator in ("discounted", "mean"), "rebel.estimator", estimator, "discounted, mean")
    rewards = (predict_fn or functools.partial(predict, cfg))(params, obs, action)  # (M, N, H)
    if estimator == "mean":
        return jnp.mean(rewards, axis=(1, 2)) / (1.0 - gamma)
    discounts = jnp.asarray(gamma, rewards.dtype) ** jnp.arange(rewards.shape[-1], dtype=rewards.dtype)
    return jnp.mean(jnp.sum(rewards * discounts, axis=-1), axis=1)


def reward_spread(rewards_a: jax.Array, rewards_b: jax.Array, weight: jax.Array) -> jax.Array:
    """(M,) each member's std of the per-step reward over the steps of its labelled pairs (>= 1e-6).

    Args:
      rewards_a, rewards_b: (M, B, H) member m's per-step rewards on both segments of its pairs.
      weight: (M, B) or (B,) 1 for real pairs, 0 for padding.
    """
    rewards = jnp.concatenate([rewards_a, rewards_b], axis=1)  # (M, 2B, H)
    w = jnp.broadcast_to(jnp.concatenate([weight, weight], axis=-1)[..., None], rewards.shape)
    total = jnp.maximum(jnp.sum(w, axis=(1, 2)), 1.0)
    mean = jnp.sum(rewards * w, axis=(1, 2)) / total
    var = jnp.sum(w * (rewards - mean[:, None, None]) ** 2, axis=(1, 2)) / total
    return jnp.maximum(jnp.sqrt(var), 1e-6)


def agent_value_term(
    cfg: Any,
    lam: float | jax.Array,
    obs: jax.Array,
    action: jax.Array,
    gamma: float | jax.Array,
    estimator: str = "discounted",
    normalize: bool = False,
    predict_fn: Callable | None = None,
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
        labelled segments (both of each pair, padding excluded; ``batch.rewards_*``), held fixed (no gradient). The
        BT loss fixes the reward's scale only up to what the labels demand, so with it one
        lambda weighs V alike on tasks whose learned rewards spread differently.
      predict_fn: as :func:`agent_value`.

    Returns:
      ``(params, batch, key) -> (loss, metrics)`` with metrics ``agent_value`` (the members'
      mean V, unscaled) and ``agent_term`` (the loss).

    References:
      REBEL (AAAI 2025), the reward loss "mle_new" (REFERENCE section 1).
    """
    _check(estimator in ("discounted", "mean"), "rebel.estimator", estimator, "discounted, mean")

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        del key  # Unused.
        obs_fixed, action_fixed = jax.lax.stop_gradient(obs), jax.lax.stop_gradient(action)
        values = agent_value(cfg, params, obs_fixed, action_fixed, gamma, estimator, predict_fn)
        if normalize:
            spread = reward_spread(batch.rewards_a, batch.rewards_b, batch.weight)
            values = values / jax.lax.stop_gradient(spread)
        loss = lam * jnp.sum(values)
        return loss, {"agent_value": jnp.mean(values), "agent_term": loss}

    return loss_fn


# The un-relaxed penalty (eq. "bilevel_rlhf_fo").


def best_segments(cfg: Any, params: Any, data: PairStore, k: int) -> tuple[Steps, jax.Array]:
    """The ``k`` labelled state segments of highest learned return: the behaviour ``V(pi*(nu))`` is estimated from.

    Both segments of every stored pair are candidates (the label does not matter: a segment
    the teacher rejected may still be the best one in another pair); each is scored by the
    ensemble-mean learned return ``sum_h r(s_h, a_h)`` under ``params`` (the reward at the start
    of the session). Empty slots of the store never win; with fewer than ``k`` stored segments
    the rest of the ``k`` are marked invalid. (On pixels, ``pixel_reward.stored_returns`` scores them
    by chunks and ``pixel_reward.stored_side`` gathers them.)

    Args:
      cfg: the reward settings.
      params: ensemble parameters the segments are ranked with.
      data: the label store of :class:`Steps`.
      k: segments to keep (at most ``2 * capacity``).

    Returns:
      ``(segments (k, H, ...), valid (k,) float)``, best first.
    """
    obs = jnp.concatenate([data.a.obs, data.b.obs])
    action = jnp.concatenate([data.a.action, data.b.action])
    filled = jnp.tile(jnp.arange(data.capacity) < data.count, 2)
    returns = jnp.sum(mean_reward(cfg, params, obs, action), axis=-1)
    index, valid = top_segments(returns, filled, k)
    return Steps(obs[index], action[index]), valid.astype(obs.dtype)


def top_segments(returns: jax.Array, filled: jax.Array, k: int) -> tuple[jax.Array, jax.Array]:
    """The ``min(k, S)`` segments of highest ``returns`` (S,) among the ``filled`` (S,) ones: ``(index, valid)``,
    best first; empty slots never win and are marked invalid where fewer than ``k`` are filled."""
    _, index = jax.lax.top_k(jnp.where(filled, returns, -jnp.inf), min(k, returns.shape[0]))
    return index, filled[index]


def optimal_value(
    cfg: Any,
    params: Any,
    best: Any,
    valid: jax.Array,
    gamma: float | jax.Array,
    estimator: str,
    horizon: int,
    best_predict_fn: Callable | None = None,
) -> jax.Array:
    """Each member's estimate of ``V(pi*(nu))``: the best segments' mean reward, sustained over the horizon.

    ``pi*(nu)`` maximises the learned reward's value; the best labelled behaviour is the
    nearest to it that the session has. With ``rbar_m`` member m's mean per-step reward over
    the valid segments' steps, ``V*_m = rbar_m * sum_{t < horizon} gamma^t`` (``discounted``,
    the horizon of the ``V(pi_theta)`` trajectories, so the two values are sums over as many
    steps) or ``rbar_m / (1 - gamma)`` (``mean``, as ``agent_value``'s). An estimate, not a
    bound: it is the value of repeating the best segment's per-step reward from the start.

    Args:
      cfg: the reward settings.
      params: ensemble parameters.
      best: (K, H) the best segments (``best_segments``; ``pixel_reward.stored_side`` on pixels), with
        ``inputs()``.
      valid: (K,) 1 for real segments, 0 for empty slots.
      gamma: discount.
      estimator: ``"discounted"`` or ``"mean"``.
      horizon: steps T of the discounted sum.
      best_predict_fn: ``(params, best) -> (M, K, H)`` the members' rewards on ``best``; default the
        ensemble's ``predict`` on ``best.inputs()``.

    Returns:
      (M,) values.
    """
    _check(estimator in ("discounted", "mean"), "rebel.estimator", estimator, "discounted, mean")
    rewards = best_predict_fn(params, best) if best_predict_fn else predict(cfg, params, *best.inputs())  # (M, K, H)
    valid = valid.astype(rewards.dtype)
    weight = jnp.broadcast_to(valid[:, None], rewards.shape[1:])
    per_step = jnp.sum(rewards * weight, axis=(1, 2)) / jnp.maximum(jnp.sum(weight), 1.0)
    if estimator == "mean":
        return per_step / (1.0 - gamma)
    return per_step * jnp.sum(jnp.asarray(gamma, rewards.dtype) ** jnp.arange(horizon, dtype=rewards.dtype))


def value_gap_term(
    cfg: Any,
    lam: float | jax.Array,
    obs: jax.Array,
    action: jax.Array,
    best: Any,
    best_valid: jax.Array,
    gamma: float | jax.Array,
    estimator: str = "discounted",
    normalize: bool = False,
    predict_fn: Callable | None = None,
    best_predict_fn: Callable | None = None,
) -> LossTerm:
    """REBEL's un-relaxed penalty ``lambda * sum_m (V*_m - V_m)`` (the paper's eq. "bilevel_rlhf_fo").

    Eq. "bilevel_rlhf_fo" maximises ``L + lambda * (V(pi_theta) - V(pi*(nu)))``; as a
    minimised loss the term is ``+lambda * (V(pi*(nu)) - V(pi_theta))``. ``V_m`` is
    ``agent_value`` on the current policy's trajectories and ``V*_m`` is ``optimal_value`` on
    the best labelled segments; both pass through ``stop_gradient`` on their inputs, so only
    the reward parameters get gradients, and the best segments stay fixed while the reward
    trains (the paper's first-order step: ``grad_nu V(pi*(nu))`` is the reward's gradient at
    the fixed optimal behaviour). With ``lambda > 0`` (the paper's sign) the term raises the
    current policy's value towards the best behaviour's: the prose of the paper's section on
    agent preference, which the literal lower bound (``agent_value_term``) contradicts.

    Args:
      cfg: the reward settings.
      lam: signed weight lambda.
      obs: (N, T, obs_size) states of the current policy's trajectories (or what ``predict_fn`` reads).
      action: (N, T, act_size) its actions.
      best: (K, H) the best labelled segments (:func:`best_segments`), with ``inputs()``.
      best_valid: (K,) 1 for real segments.
      gamma: discount of both values.
      estimator: ``"discounted"`` or ``"mean"``; ``V*`` is summed over T steps (``discounted``).
      normalize: divide both values by each member's spread of the per-step reward on the
        batch's labelled segments, as ``agent_value_term``.
      predict_fn: the members' rewards on ``obs`` (:func:`agent_value`); default the ensemble's ``predict``.
      best_predict_fn: the same on ``best`` (:func:`optimal_value`).

    Returns:
      ``(params, batch, key) -> (loss, metrics)`` with metrics ``agent_value`` (mean V),
      ``optimal_value`` (mean V*) and ``agent_term`` (the loss).

    References:
      REBEL (AAAI 2025), the penalty reformulation "bilevel_rlhf_fo" (REFERENCE section 1).
    """
    _check(estimator in ("discounted", "mean"), "rebel.estimator", estimator, "discounted, mean")
    horizon = obs.shape[1]
    fixed = jax.lax.stop_gradient

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        del key  # Unused.
        values = agent_value(cfg, params, fixed(obs), fixed(action), gamma, estimator, predict_fn)
        best_values = optimal_value(
            cfg, params, fixed(best), fixed(best_valid), gamma, estimator, horizon, best_predict_fn
        )
        if normalize:
            spread = fixed(reward_spread(batch.rewards_a, batch.rewards_b, batch.weight))
            values, best_values = values / spread, best_values / spread
        loss = lam * jnp.sum(best_values - values)
        metrics = {"agent_value": jnp.mean(values), "optimal_value": jnp.mean(best_values), "agent_term": loss}
        return loss, metrics

    return loss_fn


class REBEL(Method):
    name = "rebel"
    config = AgentPreferenceConfig

    def validate(self, cfg):
        rebel = cfg.rebel
        rebel.validate()
        if rebel.source == "replay":
            length = rebel.segment_length
            _check(length <= cfg.env.episode_length, "rebel.segment_length", length, "<= env.episode_length")
            return
        _check(rebel.episodes <= cfg.train.eval_episodes, "rebel.episodes", rebel.episodes, "<= train.eval_episodes")
        if not cfg.pixels:  # the pixel trainer checks in agent steps
            _check(rebel.horizon <= cfg.env.episode_length, "rebel.horizon", rebel.horizon, "<= env.episode_length")
            cfg.check_complete_episode("rebel.source='onpolicy'", "V's episodes", "--rebel.source replay")

    def knob(self, cfg) -> jax.Array:
        return jnp.asarray(cfg.rebel.lam, jnp.float32)

    def trajectory_size(self, cfg, episode_length, pixels):
        if cfg.rebel.source != "onpolicy":
            return None
        return cfg.rebel.onpolicy_size(cfg.train.eval_episodes, episode_length, pixels)

    def episode_lengths(self, cfg):
        if cfg.rebel.source == "replay":
            return {"rebel.segment_length": cfg.rebel.segment_length}
        return {"rebel.horizon": cfg.rebel.horizon}

    def value_trajectories(self, trainer, ts, key: jax.Array, agent_step):
        """V's trajectories: ``(obs, actions (N, T, A), predict_fn)``, ``predict_fn(params, obs, actions) -> (M, N,
        T)`` the members' rewards (None: the ensemble's ``predict`` on ``obs`` as they are).

        On a state task, ``onpolicy``: the first ``rebel.horizon`` steps of the evaluation environments' last
        complete episodes, N = ``rebel.episodes`` and T = ``rebel.horizon`` (by default all of them, whole);
        ``replay``: ``rebel.num_segments`` replay segments, actions redrawn from the current policy (``a_h ~
        pi_theta``, held fixed). On a pixel task the stacks are kept out of the closure (:meth:`_pixel_trajectories`).
        """
        if trainer.cfg.pixels:
            return self._pixel_trajectories(trainer, ts, key, agent_step)
        rebel = trainer.cfg.rebel
        if rebel.source == "onpolicy":
            last = ts.eval_trajectory["last"]
            return jnp.swapaxes(last["obs"], 0, 1), jnp.swapaxes(last["action"], 0, 1), None
        key_segments, key_actions = jax.random.split(key)
        seg = trainer.sample_segments(ts.buffer, key_segments, rebel.num_segments, rebel.segment_length)
        return seg.obs, trainer.agent.act(ts.agent, seg.obs, key_actions, None), None

    def _pixel_trajectories(self, trainer, ts, key: jax.Array, agent_step: jax.Array):
        """V's trajectories on a pixel task. ``onpolicy``: the first ``rebel.horizon`` agent steps of the last
        complete episodes of ``rebel.episodes`` evaluation environments (the mean action of the DrQ-v2 policy frozen
        at the episode start); ``obs`` are their kept newest frames (N, T, H, W, 3), whose stacks ``predict_fn``
        rebuilds (:func:`rebel_jax.agents.frame_replay.episode_stacks`). ``replay``: ``rebel.num_segments`` replay
        segments
        of ``rebel.segment_length`` steps from the query pool, actions redrawn once from the current DrQ-v2 policy
        (its exploration noise at ``agent_step``) and held fixed; ``obs`` are their places (N, T, 2) = (row, env),
        whose frames ``predict_fn`` gathers from the replay (``pixel_reward.place_rewards``).
        """
        rebel, rcfg, buffer = trainer.cfg.rebel, trainer.reward_cfg, ts.buffer
        if rebel.source == "onpolicy":
            last = ts.eval_trajectory["last"]
            stack = trainer.env.frames

            def episode_rewards(params, frames, action):
                return reward_model.predict(rcfg, params, frame_replay.episode_stacks(frames, stack), action)

            return jnp.swapaxes(last["frame"], 0, 1), jnp.swapaxes(last["action"], 0, 1), episode_rewards
        key_segments, key_actions = jax.random.split(key)
        length = rebel.segment_length
        places = trainer.sample_segments(buffer, key_segments, rebel.num_segments, length)
        rows = pixel_reward.segment_rows(places.row, length)
        envs = jnp.broadcast_to(places.env[:, None], rows.shape)

        def act(inputs):
            row, env, key = inputs
            stacks = frame_replay.row_stacks(buffer, row % buffer.rows, env)
            return trainer.agent.act(ts.agent, stacks, key, agent_step)

        actions = jax.lax.map(act, (rows, envs, jax.random.split(key_actions, rebel.num_segments)))  # one at a time

        def predict_fn(params, place, action):
            return pixel_reward.place_rewards(rcfg, params, buffer, place, action)

        return jnp.stack([rows, envs], axis=-1), actions, predict_fn

    def best_segments(self, trainer, ts):
        """``V*``'s segments: the ``rebel.best_segments`` labelled segments (both sides of every stored pair) of
        highest ensemble-mean learned return at the session's start, and their validity (empty slots never win).
        On pixels their returns are computed by chunks and the segments gathered from the store's copies."""
        rcfg, k, reward = trainer.reward_cfg, trainer.cfg.rebel.best_segments, ts.reward
        if not trainer.cfg.pixels:
            return best_segments(rcfg, reward.params, reward.data, k)
        data = reward.data
        filled = jnp.tile(jnp.arange(data.capacity) < data.count, 2)  # a sides, then b sides
        returns = jnp.mean(pixel_reward.stored_returns(rcfg, reward.params, data), axis=0)
        index, valid = top_segments(returns, filled, k)
        return pixel_reward.stored_side(data, index), valid

    def reward_terms(self, trainer, ts, key, agent_step):
        """The BT loss and ``lambda * V`` (``rebel.form`` lower_bound) or ``lambda * (V* - V)`` (penalty), through
        :func:`agent_value_term` and :func:`value_gap_term`. ``rebel.normalize`` divides by the spread of the
        per-step rewards of the minibatch's labelled pairs (no extra encoder pass on pixels)."""
        rcfg, rebel = trainer.reward_cfg, trainer.cfg.rebel
        obs, actions, predict_fn = self.value_trajectories(trainer, ts, key, agent_step)
        common = dict(estimator=rebel.estimator, normalize=rebel.normalize, predict_fn=predict_fn)
        if rebel.form == "penalty":  # V(pi*(nu)) from the best labelled segments, ranked once per session.
            best, valid = self.best_segments(trainer, ts)
            value = value_gap_term(rcfg, ts.lam, obs, actions, best, valid, rebel.gamma, **common)
        else:
            value = agent_value_term(rcfg, ts.lam, obs, actions, rebel.gamma, **common)
        return [reward_model.bt_loss(rcfg), value]
