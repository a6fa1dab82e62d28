"""The benchmarks' own arithmetic: what they time must compute what it claims to."""

from __future__ import annotations

import pathlib
import sys

import jax
import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "benchmarks"))
import drqv2_parts  # noqa: E402


@pytest.mark.parametrize("stride", [2, 1])
def test_the_patch_product_is_the_convolutions_kernel_gradient(stride):
    key_x, key_w, key_g = jax.random.split(jax.random.PRNGKey(0), 3)
    x = jax.random.normal(key_x, (3, 11, 9, 5))
    kernel = jax.random.normal(key_w, (3, 3, 5, 4))
    y, vjp = jax.vjp(lambda w: drqv2_parts.conv(x, w, stride, "highest"), kernel)
    grad_out = jax.random.normal(key_g, y.shape)
    want = vjp(grad_out)[0]
    # A NumPy loop over output pixels: d kernel[i, j, c, o] = sum_{b, h, w} x[b, s h + i, s w + j, c] g[b, h, w, o].
    xn, gn = np.asarray(x, np.float64), np.asarray(grad_out, np.float64)
    loop = np.zeros(kernel.shape)
    for h in range(y.shape[1]):
        for w in range(y.shape[2]):
            patch = xn[:, stride * h : stride * h + 3, stride * w : stride * w + 3, :]  # (B, 3, 3, C)
            loop += np.einsum("bijc,bo->ijco", patch, gn[:, h, w, :])
    got = drqv2_parts.kernel_grad_patches(x, grad_out, stride, "highest")
    np.testing.assert_allclose(np.asarray(want), loop, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(got), loop, rtol=1e-4, atol=1e-4)
