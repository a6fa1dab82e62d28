"""The orthogonal kernel init under the seed and member ``vmap``s: the pixel reward ensemble of 2 seeds
initialises (jaxlib 0.10.2's batched LAPACK QR deadlocked on the 2-core CPU), its kernels are orthogonal
with their gains, and :func:`rebel_jax.agents.networks.orthogonal` gives flax's values for the same key."""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.agents.networks import orthogonal
from rebel_jax.preference import pixel_reward
from rebel_jax.preference.pixel_reward import PixelRewardConfig
from rebel_jax.train import seed_keys


def _assert_orthogonal(kernel: np.ndarray, gain: float) -> None:
    k = np.asarray(kernel, np.float64).reshape(-1, kernel.shape[-1])  # (fan_in, out); conv: (3*3*C, out)
    gram = k.T @ k if k.shape[0] >= k.shape[1] else k @ k.T
    np.testing.assert_allclose(gram, gain**2 * np.eye(gram.shape[0]), atol=1e-5)


def test_pixel_reward_ensemble_of_two_seeds_is_orthogonal():
    cfg = PixelRewardConfig(ensemble_size=3)  # hidden 256: the size that hung
    init = jax.jit(jax.vmap(lambda key: pixel_reward.init(cfg, key, (16, 16, 9), 2, 4, 5)))
    params = jax.device_get(init(seed_keys(0, 2)).params["params"])
    for name, layer in params.items():
        layers = layer.items() if name == "Encoder_0" else [(name, layer)]
        gain = math.sqrt(2.0) if name == "Encoder_0" else 1.0
        for _, leaf in layers:
            kernel, bias = leaf["kernel"], leaf["bias"]
            assert kernel.shape[:2] == (2, 3) and not np.any(bias)
            for seed in range(2):
                for member in range(3):
                    _assert_orthogonal(kernel[seed, member], gain)
    dense = params["Dense_0"]["kernel"]
    assert not np.allclose(dense[0], dense[1]) and not np.allclose(dense[0, 0], dense[0, 1])


@pytest.mark.parametrize("shape", [(34, 16), (16, 16), (16, 1), (3, 3, 9, 32), (5, 7)])
def test_orthogonal_matches_flax_under_vmap(shape):
    keys = jax.random.split(jax.random.key(3), 6).reshape(2, 3)
    ours = jax.jit(jax.vmap(jax.vmap(lambda key: orthogonal(math.sqrt(2.0))(key, shape, jnp.float32))))(keys)
    flax_init = nn.initializers.orthogonal(math.sqrt(2.0))
    theirs = np.stack([[flax_init(keys[i, j], shape, jnp.float32) for j in range(3)] for i in range(2)])
    np.testing.assert_array_equal(np.asarray(ours), theirs)
