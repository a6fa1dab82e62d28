"""dm_control's ``rewards.tolerance`` in JAX (``dm_control/utils/rewards.py``)."""

from __future__ import annotations

import jax.numpy as jnp


def _sigmoid(x: jnp.ndarray, value_at_1: float, kind: str) -> jnp.ndarray:
    if kind == "gaussian":
        scale = jnp.sqrt(-2.0 * jnp.log(value_at_1))
        return jnp.exp(-0.5 * (x * scale) ** 2)
    if kind == "linear":
        scaled = x * (1.0 - value_at_1)
        return jnp.where(jnp.abs(scaled) < 1.0, 1.0 - scaled, 0.0)
    raise ValueError(f"unknown sigmoid {kind!r}; valid: gaussian, linear")


def tolerance(
    x: jnp.ndarray,
    bounds: tuple[float, float],
    margin: float = 0.0,
    sigmoid: str = "gaussian",
    value_at_margin: float = 0.1,
) -> jnp.ndarray:
    """1 inside ``bounds``, decaying with distance outside them.

    Args:
      x: the value to score.
      bounds: ``(lower, upper)``, either may be infinite.
      margin: the distance outside the bounds at which the output equals
        ``value_at_margin``; 0 gives a hard indicator.
      sigmoid: ``gaussian`` or ``linear``.
      value_at_margin: the output at ``margin`` from the bounds.
    """
    lower, upper = bounds
    in_bounds = (lower <= x) & (x <= upper)
    if margin == 0:
        return jnp.where(in_bounds, 1.0, 0.0)
    distance = jnp.where(x < lower, lower - x, x - upper) / margin
    return jnp.where(in_bounds, 1.0, _sigmoid(distance, value_at_margin, sigmoid))
