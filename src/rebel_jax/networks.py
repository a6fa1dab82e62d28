"""Flax modules of the SAC learner: MLP, tanh-Gaussian actor and twin critic.

All modules take a ``precision`` string (``SACConfig.precision``): ``tf32`` uses XLA's
default matmul precision (TF32 on Ampere+ GPUs), ``highest`` forces full fp32 matmuls and
``bf16`` computes in bfloat16 with float32 parameters; every module returns float32.

References:
    Haarnoja et al. 2018b, "Soft Actor-Critic Algorithms and Applications", arXiv:1812.05905.
    Lee et al. 2021, B-Pref (rll-research/BPref): layer sizes, init and log-std clamp.
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

PRECISIONS = ("tf32", "highest", "bf16")


def dense_kwargs(precision: str) -> dict:
    """Keyword arguments of ``nn.Dense`` for a matmul precision setting.

    Args:
        precision: ``tf32``, ``highest`` or ``bf16``.

    Returns:
        A dict with ``precision``, ``dtype`` and ``param_dtype`` for ``nn.Dense``.
    """
    if precision == "tf32":
        return dict(precision=jax.lax.Precision.DEFAULT, dtype=jnp.float32, param_dtype=jnp.float32)
    if precision == "highest":
        return dict(precision=jax.lax.Precision.HIGHEST, dtype=jnp.float32, param_dtype=jnp.float32)
    if precision == "bf16":
        return dict(precision=jax.lax.Precision.DEFAULT, dtype=jnp.bfloat16, param_dtype=jnp.float32)
    raise ValueError(f"precision must be one of {PRECISIONS}; got {precision!r}")


class MLP(nn.Module):
    """``depth`` ReLU hidden layers of width ``hidden`` and a linear output layer.

    Kernels are orthogonal and biases zero, as B-Pref's ``weight_init``
    (``orthogonal_`` with its default gain 1 on every layer).

    Attributes:
        hidden: width of each hidden layer.
        depth: number of hidden layers (0 gives a linear map).
        out: output size.
        precision: ``tf32``, ``highest`` or ``bf16``.
    """

    hidden: int
    depth: int
    out: int
    precision: str = "tf32"

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """Args: x (..., in). Returns: (..., out) float32."""
        kw = dense_kwargs(self.precision)
        init = dict(kernel_init=nn.initializers.orthogonal(1.0), bias_init=nn.initializers.zeros)
        for _ in range(self.depth):
            x = nn.relu(nn.Dense(self.hidden, **init, **kw)(x))
        return nn.Dense(self.out, **init, **kw)(x).astype(jnp.float32)


class Actor(nn.Module):
    """Diagonal Gaussian policy head, squashed by tanh in :func:`sample_action`.

    Attributes:
        hidden, depth: MLP sizes.
        action_size: action dimension.
        log_std_min, log_std_max: bounds of the log standard deviation.
        precision: ``tf32``, ``highest`` or ``bf16``.
    """

    hidden: int
    depth: int
    action_size: int
    log_std_min: float = -5.0
    log_std_max: float = 2.0
    precision: str = "tf32"

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Mean and log standard deviation of the pre-tanh Gaussian.

        Args:
            obs: observations (..., obs_size).

        Returns:
            mean, log_std: each (..., action_size); log_std is smoothly bounded to
            [log_std_min, log_std_max] by B-Pref's tanh rescaling.
        """
        out = MLP(self.hidden, self.depth, 2 * self.action_size, self.precision)(obs)
        mean, raw = jnp.split(out, 2, axis=-1)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (jnp.tanh(raw) + 1.0)
        return mean, log_std


def tanh_log_det(u: jax.Array) -> jax.Array:
    """``log(1 - tanh(u)^2)`` computed stably as ``2 (log 2 - u - softplus(-2u))``.

    Args:
        u: pre-tanh values.

    Returns:
        The elementwise log-derivative of tanh at ``u``.
    """
    return 2.0 * (math.log(2.0) - u - jax.nn.softplus(-2.0 * u))


def sample_action(mean: jax.Array, log_std: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Reparameterised sample of the tanh-squashed Gaussian and its log-density.

    Args:
        mean, log_std: Gaussian parameters (..., action_size).
        key: PRNG key.

    Returns:
        action: ``tanh(mean + std * eps)`` in (-1, 1), shape (..., action_size).
        log_prob: log-density of ``action`` (change of variables, Haarnoja et al. 2018b
            appendix C), shape (...).
    """
    eps = jax.random.normal(key, mean.shape, mean.dtype)
    u = mean + jnp.exp(log_std) * eps
    gaussian = -0.5 * jnp.square(eps) - log_std - 0.5 * math.log(2.0 * math.pi)
    log_prob = jnp.sum(gaussian - tanh_log_det(u), axis=-1)
    return jnp.tanh(u), log_prob


def mode_action(mean: jax.Array) -> jax.Array:
    """Deterministic action (evaluation): ``tanh(mean)``."""
    return jnp.tanh(mean)


class DoubleCritic(nn.Module):
    """Two independent Q-networks over ``concat(obs, action)``, batched on a member axis.

    Parameters carry a leading axis of size 2 (one slice per critic), so both critics run
    as one batched matmul.

    Attributes:
        hidden, depth: MLP sizes of each critic.
        precision: ``tf32``, ``highest`` or ``bf16``.
    """

    hidden: int
    depth: int
    precision: str = "tf32"

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Args: obs (..., obs_size), action (..., action_size). Returns: q1, q2 each (...)."""
        twin = nn.vmap(
            MLP,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            out_axes=0,
            axis_size=2,
        )
        q = twin(self.hidden, self.depth, 1, self.precision)(jnp.concatenate([obs, action], axis=-1))
        return q[0, ..., 0], q[1, ..., 0]


def mlp_flops(in_size: int, hidden: int, depth: int, out: int) -> int:
    """Matmul FLOPs (2 per multiply-add) of one forward pass of :class:`MLP` on one input.

    Args:
        in_size, hidden, depth, out: the MLP's sizes.

    Returns:
        FLOPs per input row.
    """
    if depth == 0:
        return 2 * in_size * out
    return 2 * (in_size * hidden + (depth - 1) * hidden * hidden + hidden * out)
