"""The feedback schedule and the label budget: when a session is due, and which answers it may count."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rebel_jax.config import Config, FeedbackConfig


def session_index(cfg: Config, round_index):
    """The index (0-based) of the feedback session on the schedule at round ``round_index`` (if it has one)."""
    step = round_index * cfg.train.steps_per_round
    return (step - cfg.feedback_start) // cfg.feedback.interval


def session_due(cfg: Config, round_index):
    """Whether round ``round_index`` starts with a feedback session, and whether it is the first: at
    ``cfg.feedback_start``, then every ``feedback.interval`` steps; under ``feedback.budget`` ``asked`` none
    after the ``feedback.sessions`` the budget allows (B-Pref holds none once it is spent)."""
    step = round_index * cfg.train.steps_per_round
    start = cfg.feedback_start
    due = (step >= start) & ((step - start) % cfg.feedback.interval == 0)
    if cfg.feedback.sessions is not None:
        due = due & (session_index(cfg, round_index) < cfg.feedback.sessions)
    return due, step == start


def remaining_budget(feedback: FeedbackConfig, stored, index):
    """Pairs the seed may still count at session ``index`` (0-based) with ``stored`` labels held
    (``feedback.budget``): ``labels - index * queries`` asked, or ``labels - stored`` answered."""
    return feedback.labels - (index * feedback.queries if feedback.budget == "asked" else stored)


def offered_pairs(feedback: FeedbackConfig, remaining: int, queries: int) -> int:
    """How many of a session's ``queries`` pairs a person is shown, ``remaining`` being
    :func:`remaining_budget`: under ``asked`` only the first ``remaining`` (B-Pref's
    ``train_PEBBLE.py`` shrinks the last session's batch to ``max_feedback - total_feedback``, its
    "corner case: new total feed > max feed"), which are also the only ones :func:`within_budget`
    counts; under ``answered`` all of them, a skipped pair leaving its place to the next."""
    return max(0, min(remaining, queries)) if feedback.budget == "asked" else queries


def within_budget(feedback: FeedbackConfig, mask: jax.Array, stored: jax.Array, index: jax.Array) -> jax.Array:
    """``mask`` (N,) limited to the seed's remaining budget (``feedback.budget``) at session ``index`` (0-based),
    with ``stored`` labels held so far.

    ``asked`` (B-Pref): the first ``labels - index * queries`` pairs of the session, answered or skipped
    (``learn_reward``'s ``total_feedback += mb_size``; ``set_batch(max_feedback - total_feedback)`` in the
    last session). ``answered``: the answered pairs while ``labels - stored`` last.
    """
    remaining = remaining_budget(feedback, stored, index)
    if feedback.budget == "asked":
        return mask * (jnp.arange(mask.shape[-1]) < remaining)
    return mask * (jnp.cumsum(mask, axis=-1) <= remaining)
