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
from collections.abc import Callable

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


@jax.custom_batching.custom_vmap
def _qr(z: jax.Array) -> tuple[jax.Array, jax.Array]:
    q, r = jnp.linalg.qr(z)
    return q, r


@_qr.def_vmap
def _qr_vmap(axis_size: int, in_batched: list, z: jax.Array):
    """A batch of QRs as a loop of single QRs: on the CPU (jaxlib 0.10.2, 2 cores) the batched LAPACK
    kernel (``ParallelBatchMap``) of the seed- and member-vmapped inits could deadlock the thread pool."""
    del axis_size, in_batched
    return jax.lax.map(_qr, z), (True, True)


def orthogonal(scale: float = 1.0, column_axis: int = -1):
    """``nn.initializers.orthogonal(scale, column_axis)`` (``jax.random.orthogonal``'s sign-corrected QR of a
    normal matrix), the same values for the same key, whose QR stays one matrix at a time under ``vmap``."""

    def init(key: jax.Array, shape: tuple[int, ...], dtype=jnp.float32) -> jax.Array:
        if len(shape) < 2:
            raise ValueError("orthogonal initializer requires at least a 2D shape")
        n_rows, n_cols = math.prod(shape) // shape[column_axis], shape[column_axis]
        z = jax.random.normal(key, (max(n_rows, n_cols), min(n_rows, n_cols)), dtype)
        q, r = _qr(z)
        q = q * jnp.sign(jnp.diagonal(r))[None, :]
        if n_rows < n_cols:
            q = q.T
        drop = column_axis % len(shape)
        q = jnp.reshape(q, tuple(d for i, d in enumerate(shape) if i != drop) + (shape[column_axis],))
        return jnp.asarray(scale, dtype) * jnp.moveaxis(q, -1, column_axis)

    return init


class MLP(nn.Module):
    """``depth`` ReLU hidden layers of width ``hidden`` and a linear output layer.

    Kernels are orthogonal and biases zero, as B-Pref's ``weight_init``
    (``orthogonal_`` with its default gain 1 on every layer).

    Attributes:
        hidden: width of each hidden layer.
        depth: number of hidden layers (0 gives a linear map).
        out: output size.
        precision: ``tf32``, ``highest`` or ``bf16``.
        out_f32: compute the output layer in float32 (``tf32`` matmul, float32 result) whatever ``precision``:
            with ``bf16`` the hidden layers stay bfloat16 but the output is not rounded to bfloat16. The same
            parameters either way.
    """

    hidden: int
    depth: int
    out: int
    precision: str = "tf32"
    out_f32: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """Args: x (..., in). Returns: (..., out) float32."""
        kw = dense_kwargs(self.precision)
        init = dict(kernel_init=orthogonal(1.0), bias_init=nn.initializers.zeros)
        for _ in range(self.depth):
            x = nn.relu(nn.Dense(self.hidden, **init, **kw)(x))
        out_kw = dense_kwargs("tf32") if self.out_f32 and self.precision == "bf16" else kw
        return nn.Dense(self.out, **init, **out_kw)(x).astype(jnp.float32)


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
        out_f32: each critic's output layer in float32 (:class:`MLP`).
    """

    hidden: int
    depth: int
    precision: str = "tf32"
    out_f32: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Args: obs (..., obs_size), action (..., action_size). Returns: q1, q2 each (...)."""
        twin = nn.vmap(
            MLP,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=0,
            out_axes=0,
            axis_size=2,
        )
        x = jnp.concatenate([obs, action], axis=-1)
        # The input is broadcast to both members, not shared (``in_axes=None``): XLA then merges the
        # first layers into one wide matmul whose (batch, member, hidden) output must be transposed
        # to the member-major layout of the batched matmuls after it (a copy of every hidden
        # activation, forward and backward).
        q = twin(self.hidden, self.depth, 1, self.precision, self.out_f32)(jnp.broadcast_to(x, (2, *x.shape)))
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


# -- pixel networks (DrQ-v2) -------------------------------------------------------------------
# Yarats et al. 2021, "Mastering Visual Continuous Control: Improved Data-Augmented Reinforcement
# Learning" (facebookresearch/drqv2 c0c650b, drqv2.py); the same modules in SURF's pixel branch
# (alinlab/SURF 214bc1d, branch ``pixel``, agent/drqv2.py).


CONV_LAYOUT = ("NHWC", "HWIO", "NHWC")
"""``nn.Conv``'s layout in two dimensions: images channels-last, kernels (height, width, in, out)."""
KERNEL_GRADS = ("xla", "patches")


def conv_patch_kernel_grad(
    lhs: jax.Array,
    rhs: jax.Array,
    window_strides,
    padding,
    lhs_dilation=None,
    rhs_dilation=None,
    dimension_numbers=None,
    feature_group_count: int = 1,
    precision=None,
) -> jax.Array:
    """``lax.conv_general_dilated`` whose kernel gradient is one matrix product, ``patches^T @ grad_out``.

    The forward pass and the input's gradient are XLA's own. The kernel's gradient is computed from the
    input's patches (every output pixel's receptive field: one strided slice of the padded input per kernel
    tap, stacked) contracted with the output gradient over the batch and every output pixel: the same sum
    as XLA's backward-filter convolution, as one matrix product with a long contraction. Takes
    ``nn.Conv``'s arguments (its ``conv_general_dilated`` field); only the encoder's case is allowed: 2-D,
    ``CONV_LAYOUT``, no dilation, no groups.
    """
    layout = jax.lax.conv_dimension_numbers(lhs.shape, rhs.shape, CONV_LAYOUT)
    plain = all(d is None or all(x == 1 for x in d) for d in (lhs_dilation, rhs_dilation))
    if lhs.ndim != 4 or dimension_numbers not in (None, layout) or not plain or feature_group_count != 1:
        raise ValueError(
            "conv_patch_kernel_grad takes 2-D NHWC/HWIO convolutions without dilation or groups; got "
            f"lhs {lhs.shape}, dimension_numbers {dimension_numbers}, dilations {lhs_dilation} {rhs_dilation}, "
            f"feature_group_count {feature_group_count}"
        )
    window_strides, padding = tuple(window_strides), padding if isinstance(padding, str) else tuple(map(tuple, padding))

    def conv(x, w):
        return jax.lax.conv_general_dilated(
            x, w, window_strides, padding, dimension_numbers=layout, precision=precision
        )

    @jax.custom_vjp
    def run(x, w):
        return conv(x, w)

    def forward(x, w):
        return conv(x, w), (x, w)

    def backward(saved, grad_out):
        x, w = saved
        (grad_x,) = jax.vjp(lambda x: conv(x, w), x)[1](grad_out)
        height, width, channels, _ = w.shape
        pads = (
            jax.lax.padtype_to_pads(x.shape[1:3], (height, width), window_strides, padding)
            if isinstance(padding, str)
            else padding
        )
        x_padded = jnp.pad(x, ((0, 0), *pads, (0, 0)))
        (out_h, out_w), (stride_h, stride_w) = grad_out.shape[1:3], window_strides
        # Tap (i, j) of every output pixel's receptive field is a strided slice of the padded input; stacked
        # in the kernel's (kh, kw) order they are the patches, (B, H', W', kh * kw, in): memory moves only,
        # where lax.conv_general_dilated_patches is itself a grouped (depthwise) convolution.
        taps = [
            jax.lax.slice(
                x_padded,
                (0, i, j, 0),
                (x.shape[0], i + stride_h * (out_h - 1) + 1, j + stride_w * (out_w - 1) + 1, channels),
                (1, stride_h, stride_w, 1),
            )
            for i in range(height)
            for j in range(width)
        ]
        grad_w = jnp.einsum(
            "bhwtc,bhwo->tco",
            jnp.stack(taps, axis=3),
            grad_out.astype(x.dtype),
            precision=precision,
            preferred_element_type=jnp.float32,
        )
        return grad_x, grad_w.reshape(w.shape).astype(w.dtype)

    run.defvjp(forward, backward)
    return run(lhs, rhs)


def channel_padded(conv: Callable, channels: int) -> Callable:
    """``conv`` (``lax.conv_general_dilated``'s arguments, NHWC/HWIO) with its input and kernel zero-padded to
    ``channels`` input channels: the same output (zeros add nothing) and the same gradients for the real channels,
    for convolution kernels that are faster on a multiple of 8 channels (DrQ-v2's first layer sees 9)."""

    def run(lhs, rhs, *args, **kwargs):
        extra = channels - lhs.shape[-1]
        if extra > 0:
            lhs = jnp.pad(lhs, [(0, 0)] * (lhs.ndim - 1) + [(0, extra)])
            rhs = jnp.pad(rhs, [(0, 0)] * (rhs.ndim - 2) + [(0, extra), (0, 0)])
        return conv(lhs, rhs, *args, **kwargs)

    return run


class Encoder(nn.Module):
    """DrQ-v2's convolutional encoder: four 3x3 convolutions of 32 channels, strides 2, 1, 1, 1, each
    followed by ReLU, no padding, flattened (drqv2.py:48-67).

    Input pixels are scaled to ``x / 255 - 0.5`` (drqv2.py:64). An 84x84 image gives 35x35x32 = 39,200
    features (drqv2.py:53). Kernels are orthogonal with ReLU gain sqrt(2) and biases zero, as
    DrQ-v2's ``weight_init`` for convolutions (utils.py:57-61). Channels are last (NHWC), where
    PyTorch's are first: the flattened order differs, which the next linear layer absorbs.

    Attributes:
        channels: output channels of every convolution.
        precision: ``tf32``, ``highest`` or ``bf16``.
        kernel_grad: ``xla`` (XLA's backward-filter convolution) or ``patches``
            (:func:`conv_patch_kernel_grad`): the same gradient, computed another way (a speed setting).
        first_channels: the first convolution's input channels zero-padded to this many (:func:`channel_padded`;
            0 or fewer than the input's: as they are); the same function and parameters (a speed setting).
    """

    channels: int = 32
    precision: str = "tf32"
    kernel_grad: str = "xla"
    first_channels: int = 0

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        """Args: obs (..., H, W, C), uint8 or float in [0, 255]. Returns: (..., features) float32."""
        kw = dense_kwargs(self.precision)  # nn.Conv takes the same precision arguments
        init = dict(kernel_init=orthogonal(math.sqrt(2.0)), bias_init=nn.initializers.zeros)
        if self.kernel_grad not in KERNEL_GRADS:
            raise ValueError(f"kernel_grad must be one of {KERNEL_GRADS}; got {self.kernel_grad!r}")
        if self.kernel_grad == "patches":
            kw = kw | {"conv_general_dilated": conv_patch_kernel_grad}
        x = obs.astype(jnp.float32) / 255.0 - 0.5
        base = kw.get("conv_general_dilated", jax.lax.conv_general_dilated)
        first = kw | {"conv_general_dilated": channel_padded(base, self.first_channels)}
        for stride, layer_kw in zip((2, 1, 1, 1), (first, kw, kw, kw), strict=True):
            conv = nn.Conv(self.channels, (3, 3), strides=(stride, stride), padding="VALID", **init, **layer_kw)
            x = nn.relu(conv(x))
        return x.reshape(*x.shape[:-3], -1).astype(jnp.float32)


def encoder_output_size(height: int, width: int, channels: int = 32) -> int:
    """Features of :class:`Encoder` on an ``height x width`` image (84x84: 32 x 35 x 35 = 39,200)."""
    h, w = (height - 3) // 2 + 1 - 6, (width - 3) // 2 + 1 - 6
    return channels * h * w


class Trunk(nn.Module):
    """DrQ-v2's trunk: ``tanh(LayerNorm(Linear(features)))`` (drqv2.py:74-75, 100-101).

    LayerNorm's epsilon is PyTorch's default 1e-5 (flax's is 1e-6); its scale starts at 1 and its bias at 0.

    Attributes:
        features: output size (DrQ-v2's ``feature_dim``, 50).
        precision: ``tf32``, ``highest`` or ``bf16``.
    """

    features: int
    precision: str = "tf32"

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        init = dict(kernel_init=orthogonal(1.0), bias_init=nn.initializers.zeros)
        x = nn.Dense(self.features, **init, **dense_kwargs(self.precision))(x).astype(jnp.float32)
        return jnp.tanh(nn.LayerNorm(epsilon=1e-5)(x))


class PixelActor(nn.Module):
    """DrQ-v2's deterministic actor head on encoder features: trunk, MLP, ``tanh`` mean (drqv2.py:70-93).

    The exploration noise (a fixed, scheduled standard deviation) is applied outside, by
    :func:`rebel_jax.agents.drqv2.truncated_sample`.

    Attributes:
        features: trunk size (50); hidden, depth: MLP sizes (1024, 2); action_size: action dimension.
        precision: ``tf32``, ``highest`` or ``bf16``.
    """

    features: int
    hidden: int
    depth: int
    action_size: int
    precision: str = "tf32"

    @nn.compact
    def __call__(self, h: jax.Array) -> jax.Array:
        """Args: h (..., encoder features). Returns: the mean action (..., action_size) in (-1, 1)."""
        z = Trunk(self.features, self.precision)(h)
        return jnp.tanh(MLP(self.hidden, self.depth, self.action_size, self.precision)(z))


class PixelCritic(nn.Module):
    """DrQ-v2's critic on encoder features: one trunk shared by two Q-networks on ``concat(trunk, action)``
    (drqv2.py:96-121).

    Attributes:
        features: trunk size (50); hidden, depth: sizes of each Q MLP (1024, 2).
        precision: ``tf32``, ``highest`` or ``bf16``.
        out_f32: the Q outputs in float32 (:class:`MLP`; ``drqv2.critic_out_f32``).
    """

    features: int
    hidden: int
    depth: int
    precision: str = "tf32"
    out_f32: bool = False

    @nn.compact
    def __call__(self, h: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Args: h (..., encoder features), action (..., action_size). Returns: q1, q2 each (...)."""
        z = Trunk(self.features, self.precision)(h)
        return DoubleCritic(self.hidden, self.depth, self.precision, self.out_f32)(z, action)
