"""Soft actor-critic with a learned temperature, in B-Pref's variant.

One :meth:`SAC.update` is: a twin-critic step on the soft Bellman residual, an actor step
on the reparameterised policy objective, a temperature step, and a Polyak update of the
target critic every ``target_every`` updates (B-Pref updates the actor every step).

Each loss comes from a factory returning a pure ``loss(params, batch, key, **context)``
where ``context`` holds the non-differentiated inputs (other networks' parameters,
temperature) as keywords; binding them with :func:`functools.partial` gives the
``(params, batch, key) -> (loss, metrics)`` form applied by :func:`gradient_step`.

References:
    Haarnoja et al. 2018b, "Soft Actor-Critic Algorithms and Applications", arXiv:1812.05905.
    Lee et al. 2021, "B-Pref: Benchmarking Preference-Based Reinforcement Learning".
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, Literal

import flax.struct
import jax
import jax.numpy as jnp
import optax

from rebel_jax.agents.base import UpdateSchedule
from rebel_jax.agents.networks import Actor, DoubleCritic, mlp_flops, mode_action, sample_action
from rebel_jax.agents.replay import Transition
from rebel_jax.core.errors import check as _check

Precision = Literal["tf32", "highest", "bf16"]

MAX_UTD = 100.0
"""The largest ``sac.utd`` accepted: 100 updates per transition is far beyond any published setting
(B-Pref 1, REDQ 20), and a larger value makes a round run for hours with no output."""


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """Soft actor-critic (Haarnoja et al. 2018) with B-Pref's settings by default."""

    hidden: int = 1024
    """Width of each hidden layer of the actor and of each critic."""
    depth: int = 2
    """Hidden layers of the actor and of each critic."""
    batch_size: int = 1024
    """Transitions per gradient step."""
    actor_lr: float = 5e-4
    """Adam learning rate of the actor."""
    critic_lr: float = 5e-4
    """Adam learning rate of the twin critic."""
    alpha_lr: float = 1e-4
    """Adam learning rate of the log-temperature."""
    init_temperature: float = 0.1
    """Initial entropy temperature alpha."""
    gamma: float = 0.99
    """Discount factor."""
    tau: float = 0.005
    """Polyak rate of the target critic."""
    target_every: int = 2
    """Gradient steps between target-critic updates."""
    log_std_min: float = -5.0
    """Lower clamp of the actor's log standard deviation."""
    log_std_max: float = 2.0
    """Upper clamp of the actor's log standard deviation."""
    utd: float = 1.0
    """Gradient updates per collected transition (update-to-data ratio); ``round(utd * num_envs)`` per
    vector step. B-Pref uses 1; lower values are cheaper (BENCHMARKS.md) and a recorded deviation."""
    precision: Precision = "tf32"
    """Matmul precision: ``tf32`` (XLA's default on GPU), ``highest`` (fp32) or ``bf16`` (bf16 compute, fp32 params)."""

    def validate(self) -> None:
        for name in ("hidden", "depth", "batch_size", "target_every"):
            _check(getattr(self, name) >= 1, f"sac.{name}", getattr(self, name), ">= 1")
        for name in ("actor_lr", "critic_lr", "alpha_lr", "init_temperature"):
            _check(getattr(self, name) > 0, f"sac.{name}", getattr(self, name), "> 0")
        _check(0 <= self.gamma < 1, "sac.gamma", self.gamma, "[0, 1)")
        _check(0 < self.tau <= 1, "sac.tau", self.tau, "(0, 1]")
        _check(self.log_std_min < self.log_std_max, "sac.log_std_min", self.log_std_min, "< log_std_max")
        _check(0 < self.utd <= MAX_UTD, "sac.utd", self.utd, f"(0, {MAX_UTD:g}] updates per transition")
        _check(self.precision in ("tf32", "highest", "bf16"), "sac.precision", self.precision, "tf32, highest, bf16")


__all__ = [
    "SAC",
    "SACState",
    "Transition",
    "gradient_step",
    "make_actor_loss",
    "make_alpha_loss",
    "make_critic_loss",
    "polyak",
    "update_flops",
]

Params = Any
Metrics = dict[str, jax.Array]
LossFn = Callable[..., tuple[jax.Array, Metrics]]


@flax.struct.dataclass
class SACState:
    """Everything SAC carries between updates.

    Attributes:
        actor_params, critic_params, target_critic_params: network parameters.
        log_alpha: () log of the entropy temperature.
        actor_opt, critic_opt, alpha_opt: Adam states of the three optimisers.
        steps: () int32 number of updates done.
    """

    actor_params: Params
    critic_params: Params
    target_critic_params: Params
    log_alpha: jax.Array
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    alpha_opt: optax.OptState
    steps: jax.Array


def gradient_step(
    loss_fn: LossFn, optimizer: optax.GradientTransformation, params, opt_state, batch, key: jax.Array
) -> tuple[Params, optax.OptState, Metrics]:
    """One optimiser step on any ``(params, batch, key) -> (loss, metrics)`` loss.

    Args:
        loss_fn: pure loss, differentiated with respect to its first argument.
        optimizer: optax transformation.
        params: parameters to update.
        opt_state: ``optimizer``'s state for ``params``.
        batch: data passed through to ``loss_fn``.
        key: PRNG key passed through to ``loss_fn``.

    Returns:
        params, opt_state: updated; metrics: ``loss_fn``'s metrics (before the step).
    """
    grads, metrics = jax.grad(loss_fn, has_aux=True)(params, batch, key)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, metrics


def make_critic_loss(actor: Actor, critic: DoubleCritic, gamma: float) -> LossFn:
    """Soft Q loss J_Q (Haarnoja et al. 2018b, eq. 5; gradient eq. 6) for both critics.

    The target is ``r + discount * gamma * (min_i Qtarget_i(s', a') - alpha log pi(a'|s'))``
    with ``a' ~ pi(.|s')``, held fixed; the loss is the sum of both critics' mean squared
    errors (B-Pref).

    Args:
        actor, critic: the modules.
        gamma: discount factor.

    Returns:
        ``loss(critic_params, batch, key, *, actor_params, target_params, alpha)``.
    """

    def loss(critic_params, batch: Transition, key, *, actor_params, target_params, alpha):
        mean, log_std = actor.apply(actor_params, batch.next_obs)
        next_action, next_log_prob = sample_action(mean, log_std, key)
        tq1, tq2 = critic.apply(target_params, batch.next_obs, next_action)
        soft_value = jnp.minimum(tq1, tq2) - alpha * next_log_prob
        target = jax.lax.stop_gradient(batch.reward + batch.discount * gamma * soft_value)
        q1, q2 = critic.apply(critic_params, batch.obs, batch.action)
        value = jnp.mean(jnp.square(q1 - target)) + jnp.mean(jnp.square(q2 - target))
        return value, {"critic_loss": value, "q": 0.5 * jnp.mean(q1 + q2)}

    return loss


def make_actor_loss(actor: Actor, critic: DoubleCritic) -> LossFn:
    """Policy loss J_pi (Haarnoja et al. 2018b, eq. 7, reparameterised; gradient eq. 10).

    ``E_s E_eps [alpha log pi(f(eps; s) | s) - min_i Q_i(s, f(eps; s))]`` with the critic
    and the temperature held fixed.

    Args:
        actor, critic: the modules.

    Returns:
        ``loss(actor_params, batch, key, *, critic_params, alpha)``; its metrics hold
        ``entropy`` = -mean log pi, used by the temperature loss.
    """

    def loss(actor_params, batch: Transition, key, *, critic_params, alpha):
        mean, log_std = actor.apply(actor_params, batch.obs)
        action, log_prob = sample_action(mean, log_std, key)
        q1, q2 = critic.apply(critic_params, batch.obs, action)
        value = jnp.mean(alpha * log_prob - jnp.minimum(q1, q2))
        return value, {"actor_loss": value, "entropy": -jnp.mean(log_prob)}

    return loss


def make_alpha_loss(action_size: int) -> LossFn:
    """Temperature loss J(alpha) (Haarnoja et al. 2018b, eq. 18), target entropy -|A|.

    ``alpha * (H - target_entropy)`` with ``alpha = exp(log_alpha)`` and the policy entropy
    estimate ``H`` held fixed, as B-Pref (which differentiates alpha, not log alpha).

    Args:
        action_size: action dimension; the target entropy is ``-action_size``.

    Returns:
        ``loss(log_alpha, batch, key, *, entropy)`` with ``entropy`` the actor step's
        ``-mean log pi`` on the same batch.
    """
    target_entropy = -float(action_size)

    def loss(log_alpha, batch: Transition, key, *, entropy):
        del batch, key  # Unused: the entropy estimate comes from the actor step.
        value = jnp.exp(log_alpha) * jax.lax.stop_gradient(entropy - target_entropy)
        return value, {"alpha_loss": value}

    return loss


def polyak(target, online, tau: float, move: jax.Array):
    """``target + tau (online - target)`` where ``move`` is true, else ``target`` unchanged.

    Args:
        target, online: parameter pytrees.
        tau: Polyak rate.
        move: () bool, may be traced.

    Returns:
        The new target parameters.
    """
    moved = optax.incremental_update(online, target, tau)
    return jax.tree.map(lambda m, t: jnp.where(move, m, t), moved, target)


class SAC:
    """SAC built from a :class:`SACConfig`; every method is pure, jittable and vmappable.

    It implements :class:`rebel_jax.agents.base.Agent` (the ``step`` arguments unused: SAC has no schedule).

    Args:
        cfg: hyperparameters.
        obs_size: observation dimension.
        action_size: action dimension (actions in [-1, 1]).
    """

    def __init__(self, cfg: SACConfig, obs_size: int, action_size: int):
        self.cfg, self.obs_size, self.action_size = cfg, obs_size, action_size
        self.actor = Actor(cfg.hidden, cfg.depth, action_size, cfg.log_std_min, cfg.log_std_max, cfg.precision)
        self.critic = DoubleCritic(cfg.hidden, cfg.depth, cfg.precision)
        self.actor_opt = optax.adam(cfg.actor_lr)
        self.critic_opt = optax.adam(cfg.critic_lr)
        self.alpha_opt = optax.adam(cfg.alpha_lr)
        self.critic_loss = make_critic_loss(self.actor, self.critic, cfg.gamma)
        self.actor_loss = make_actor_loss(self.actor, self.critic)
        self.alpha_loss = make_alpha_loss(action_size)
        self.batch_size = cfg.batch_size
        self.sample_args: dict[str, Any] = {}

    metric_names = ("critic_loss", "actor_loss", "alpha_loss", "alpha", "q", "entropy")

    def schedule(self, num_envs: int) -> UpdateSchedule:
        """``utd * num_envs`` updates at every vector step once ``(t + 1) * num_envs`` reach the seed steps (B-Pref)."""
        return UpdateSchedule(per_step=max(1, round(self.cfg.utd * num_envs)), period=1, counts_current=True)

    def _init_critic(self, key: jax.Array):
        obs, action = jnp.zeros((1, self.obs_size)), jnp.zeros((1, self.action_size))
        return self.critic.init(key, obs, action)

    def init(self, key: jax.Array) -> SACState:
        """Fresh state: random networks, target = critic, ``alpha = init_temperature``.

        Args:
            key: PRNG key.

        Returns:
            The initial :class:`SACState`.
        """
        key_actor, key_critic = jax.random.split(key)
        actor_params = self.actor.init(key_actor, jnp.zeros((1, self.obs_size)))
        critic_params = self._init_critic(key_critic)
        log_alpha = jnp.log(jnp.asarray(self.cfg.init_temperature, jnp.float32))
        return SACState(
            actor_params=actor_params,
            critic_params=critic_params,
            target_critic_params=critic_params,
            log_alpha=log_alpha,
            actor_opt=self.actor_opt.init(actor_params),
            critic_opt=self.critic_opt.init(critic_params),
            alpha_opt=self.alpha_opt.init(log_alpha),
            steps=jnp.zeros((), jnp.int32),
        )

    def reset_critic(self, state: SACState, key: jax.Array) -> SACState:
        """Re-initialise critic, target critic and critic optimiser; keep actor and alpha.

        Used after unsupervised pre-training (PEBBLE).

        Args:
            state: current state.
            key: PRNG key.

        Returns:
            The state with a fresh critic.
        """
        critic_params = self._init_critic(key)
        return state.replace(
            critic_params=critic_params,
            target_critic_params=critic_params,
            critic_opt=self.critic_opt.init(critic_params),
        )

    def _critic_step(self, state: SACState, batch: Transition, key: jax.Array):
        loss = functools.partial(
            self.critic_loss,
            actor_params=state.actor_params,
            target_params=state.target_critic_params,
            alpha=jnp.exp(state.log_alpha),
        )
        params, opt, metrics = gradient_step(loss, self.critic_opt, state.critic_params, state.critic_opt, batch, key)
        return state.replace(critic_params=params, critic_opt=opt), metrics

    def _actor_step(self, state: SACState, batch: Transition, key: jax.Array):
        loss = functools.partial(self.actor_loss, critic_params=state.critic_params, alpha=jnp.exp(state.log_alpha))
        params, opt, metrics = gradient_step(loss, self.actor_opt, state.actor_params, state.actor_opt, batch, key)
        return state.replace(actor_params=params, actor_opt=opt), metrics

    def _alpha_step(self, state: SACState, batch: Transition, key: jax.Array, entropy: jax.Array):
        loss = functools.partial(self.alpha_loss, entropy=entropy)
        log_alpha, opt, metrics = gradient_step(loss, self.alpha_opt, state.log_alpha, state.alpha_opt, batch, key)
        return state.replace(log_alpha=log_alpha, alpha_opt=opt), metrics

    def update(
        self, state: SACState, batch: Transition, key: jax.Array, step: jax.Array | None = None
    ) -> tuple[SACState, Metrics]:
        """One SAC update: critic, actor, temperature, then the target every ``target_every``.

        The target critic moves (Polyak rate ``tau``) on updates where ``steps`` (before
        this update) is a multiple of ``target_every``.

        Args:
            state: current state.
            batch: a :class:`Transition` batch.
            key: PRNG key.
            step: unused (the agent steps taken; SAC has no schedule).

        Returns:
            state: updated, ``steps`` incremented.
            metrics: critic_loss, actor_loss, alpha_loss, alpha (used in this update),
                q (mean predicted Q on the batch), entropy (-mean log pi).
        """
        del step  # Unused.
        key_critic, key_actor, key_alpha = jax.random.split(key, 3)
        alpha = jnp.exp(state.log_alpha)
        state, critic_metrics = self._critic_step(state, batch, key_critic)
        state, actor_metrics = self._actor_step(state, batch, key_actor)
        state, alpha_metrics = self._alpha_step(state, batch, key_alpha, actor_metrics["entropy"])
        move = state.steps % self.cfg.target_every == 0
        target = polyak(state.target_critic_params, state.critic_params, self.cfg.tau, move)
        state = state.replace(target_critic_params=target, steps=state.steps + 1)
        return state, {**critic_metrics, **actor_metrics, **alpha_metrics, "alpha": alpha}

    def act(self, state: SACState, obs: jax.Array, key: jax.Array, step: jax.Array | None = None) -> jax.Array:
        """Stochastic action ``tanh(mean + std * eps)``.

        Args:
            state: the agent's state (its actor is read).
            obs: (..., obs_size).
            key: PRNG key.
            step: unused.

        Returns:
            (..., action_size) actions in (-1, 1).
        """
        del step  # Unused.
        mean, log_std = self.actor.apply(state.actor_params, obs)
        return sample_action(mean, log_std, key)[0]

    def policy(self, state: SACState):
        """The actor's parameters: what :meth:`mean_action` reads."""
        return state.actor_params

    def mean_action(self, policy, obs: jax.Array) -> jax.Array:
        """The mean action of ``policy`` (:meth:`policy`), :meth:`act_deterministic`."""
        return self.act_deterministic(policy, obs)

    def act_deterministic(self, actor_params, obs: jax.Array) -> jax.Array:
        """Mean action ``tanh(mean)`` for evaluation.

        Args:
            actor_params: actor parameters.
            obs: (..., obs_size).

        Returns:
            (..., action_size) actions in (-1, 1).
        """
        return mode_action(self.actor.apply(actor_params, obs)[0])

    def q_values(self, critic_params, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Both critics' Q(s, a).

        Args:
            critic_params: critic parameters.
            obs: (..., obs_size); action: (..., action_size).

        Returns:
            q1, q2: each (...).
        """
        return self.critic.apply(critic_params, obs, action)


def update_flops(cfg: SACConfig, obs_size: int, action_size: int) -> float:
    """Matmul FLOPs of one :meth:`SAC.update` (forward and backward), for benchmarks.

    Counted per batch row: the critic step runs the actor forward on s', the target twin
    forward, and the twin forward + backward (3x forward); the actor step runs the actor
    forward + backward (3x) and the twin forward + backward to the action only (2x: the
    critic's weight gradients are not computed). The temperature step has no matmuls.

    Args:
        cfg: hyperparameters (sizes and batch size).
        obs_size, action_size: problem sizes.

    Returns:
        FLOPs of one update.
    """
    actor = mlp_flops(obs_size, cfg.hidden, cfg.depth, 2 * action_size)
    twin = 2 * mlp_flops(obs_size + action_size, cfg.hidden, cfg.depth, 1)
    critic_step = actor + twin + 3 * twin
    actor_step = 3 * actor + 2 * twin
    return float(cfg.batch_size * (critic_step + actor_step))
