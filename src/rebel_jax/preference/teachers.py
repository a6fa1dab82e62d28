"""Scripted preference teachers (B-Pref, Lee et al. 2021).

A teacher compares the true returns of two segments and answers which one it prefers.
B-Pref's simulated teachers are one rule with five knobs (rll-research/BPref@f3ece2e), applied
in this order to each pair ``(seg_a, seg_b)``:

1. **skip**: the pair is dropped (``mask = 0``) if ``max(R_a, R_b) <= margin * eps_skip``.
2. **equal**: if ``|R_a - R_b| < margin * eps_equal`` the label is 0.5 (a soft target).
3. **myopic**: the reward at step ``t`` of a length-``H`` segment is weighted
   ``gamma ** (H - 1 - t)``, so recent steps count more.
4. **stochastic**: the label is drawn from the Bradley-Terry model with temperature
   ``beta``: ``P(b preferred) = softmax(beta * [R_a, R_b])[1]``; ``beta = inf`` is the
   perfectly rational teacher.
5. **mistake**: the label of step 4 is flipped with probability ``eps_mistake``.

As in B-Pref's code (``RewardModel.get_label``), the skip and equal tests use the plain
(undiscounted) segment returns, the myopic weights apply only to the comparison of steps 4-5,
and an "equal" answer overrides a mistake (the 0.5 label is written last).

Label convention (used by the whole package, and by ``reward_model.bt_loss``):
``label = P(seg_b is preferred to seg_a)``, i.e. the index of the preferred segment as in
B-Pref: 0.0 means ``seg_a`` is preferred, 1.0 means ``seg_b`` is preferred, 0.5 means equal.
A rational teacher facing an exact tie of the myopic returns answers 0.0 (``seg_a``), as
B-Pref's ``1 * (R_a < R_b)`` does.

All knobs may be Python floats or JAX scalars: the function never branches on them in
Python, so it jits once and vmaps over seeds (and over the knobs themselves).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Any

import jax
import jax.numpy as jnp

from rebel_jax.core.errors import check as _check
from rebel_jax.core.ranges import Range


@dataclasses.dataclass(frozen=True)
class TeacherConfig:
    """A B-Pref scripted teacher; the defaults are the oracle (perfectly rational, no noise)."""

    beta: Annotated[float, Range(0, lo_open=True, inf=True)] = math.inf
    """Rationality of the Bradley-Terry answer, P(b) = sigmoid(beta * (R_b - R_a)); inf is rational."""
    gamma: float = 1.0
    """Myopia: the reward of step t of a length-H segment is weighted gamma**(H-1-t); 1 is not myopic."""
    eps_mistake: float = 0.0
    """Probability of flipping the (non-equal) answer."""
    eps_skip: float = 0.0
    """Skip the pair if both returns are <= eps_skip * margin (margin = average segment return); 0 never skips."""
    eps_equal: float = 0.0
    """Answer 0.5 if the returns differ by less than eps_equal * margin; 0 never answers equal."""

    def validate(self) -> None:
        _check(self.beta > 0, "teacher.beta", self.beta, "> 0 (inf for a rational teacher)")
        _check(0 < self.gamma <= 1, "teacher.gamma", self.gamma, "(0, 1]")
        _check(0 <= self.eps_mistake <= 1, "teacher.eps_mistake", self.eps_mistake, "[0, 1]")
        _check(0 <= self.eps_skip < math.inf, "teacher.eps_skip", self.eps_skip, "[0, inf)")
        _check(0 <= self.eps_equal < math.inf, "teacher.eps_equal", self.eps_equal, "[0, inf)")


PRESETS: dict[str, TeacherConfig] = {
    "oracle": TeacherConfig(),
    "noisy": TeacherConfig(beta=1.0),
    "mistake": TeacherConfig(eps_mistake=0.1),
    "skip": TeacherConfig(eps_skip=0.1),
    "equal": TeacherConfig(eps_equal=0.1),
    "myopic": TeacherConfig(gamma=0.9),
}
"""B-Pref's six teachers (rll-research/BPref@f3ece2e); combinations are plain ``TeacherConfig``s."""


def knobs(cfg: TeacherConfig) -> dict[str, jax.Array]:
    """The teacher's knobs as float32 scalars: a pytree a sweep can stack and vmap over."""
    return {field.name: jnp.asarray(getattr(cfg, field.name), jnp.float32) for field in dataclasses.fields(cfg)}


def myopic_returns(rewards: jax.Array, gamma: jax.Array | float) -> jax.Array:
    """Segment returns with B-Pref's myopic weights.

    Args:
      rewards: (..., H) true rewards of each segment step.
      gamma: myopia factor; step ``t`` is weighted ``gamma ** (H - 1 - t)``.

    Returns:
      (...,) weighted sums over the last axis.
    """
    horizon = rewards.shape[-1]
    weights = jnp.asarray(gamma, rewards.dtype) ** jnp.arange(horizon - 1, -1, -1, dtype=rewards.dtype)
    return jnp.sum(rewards * weights, axis=-1)


def rational_or_stochastic(
    returns_a: jax.Array, returns_b: jax.Array, beta: jax.Array | float, uniforms: jax.Array
) -> jax.Array:
    """The Bradley-Terry answer of step 4 as a {0, 1} float (1 = ``seg_b`` preferred).

    Args:
      returns_a: (N,) myopic returns of ``seg_a``.
      returns_b: (N,) myopic returns of ``seg_b``.
      beta: rationality; ``inf`` gives ``1 * (R_a < R_b)`` (ties answer ``seg_a``).
      uniforms: (N,) U[0, 1) draws; the stochastic answer is ``uniforms < sigmoid(beta * (R_b - R_a))``.

    Returns:
      (N,) float labels in {0, 1}.
    """
    beta = jnp.asarray(beta, returns_a.dtype)
    rational = returns_a < returns_b
    finite_beta = jnp.where(jnp.isinf(beta), 1.0, beta)  # Keeps the unused branch finite.
    prob_b = jax.nn.sigmoid(finite_beta * (returns_b - returns_a))  # = softmax(beta * [R_a, R_b])[1]
    stochastic = uniforms < prob_b
    return jnp.where(jnp.isinf(beta), rational, stochastic).astype(returns_a.dtype)


def label(
    cfg: TeacherConfig, key: jax.Array, seg_a: Any, seg_b: Any, margin: jax.Array | float
) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
    """Labels a batch of segment pairs as B-Pref's scripted teacher.

    Args:
      cfg: the teacher's knobs.
      key: PRNG key; split into (stochastic answer, mistake) keys, each drawing N uniforms.
      seg_a: ``queries.Segments`` (anything with ``true_reward`` of shape (N, H)).
      seg_b: the same for the other segment of each pair.
      margin: average true return of a length-H segment under recent episodes, i.e.
        ``mean episode return * H / episode_length`` (``queries.reward_margin``); the skip and
        equal thresholds are ``margin * eps_skip`` and ``margin * eps_equal``.

    Returns:
      labels: (N,) float in {0, 0.5, 1}, ``P(seg_b preferred)``; skipped pairs read 0.
      mask: (N,) float, 0 for skipped pairs and 1 otherwise.
      info: ``num_skipped`` and ``num_equal`` (equal among the kept pairs), int32 scalars.

    References:
      Lee, Smith, Abbeel. B-Pref: Benchmarking Preference-Based Reinforcement Learning, 2021.
    """
    key_answer, key_mistake = jax.random.split(key)
    rewards_a, rewards_b = seg_a.true_reward, seg_b.true_reward
    num = rewards_a.shape[0]
    dtype = rewards_a.dtype

    sum_a, sum_b = jnp.sum(rewards_a, axis=-1), jnp.sum(rewards_b, axis=-1)
    skip_threshold = margin * jnp.asarray(cfg.eps_skip, dtype)
    equal_threshold = margin * jnp.asarray(cfg.eps_equal, dtype)
    skipped = (jnp.asarray(cfg.eps_skip) > 0) & (jnp.maximum(sum_a, sum_b) <= skip_threshold)
    equal = jnp.abs(sum_a - sum_b) < equal_threshold

    answer = rational_or_stochastic(
        myopic_returns(rewards_a, cfg.gamma),
        myopic_returns(rewards_b, cfg.gamma),
        cfg.beta,
        jax.random.uniform(key_answer, (num,), dtype),
    )
    flip = jax.random.uniform(key_mistake, (num,), dtype) < cfg.eps_mistake
    answer = jnp.where(flip, 1.0 - answer, answer)
    answer = jnp.where(equal, 0.5, answer)

    labels = jnp.where(skipped, 0.0, answer).astype(dtype)
    mask = (~skipped).astype(dtype)
    info = {
        "num_skipped": jnp.sum(skipped).astype(jnp.int32),
        "num_equal": jnp.sum(equal & ~skipped).astype(jnp.int32),
    }
    return labels, mask, info


def oracle_agreement(key: jax.Array, seg_a: Any, seg_b: Any, labels: jax.Array, mask: jax.Array) -> jax.Array:
    """The share of the kept answers (``mask``) that equal the oracle's on the same segments; NaN if none was kept.

    The label noise a teacher (scripted, or a person) actually put into a session: 1 for the oracle, the
    flipped and "equal" answers lowering it. Skipped pairs (mask 0) do not count.

    Args:
      key: any PRNG key (the oracle's answers do not depend on it).
      seg_a, seg_b: as for :func:`label`.
      labels: (N,) the answers; mask: (N,) 1 for a kept answer, 0 otherwise.
    """
    oracle, _, _ = label(PRESETS["oracle"], key, seg_a, seg_b, 0.0)
    kept = jnp.sum(mask)
    return jnp.where(kept > 0, jnp.sum(mask * (labels == oracle)) / jnp.maximum(kept, 1.0), jnp.nan)


def session_metrics(info: dict) -> dict:
    """A session's teacher metrics as both trainers log them (``train.SESSION_METRICS``): :func:`label`'s
    ``info`` counts and its ``oracle_agreement`` (:func:`oracle_agreement`)."""
    return {
        "session_skipped": info["num_skipped"],
        "session_equal": info["num_equal"],
        "session_oracle_agreement": info["oracle_agreement"],
    }
