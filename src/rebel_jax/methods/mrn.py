"""MRN, Meta-Reward-Net (Liu et al., NeurIPS 2022): the reward also learnt through the critic it trains.

MRN (RyanLiu112/MRN@ef67eaf, built on B-Pref) is PEBBLE plus a bilevel step (:meth:`MRN.agent_step`) every
``mrn.meta_period`` environment steps of the feedback phase while the label budget lasts
(train_MRN.py:413-417). On a replay minibatch, the critic theta takes one plain SGD step at the critic's
learning rate on its soft Bellman loss with the ensemble-mean learned reward ``r_phi`` (train_MRN.py:187-215,
utils.py:274-296, whose copied Adam state is never read):

    theta'(phi) = theta - critic_lr * grad_theta [MSE(Q1_theta, y) + MSE(Q2_theta, y)],
    y = r_phi(s, a) + discount * gamma * stop_gradient(min_j Qtarget_j(s', a') - alpha log pi(a'|s')).

The outer loss scores each of the last session's labelled pairs by the updated critic's Q at the first
state-action of each segment, each critic head a pair of logits (train_MRN.py:172-183, :219-239):
``outer_weight * (CE(Q1_theta') + CE(Q2_theta'))``. Its gradient with respect to phi, through the inner step,
drives one step of the reward ensemble's own optimiser (the preference training's Adam and its state,
train_MRN.py:242-244), and the replay is relabelled with the new reward (:415). The reward is still trained on
the labels each session as PEBBLE's. Differences from the original: docs/methods.md.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax

from rebel_jax.agents import replay
from rebel_jax.agents.networks import sample_action
from rebel_jax.core.errors import check
from rebel_jax.methods.base import Method
from rebel_jax.preference import reward_model


@dataclasses.dataclass(frozen=True)
class MRNConfig:
    """MRN's settings: its walker_walk command (RyanLiu112/MRN@ef67eaf:README.md:45; config/train_MRN.yaml)."""

    meta_period: int = 1000
    """Environment steps between two bilevel steps (``num_meta_steps``: 1000 in the walker command, 10000 in the
    door-open one, 5000 in train_MRN.yaml:12); a multiple of ``env.num_envs``."""
    outer_weight: float = 0.1
    """Weight of the outer cross-entropy (``outer_weight``, train_MRN.yaml:29)."""
    outer_pairs: int = 0
    """The last this-many labelled pairs make the outer loss (``reward_batch``, the session's size); 0: the
    session's size ``feedback.queries``."""

    def validate(self, num_envs: int) -> None:
        """Checks the ranges; ``num_envs`` the training environments of a vector step."""
        check(self.meta_period >= 1, "mrn.meta_period", self.meta_period, ">= 1")
        allowed = f"a multiple of env.num_envs={num_envs} (one bilevel step per vector step)"
        check(self.meta_period % num_envs == 0, "mrn.meta_period", self.meta_period, allowed)
        check(self.outer_weight >= 0, "mrn.outer_weight", self.outer_weight, ">= 0")
        check(self.outer_pairs >= 0, "mrn.outer_pairs", self.outer_pairs, ">= 0 (0: feedback.queries)")


def scheduled(cfg, num_envs: int, t: jax.Array) -> jax.Array:
    """Whether vector step ``t`` (unbatched) is on MRN's schedule, its budget counted by ``asked`` pairs: env step
    ``s = t * num_envs`` after the first feedback session, a multiple of ``meta_period``, and, under
    ``feedback.budget`` ``asked``, ``total_feedback < max_feedback`` after the sessions held by then."""
    step = t * num_envs
    due = (step > cfg.feedback_start) & (step % cfg.mrn.meta_period == 0)
    if cfg.feedback.budget == "asked":
        due &= remaining(cfg, 0, step) > 0
    return due


def remaining(cfg, stored, step: jax.Array) -> jax.Array:
    """Labels left after the sessions held by env step ``step``, ``stored`` held: ``budget.remaining_budget``'s
    count (asked: ``labels - sessions * queries``; answered: ``labels - stored``)."""
    feedback = cfg.feedback
    return feedback.labels - (sessions_held(cfg, step) * feedback.queries if feedback.budget == "asked" else stored)


def sessions_held(cfg, step: jax.Array) -> jax.Array:
    """Feedback sessions held before the updates at env step ``step`` (>= ``feedback_start``)."""
    return (step - cfg.feedback_start) // cfg.feedback.interval + 1


def meta_due(cfg, num_envs: int, t: jax.Array, stored: jax.Array) -> jax.Array:
    """Whether vector step ``t`` runs a bilevel step for a seed with ``stored`` labels: :func:`scheduled` and labels
    left (:func:`remaining` after the sessions held: the original's ``total_feedback < max_feedback``)."""
    return scheduled(cfg, num_envs, t) & (remaining(cfg, stored, t * num_envs) > 0)


def last_pairs(store: reward_model.PairStore, n: int):
    """The last ``n`` labelled pairs of ``store``, as the first state-action of each segment.

    Returns:
      ``a``, ``b`` (:class:`rebel_jax.preference.reward_model.Steps`, obs (n, obs_size), action (n, act_size)),
      ``labels``
      (n,) ``P(b preferred)`` and ``weight`` (n,) 1 for stored pairs (0 where fewer than ``n`` are).
    """
    n = min(n, store.capacity)
    slots = (store.ptr - n + jnp.arange(n)) % store.capacity
    weight = (jnp.arange(n) >= n - store.count).astype(jnp.float32)
    first = [reward_model.Steps(seg.obs[slots, 0], seg.action[slots, 0]) for seg in (store.a, store.b)]
    return first[0], first[1], store.labels[slots], weight


def soft_value(sac, state, next_obs: jax.Array, key: jax.Array) -> jax.Array:
    """``min_j Qtarget_j(s', a') - alpha log pi(a'|s')`` with ``a' ~ pi(s')``, held fixed (train_MRN.py:199-204)."""
    mean, log_std = sac.actor.apply(state.actor_params, next_obs)
    action, log_prob = sample_action(mean, log_std, key)
    tq1, tq2 = sac.critic.apply(state.target_critic_params, next_obs, action)
    return jax.lax.stop_gradient(jnp.minimum(tq1, tq2) - jnp.exp(state.log_alpha) * log_prob)


def inner_loss(sac, critic_params, reward: jax.Array, batch: replay.Transition, value: jax.Array) -> jax.Array:
    """The critic's loss with the reward ``reward`` (B,) differentiable: the sum of both heads' mean squared errors
    to ``reward + discount * gamma * value`` (train_MRN.py:205-209)."""
    target = reward + batch.discount * sac.cfg.gamma * value
    q1, q2 = sac.critic.apply(critic_params, batch.obs, batch.action)
    return jnp.mean(jnp.square(q1 - target)) + jnp.mean(jnp.square(q2 - target))


def outer_loss(sac, rcfg, reward_params, critic_params, batch, value, pairs, lr: float, weight: float) -> jax.Array:
    """MRN's outer loss as a function of the reward ensemble's parameters (differentiate it with respect to them).

    Args:
      sac: the agent (:class:`rebel_jax.agents.sac.SAC`), its networks.
      rcfg: the reward ensemble's settings.
      reward_params: phi, the members' parameters.
      critic_params: theta, the critic's parameters before the inner step.
      batch: the replay minibatch of the inner step.
      value: (B,) :func:`soft_value` of ``batch.next_obs``.
      pairs: :func:`last_pairs`.
      lr: the inner step's learning rate (the critic's).
      weight: ``outer_weight``.

    Returns:
      ``weight * (CE_1 + CE_2)``: each head's cross-entropy, the mean over the weighted pairs, of the logits
      ``[Q_j(a), Q_j(b)]`` of the critic after one SGD step on :func:`inner_loss` with ``r_phi``.
    """

    def inner(theta):
        reward = reward_model.mean_reward(rcfg, reward_params, batch.obs, batch.action)
        return inner_loss(sac, theta, reward, batch, value)

    theta = jax.tree.map(lambda p, g: p - lr * g, critic_params, jax.grad(inner)(critic_params))
    a, b, labels, mask = pairs
    ce = [
        reward_model.bt_cross_entropy(q_b - q_a, labels)
        for q_a, q_b in zip(sac.q_values(theta, a.obs, a.action), sac.q_values(theta, b.obs, b.action), strict=True)
    ]
    return weight * sum(jnp.sum(c * mask) for c in ce) / jnp.maximum(jnp.sum(mask), 1.0)


class MRN(Method):
    """PEBBLE with MRN's bilevel reward step, every --mrn.meta-period env steps while labels remain."""

    name = "mrn"
    config = MRNConfig
    pixels = False

    def validate(self, cfg):
        cfg.mrn.validate(cfg.env.num_envs)
        check(not cfg.pixels, "env.task", cfg.env.task, "a state task with --algo mrn (its bilevel step is SAC's)")

    def agent_step(self, trainer, ts, t, key):
        """MRN's bilevel step after the vector step's updates, where :func:`meta_due`: the outer loss's gradient
        through one SGD step of the critic, one step of the reward optimiser, then the replay relabelled.

        Returns:
          The state and the metrics ``outer_loss`` (before the reward's step) and ``meta_step`` (1), NaN where the
          step did not run.
        """
        cfg, sac, rcfg = trainer.cfg, trainer.agent, trainer.reward_cfg
        mrn, n = cfg.mrn, trainer.num_train
        nan = jnp.full((), jnp.nan, jnp.float32)

        reward, buffer = ts.reward, ts.buffer
        old = (reward.params, reward.opt_state, buffer.learned_reward)

        def meta():  # what it changes comes out of the cond; the replay's other fields are only read
            key_batch, key_next = jax.random.split(key)
            batch = trainer.sample(buffer, key_batch, True)
            value = soft_value(sac, ts.agent, batch.next_obs, key_next)
            pairs = last_pairs(reward.data, mrn.outer_pairs or cfg.feedback.queries)
            args = (ts.agent.critic_params, batch, value, pairs, cfg.sac.critic_lr, mrn.outer_weight)
            loss, grads = jax.value_and_grad(outer_loss, argnums=2)(sac, rcfg, reward.params, *args)
            optimizer = trainer.reward_optimizer or optax.adam(rcfg.lr)
            updates, opt_state = optimizer.update(grads, reward.opt_state, reward.params)
            params = optax.apply_updates(reward.params, updates)

            def reward_fn(obs, action):
                return reward_model.mean_reward(rcfg, params, obs, action)

            learned = replay.relabel(buffer, reward_fn, chunk_rows=max(1, 16_384 // n)).learned_reward
            run = meta_due(cfg, n, t, reward.data.count)  # per seed: its labels left (answered budget)
            new = jax.tree.map(lambda x, y: jnp.where(run, x, y), (params, opt_state, learned), old)
            return new, {"outer_loss": jnp.where(run, loss, nan), "meta_step": jnp.where(run, 1.0, nan)}

        def skip():
            return old, {"outer_loss": nan, "meta_step": nan}

        (params, opt_state, learned), metrics = jax.lax.cond(scheduled(cfg, n, t), meta, skip)
        reward = reward.replace(params=params, opt_state=opt_state)
        return ts.replace(reward=reward, buffer=buffer.replace(learned_reward=learned)), metrics
