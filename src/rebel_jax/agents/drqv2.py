"""DrQ-v2: the pixel agent of SURF's pixel experiments, as pure, jittable, vmappable functions.

One :meth:`DrQV2.update` is DrQ-v2's ``DrQV2Agent.update`` (facebookresearch/drqv2 c0c650b,
drqv2.py:230-262; the same code in alinlab/SURF 214bc1d, branch ``pixel``, agent/drqv2.py:311-342):

1. random shifts of ``obs`` and ``next_obs``, each with its own shifts (drqv2.py:240-242);
2. ``obs`` encoded with gradient, ``next_obs`` without (drqv2.py:243-246);
3. a critic step on the n-step TD error with the scheduled, clipped target-policy noise, whose
   gradient trains the critic *and the encoder* (drqv2.py:177-204);
4. an actor step on ``-min(Q1, Q2)`` of the (already updated) critic at the *detached* features of
   step 2: the actor's gradient never reaches the encoder (drqv2.py:206-228, 256);
5. a Polyak update of the target critic with rate ``tau`` after every update (drqv2.py:259).

There is no target encoder: the target critic reads the online encoder's features of
``next_obs`` (drqv2.py:244-246). Updates happen every ``update_every`` agent steps
(drqv2.py:233-234); the caller (the trainer) decides when.

Each loss comes from a factory returning a pure ``loss(params, batch, key, **context)``, as in
:mod:`rebel_jax.agents.sac`.

References:
    Yarats et al. 2021, "Mastering Visual Continuous Control: Improved Data-Augmented
    Reinforcement Learning", arXiv:2107.09645.
    Park et al. 2022, "SURF", ICLR (its pixel experiments use this agent).
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
from rebel_jax.agents.networks import Encoder, PixelActor, PixelCritic
from rebel_jax.core.errors import check as _check

Params = Any
Metrics = dict[str, jax.Array]
LossFn = Callable[..., tuple[jax.Array, Any]]

CLAMP_EPS = 1e-6
"""Actions are clamped to ``[-1 + eps, 1 - eps]`` (DrQ-v2's ``TruncatedNormal``, utils.py:106, 112-115)."""


@dataclasses.dataclass(frozen=True)
class DrQV2Config:
    """DrQ-v2's hyperparameters (cfgs/config.yaml of drqv2 and of SURF's pixel branch).

    The defaults are DrQ-v2's and cheetah_run's (cfgs/task/cheetah_run.yaml -> medium.yaml);
    :func:`task_config` gives walker's (cfgs/task/walker_*.yaml -> easy.yaml).
    """

    feature_dim: int = 50
    """Trunk width after the encoder (config.yaml:32 ``feature_dim``)."""
    hidden: int = 1024
    """Width of the actor's and of each critic's hidden layers (config.yaml:44 ``hidden_dim``)."""
    depth: int = 2
    """Hidden layers of the actor and of each critic (drqv2.py:77-81, 103-111)."""
    lr: float = 1e-4
    """Adam learning rate of the encoder, actor and critic (config.yaml:31 ``lr``; drqv2.py:148-150)."""
    tau: float = 0.01
    """Polyak rate of the target critic, applied after every update (config.yaml:40; drqv2.py:259)."""
    update_every: int = 2
    """Agent steps per update (config.yaml:41 ``update_every_steps``; drqv2.py:233)."""
    batch_size: int = 256
    """Transitions per update (config.yaml:21; walker 512, cfgs/task/walker_walk.yaml:7)."""
    nstep: int = 3
    """Steps of the n-step return (config.yaml:20; walker 1, cfgs/task/walker_walk.yaml:6)."""
    gamma: float = 0.99
    """Discount per agent step (config.yaml:9 ``discount``)."""
    std_init: float = 1.0
    """Exploration standard deviation at agent step 0 (``linear(1.0,0.1,...)``, cfgs/task/medium.yaml:2)."""
    std_final: float = 0.1
    """Exploration standard deviation at the end of the schedule and after."""
    std_steps: int = 500_000
    """Agent steps of the linear schedule (medium.yaml:2: 500,000; easy.yaml:2, walker: 100,000).

    DrQ-v2 evaluates the schedule at ``global_step``, which counts *agent* steps (train.py:175-181,
    drqv2.py:167, 181, 209; utils.py:129-137), so with action repeat 2 these are 1M and 200k frames."""
    std_clip: float = 0.3
    """Clip of the policy noise in the critic target and the actor loss (config.yaml:47; drqv2.py:183, 211)."""
    pad: int = 4
    """Random-shift padding in pixels (drqv2.py:153)."""
    precision: Literal["tf32", "highest", "bf16"] = "tf32"
    """Matmul and convolution precision (see :mod:`rebel_jax.agents.networks`)."""
    kernel_grad: Literal["xla", "patches"] = "xla"
    """How the encoder's kernel gradients are computed: XLA's backward-filter convolutions, or one matrix
    product of the input patches with the output gradient each
    (:func:`rebel_jax.agents.networks.conv_patch_kernel_grad`).
    The same gradients up to float rounding; a speed setting, not a DrQ-v2 one. On one H100 (bf16, 5 seeds
    looped, 2026-11-25) ``patches`` was 28% slower (``benchmarks/results/drqv2_update.json``), so ``xla`` stays
    the default."""
    first_channels: int = 0
    """The encoder's first convolution sees its 9 input channels (3 stacked RGB frames) zero-padded to this many
    (:func:`rebel_jax.agents.networks.channel_padded`; 0: as they are). The same function and parameters up to float
    rounding; a speed setting for convolution kernels that want a multiple of 8 channels, not a DrQ-v2 one."""
    critic_out_f32: bool = False
    """With ``precision`` bf16, compute each critic's output layer (1024 -> 1) in float32, so that Q and the TD
    target are not rounded to bfloat16 (not a DrQ-v2 setting: DrQ-v2 is float32 throughout). Rounded, Q near 5
    moves in steps of 1/32, about the 0.05 per-step reward a lying walker gets, the only signal on the plateau
    where failed walker seeds stay (notes/drqv2_audit.md, difference 1). With it 5 of 8 walker seeds took off by
    120k frames (3 of 8 without) and 4 of 5 walked at 500k (1 of 3 without): never significant, never against it
    (RESULTS.md). The walker DrQ-v2 runs turn it on (``experiments/baselines_h100.sh``, ``drqv2_seed`` with
    ``CRITIC_F32=1``); off by default so that the pixel preference runs, which all rounded Q, keep one setting.
    The same parameters either way."""
    seed_loop: bool = True
    """Run a ``vmap`` of :meth:`DrQV2.update` (the trainer's over seeds) as a loop over its entries
    (``jax.custom_batching.sequential_vmap``: ``lax.map``), one seed's update at a time, instead of one
    batched update: the same numbers up to float rounding. Batched, each of the encoder's
    convolutions and their gradients becomes one grouped convolution (``feature_group_count`` = seeds);
    looped, each is a plain one (not a DrQ-v2 setting). On one H100 the looped update of 5 seeds at
    84x84 (batch 512) takes 30.2 ms against the batched 206.2 ms in tf32
    (``benchmarks/results/drqv2_update.json``), hence on by default."""

    def validate(self) -> None:
        for name in ("feature_dim", "hidden", "depth", "update_every", "batch_size", "nstep", "std_steps"):
            _check(getattr(self, name) >= 1, f"drqv2.{name}", getattr(self, name), ">= 1")
        _check(self.lr > 0, "drqv2.lr", self.lr, "> 0")
        _check(0 < self.tau <= 1, "drqv2.tau", self.tau, "(0, 1]")
        _check(0 <= self.gamma < 1, "drqv2.gamma", self.gamma, "[0, 1)")
        for name in ("std_init", "std_final", "std_clip"):
            _check(getattr(self, name) >= 0, f"drqv2.{name}", getattr(self, name), ">= 0")
        _check(self.pad >= 0, "drqv2.pad", self.pad, ">= 0")
        _check(self.precision in ("tf32", "highest", "bf16"), "drqv2.precision", self.precision, "tf32, highest, bf16")
        _check(self.kernel_grad in ("xla", "patches"), "drqv2.kernel_grad", self.kernel_grad, "xla, patches")
        _check(self.first_channels >= 0, "drqv2.first_channels", self.first_channels, ">= 0")
        _check(isinstance(self.seed_loop, bool), "drqv2.seed_loop", self.seed_loop, "True, False")
        _check(isinstance(self.critic_out_f32, bool), "drqv2.critic_out_f32", self.critic_out_f32, "True, False")


def task_config(task: str, base: DrQV2Config = DrQV2Config()) -> DrQV2Config:
    """``base`` with DrQ-v2's per-task settings (identical in SURF's pixel branch, cfgs/task/).

    walker_{stand,walk} (easy.yaml): std over 100k agent steps; walker_run (medium.yaml): 500k; every
    walker task: n-step 1 and batch 512 (walker_walk.yaml:6-7); cheetah_run (cheetah_run.yaml, medium.yaml):
    the defaults. A ``_pixels`` suffix is ignored.
    """
    name = task.removesuffix("_pixels")
    if name.startswith("walker"):
        steps = 500_000 if name == "walker_run" else 100_000
        return dataclasses.replace(base, nstep=1, batch_size=512, std_steps=steps)
    return base


@flax.struct.dataclass
class PixelTransition:
    """A batch of n-step pixel transitions, DrQ-v2's ``(obs, action, reward, discount, next_obs)``.

    Attributes:
        obs: (B, H, W, 3 * frames) uint8 frame stack, oldest frame first.
        action: (B, action_size) the first action of the n steps.
        reward: (B,) n-step return ``sum_i (gamma^i prod_{j<i} d_j) r_i`` (:func:`nstep_return`).
        discount: (B,) ``gamma^n prod_i d_i``, the weight of the bootstrap value.
        next_obs: (B, H, W, 3 * frames) the frame stack n steps later.
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    discount: jax.Array
    next_obs: jax.Array


def nstep_return(rewards: jax.Array, discounts: jax.Array, gamma: float) -> tuple[jax.Array, jax.Array]:
    """The n-step return and bootstrap discount of DrQ-v2's replay (replay_buffer.py:154-160).

    DrQ-v2's loop is ``R += D * r_i; D *= d_i * gamma`` from ``R = 0, D = 1``: a terminal step
    (``d_i = 0``) keeps its own reward and drops every later one and the bootstrap.

    Args:
        rewards: (..., n) rewards of the n steps.
        discounts: (..., n) 0 where the step terminated the episode, else 1.
        gamma: discount per step.

    Returns:
        reward (...), discount (...).
    """
    n = rewards.shape[-1]
    step = discounts * gamma
    before = jnp.concatenate([jnp.ones_like(step[..., :1]), jnp.cumprod(step, axis=-1)[..., : n - 1]], axis=-1)
    return jnp.sum(before * rewards, axis=-1), jnp.prod(step, axis=-1)


def draw_shifts(key: jax.Array, batch_size: int, pad: int) -> jax.Array:
    """Integer shifts ``(x, y)`` uniform in ``[0, 2 pad]``, one pair per image (drqv2.py:34-38)."""
    return jax.random.randint(key, (batch_size, 2), 0, 2 * pad + 1)


def shift_images(obs: jax.Array, shifts: jax.Array, pad: int) -> jax.Array:
    """DrQ-v2's shift of each image by its own ``(x, y)`` (``RandomShiftsAug.forward``, drqv2.py:19-45).

    DrQ-v2 replicate-pads by ``pad`` (drqv2.py:23), then samples with bilinear ``grid_sample``
    (``align_corners=False``, drqv2.py:42-45) on the grid
    ``linspace(-1 + 1/(H+2p), 1 - 1/(H+2p), H+2p)[:H] + shift * 2/(H+2p)`` (drqv2.py:24-41). In pixel
    units that grid falls on the padded image's pixel centres ``i + shift``, where the bilinear weights
    are 1 and 0: the result is the padded image's ``H x W`` window at ``(y, x) = shift``. It is taken
    here as that window (a slice, exact, in the input's dtype); tests compare it with a NumPy
    ``grid_sample`` on DrQ-v2's grid.

    Args:
        obs: (B, H, W, C) images, any dtype.
        shifts: (B, 2) int ``(x, y)`` in ``[0, 2 pad]``.
        pad: padding in pixels.

    Returns:
        (B, H, W, C) shifted images.
    """
    _, height, width, channels = obs.shape
    padded = jnp.pad(obs, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")  # PyTorch's 'replicate'

    def window(image, shift):
        return jax.lax.dynamic_slice(image, (shift[1], shift[0], 0), (height, width, channels))

    return jax.vmap(window)(padded, shifts)


def random_shift(key: jax.Array, obs: jax.Array, pad: int) -> jax.Array:
    """DrQ-v2's random-shift augmentation: :func:`shift_images` at :func:`draw_shifts`.

    The shifts pass through ``jax.lax.optimization_barrier``, which changes no value: without it XLA fused the
    threefry draws into the per-pixel window loop and recomputed them there (a GPU profile, BENCHMARKS.md).

    Args:
        key: PRNG key.
        obs: (B, H, W, C) images.
        pad: padding in pixels (0: no augmentation).

    Returns:
        (B, H, W, C) shifted images.
    """
    if pad == 0:
        return obs
    return shift_images(obs, jax.lax.optimization_barrier(draw_shifts(key, obs.shape[0], pad)), pad)


def std_schedule(cfg: DrQV2Config, step: jax.Array) -> jax.Array:
    """DrQ-v2's ``linear(init, final, duration)`` at agent step ``step`` (utils.py:129-137)."""
    mix = jnp.clip(jnp.asarray(step, jnp.float32) / cfg.std_steps, 0.0, 1.0)
    return (1.0 - mix) * cfg.std_init + mix * cfg.std_final


def truncated_sample(mean: jax.Array, std: jax.Array, key: jax.Array, clip: float | None) -> jax.Array:
    """DrQ-v2's ``TruncatedNormal.sample`` (utils.py:105-126): ``mean + clip(std * eps, -c, c)``,
    clamped to ``[-1 + 1e-6, 1 - 1e-6]`` with a straight-through gradient (the clamp's gradient is 1).

    Args:
        mean: (..., action_size) in (-1, 1).
        std: () or broadcastable standard deviation.
        key: PRNG key.
        clip: noise clip, or None (exploration, drqv2.py:172).

    Returns:
        (..., action_size) actions.
    """
    noise = std * jax.random.normal(key, mean.shape, mean.dtype)
    if clip is not None:
        noise = jnp.clip(noise, -clip, clip)
    x = mean + noise
    clamped = jnp.clip(x, -1.0 + CLAMP_EPS, 1.0 - CLAMP_EPS)
    return x + jax.lax.stop_gradient(clamped - x)


@flax.struct.dataclass
class DrQV2State:
    """Everything DrQ-v2 carries between updates.

    Attributes:
        encoder_params, actor_params, critic_params, target_critic_params: network parameters.
        encoder_opt, actor_opt, critic_opt: Adam states (three optimisers, as drqv2.py:148-150).
        steps: () int32 updates done.
    """

    encoder_params: Params
    actor_params: Params
    critic_params: Params
    target_critic_params: Params
    encoder_opt: optax.OptState
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    steps: jax.Array


def make_critic_loss(encoder: Encoder, actor: PixelActor, critic: PixelCritic, clip: float) -> LossFn:
    """DrQ-v2's critic loss (drqv2.py:177-189), differentiated with respect to the encoder *and* the critic.

    ``target = reward + discount * min_i Qtarget_i(h', a')`` with ``h'`` the encoder's features of the
    (augmented) ``next_obs`` and ``a' = mean(h') + clip(std eps)``, all held fixed; the loss is the
    sum of both critics' mean squared errors.

    Returns:
        ``loss({"encoder": ..., "critic": ...}, batch, key, *, actor_params, target_params, std)``; its
        auxiliary output is ``(metrics, features)`` with ``features`` the detached encoder features of
        ``batch.obs``, for the actor step (drqv2.py:256).
    """

    def loss(params, batch: PixelTransition, key, *, actor_params, target_params, std):
        features = encoder.apply(params["encoder"], batch.obs)
        next_features = jax.lax.stop_gradient(encoder.apply(params["encoder"], batch.next_obs))
        next_action = truncated_sample(actor.apply(actor_params, next_features), std, key, clip)
        tq1, tq2 = critic.apply(target_params, next_features, next_action)
        target = jax.lax.stop_gradient(batch.reward + batch.discount * jnp.minimum(tq1, tq2))
        q1, q2 = critic.apply(params["critic"], features, batch.action)
        value = jnp.mean(jnp.square(q1 - target)) + jnp.mean(jnp.square(q2 - target))
        metrics = {"critic_loss": value, "q": 0.5 * jnp.mean(q1 + q2), "target_q": jnp.mean(target)}
        return value, (metrics, jax.lax.stop_gradient(features))

    return loss


def make_actor_loss(actor: PixelActor, critic: PixelCritic, clip: float) -> LossFn:
    """DrQ-v2's actor loss ``-mean min(Q1, Q2)(h, mean(h) + clip(std eps))`` (drqv2.py:206-216).

    ``h`` are encoder features computed outside (and detached there); the critic is held fixed.

    Returns:
        ``loss(actor_params, features, key, *, critic_params, std)``.
    """

    def loss(actor_params, features, key, *, critic_params, std):
        action = truncated_sample(actor.apply(actor_params, features), std, key, clip)
        q1, q2 = critic.apply(critic_params, features, action)
        value = -jnp.mean(jnp.minimum(q1, q2))
        return value, {"actor_loss": value}

    return loss


class DrQV2:
    """DrQ-v2 built from a :class:`DrQV2Config`; every method is pure, jittable and vmappable.

    It implements :class:`rebel_jax.agents.base.Agent`.

    Args:
        cfg: hyperparameters.
        obs_shape: (H, W, C) of the uint8 frame stacks.
        action_size: action dimension (actions in [-1, 1]).
    """

    def __init__(self, cfg: DrQV2Config, obs_shape: tuple[int, int, int], action_size: int):
        self.cfg, self.obs_shape, self.action_size = cfg, tuple(obs_shape), action_size
        self.encoder = Encoder(precision=cfg.precision, kernel_grad=cfg.kernel_grad, first_channels=cfg.first_channels)
        self.actor = PixelActor(cfg.feature_dim, cfg.hidden, cfg.depth, action_size, cfg.precision)
        self.critic = PixelCritic(cfg.feature_dim, cfg.hidden, cfg.depth, cfg.precision, cfg.critic_out_f32)
        self.optimizer = optax.adam(cfg.lr)  # One learning rate for all three (drqv2.py:148-150).
        self.critic_loss = make_critic_loss(self.encoder, self.actor, self.critic, cfg.std_clip)
        self.actor_loss = make_actor_loss(self.actor, self.critic, cfg.std_clip)
        self._looped_update = jax.custom_batching.sequential_vmap(self._update)
        self.batch_size = cfg.batch_size
        self.sample_args: dict[str, Any] = {"nstep": cfg.nstep, "gamma": cfg.gamma}

    metric_names = ("critic_loss", "actor_loss", "q", "target_q", "std")

    def schedule(self, num_envs: int) -> UpdateSchedule:
        """One update every ``update_every`` agent steps once ``t * num_envs`` reach the seed steps (drqv2.py:233):
        ``num_envs / update_every`` updates per vector step, or one every ``update_every / num_envs`` vector steps."""
        every = self.cfg.update_every
        per_step, period = max(1, num_envs // every), max(1, every // num_envs)
        return UpdateSchedule(per_step=per_step, period=period, counts_current=False)

    def _features_shape(self) -> jax.ShapeDtypeStruct:
        obs = jax.ShapeDtypeStruct((1, *self.obs_shape), jnp.uint8)
        params = jax.eval_shape(self.encoder.init, jax.random.PRNGKey(0), obs)
        return jax.eval_shape(self.encoder.apply, params, obs)

    def _init_critic(self, key: jax.Array):
        features = jnp.zeros(self._features_shape().shape)
        return self.critic.init(key, features, jnp.zeros((1, self.action_size)))

    def init(self, key: jax.Array) -> DrQV2State:
        """Fresh state: random networks (orthogonal init), target critic = critic.

        Args:
            key: PRNG key.

        Returns:
            The initial :class:`DrQV2State`.
        """
        key_encoder, key_actor, key_critic = jax.random.split(key, 3)
        encoder_params = self.encoder.init(key_encoder, jnp.zeros((1, *self.obs_shape), jnp.uint8))
        actor_params = self.actor.init(key_actor, jnp.zeros(self._features_shape().shape))
        critic_params = self._init_critic(key_critic)
        return DrQV2State(
            encoder_params=encoder_params,
            actor_params=actor_params,
            critic_params=critic_params,
            target_critic_params=critic_params,
            encoder_opt=self.optimizer.init(encoder_params),
            actor_opt=self.optimizer.init(actor_params),
            critic_opt=self.optimizer.init(critic_params),
            steps=jnp.zeros((), jnp.int32),
        )

    def reset_critic(self, state: DrQV2State, key: jax.Array) -> DrQV2State:
        """A fresh critic, target critic and critic optimiser; encoder and actor kept (SURF's pixel
        ``reset_critic``, agent/drqv2.py of its pixel branch)."""
        critic_params = self._init_critic(key)
        return state.replace(
            critic_params=critic_params,
            target_critic_params=critic_params,
            critic_opt=self.optimizer.init(critic_params),
        )

    def update(
        self, state: DrQV2State, batch: PixelTransition, key: jax.Array, step: jax.Array
    ) -> tuple[DrQV2State, Metrics]:
        """One DrQ-v2 update: augment, critic + encoder step, actor step, target critic.

        With ``cfg.seed_loop`` a ``vmap`` of this method runs one entry at a time (``lax.map``); called
        unbatched it is the same update either way.

        Args:
            state: current state.
            batch: n-step transitions with uint8 frame stacks (not yet augmented).
            key: PRNG key.
            step: the agent step the exploration schedule is read at (DrQ-v2's ``global_step``).

        Returns:
            state: updated, ``steps`` incremented.
            metrics: critic_loss, actor_loss, q (mean predicted Q), target_q, std.
        """
        if self.cfg.seed_loop:  # Positional arguments: custom_vmap takes no keywords.
            return self._looped_update(state, batch, key, step)
        return self._update(state, batch, key, step)

    def _update(
        self, state: DrQV2State, batch: PixelTransition, key: jax.Array, step: jax.Array
    ) -> tuple[DrQV2State, Metrics]:
        """:meth:`update` as one batched computation under ``vmap``."""
        key_obs, key_next, key_critic, key_actor = jax.random.split(key, 4)
        batch = batch.replace(
            obs=random_shift(key_obs, batch.obs, self.cfg.pad),
            next_obs=random_shift(key_next, batch.next_obs, self.cfg.pad),
        )
        std = std_schedule(self.cfg, step)
        critic_loss = functools.partial(
            self.critic_loss, actor_params=state.actor_params, target_params=state.target_critic_params, std=std
        )
        params = {"encoder": state.encoder_params, "critic": state.critic_params}
        grads, (critic_metrics, features) = jax.grad(critic_loss, has_aux=True)(params, batch, key_critic)
        encoder_update, encoder_opt = self.optimizer.update(grads["encoder"], state.encoder_opt, state.encoder_params)
        critic_update, critic_opt = self.optimizer.update(grads["critic"], state.critic_opt, state.critic_params)
        encoder_params = optax.apply_updates(state.encoder_params, encoder_update)
        critic_params = optax.apply_updates(state.critic_params, critic_update)

        actor_loss = functools.partial(self.actor_loss, critic_params=critic_params, std=std)
        actor_grads, actor_metrics = jax.grad(actor_loss, has_aux=True)(state.actor_params, features, key_actor)
        actor_update, actor_opt = self.optimizer.update(actor_grads, state.actor_opt, state.actor_params)
        actor_params = optax.apply_updates(state.actor_params, actor_update)

        target = optax.incremental_update(critic_params, state.target_critic_params, self.cfg.tau)
        state = DrQV2State(
            encoder_params=encoder_params,
            actor_params=actor_params,
            critic_params=critic_params,
            target_critic_params=target,
            encoder_opt=encoder_opt,
            actor_opt=actor_opt,
            critic_opt=critic_opt,
            steps=state.steps + 1,
        )
        return state, {**critic_metrics, **actor_metrics, "std": std}

    def act(self, state: DrQV2State, obs: jax.Array, key: jax.Array, step: jax.Array) -> jax.Array:
        """Exploration action ``mean + std(step) eps``, unclipped noise, clamped to (-1, 1) (drqv2.py:164-175).

        Args:
            state: agent state.
            obs: (..., H, W, C) uint8 frame stacks (not augmented).
            key: PRNG key.
            step: agent step of the schedule.

        Returns:
            (..., action_size) actions.
        """
        mean = self.actor.apply(state.actor_params, self.encoder.apply(state.encoder_params, obs))
        return truncated_sample(mean, std_schedule(self.cfg, step), key, None)

    def act_deterministic(self, state: DrQV2State, obs: jax.Array) -> jax.Array:
        """The mean action, DrQ-v2's evaluation (drqv2.py:169-170)."""
        return self.actor.apply(state.actor_params, self.encoder.apply(state.encoder_params, obs))

    def policy(self, state: DrQV2State) -> dict:
        """The deterministic policy's parameters, ``{"encoder": ..., "actor": ...}``."""
        return {"encoder": state.encoder_params, "actor": state.actor_params}

    def mean_action(self, policy: dict, obs: jax.Array) -> jax.Array:
        """The mean action of ``policy`` (:meth:`policy`) at frame stacks ``obs`` (..., H, W, C)."""
        return self.actor.apply(policy["actor"], self.encoder.apply(policy["encoder"], obs))

    def q_values(self, state: DrQV2State, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Both critics' Q at un-augmented frame stacks."""
        return self.critic.apply(state.critic_params, self.encoder.apply(state.encoder_params, obs), action)
