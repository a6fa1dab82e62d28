"""The feedback schedule and the label budget: when a session is due, and which answers it may count."""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp

from rebel_jax.core.errors import check as _check


@dataclasses.dataclass(frozen=True)
class FeedbackConfig:
    """When the teacher is asked, and how much (B-Pref's schedule).

    The first feedback session comes at env step ``train.seed_steps + pretrain.steps`` (the end of
    unsupervised pre-training, as B-Pref), then one every ``interval`` steps while the budget
    lasts; ``budget`` says what it counts.
    """

    labels: int = 100
    """Total label budget per seed (pairs; ``budget`` says which)."""
    per_session: int = 0
    """Pairs asked per session; 0 means ``labels // 10`` (B-Pref: 10 sessions, e.g. 10 for 100 labels)."""
    interval: int = 20_000
    """Environment steps between feedback sessions; a multiple of ``train.steps_per_round``."""
    budget: Literal["answered", "asked"] = "answered"
    """What counts against ``labels``. ``asked``, B-Pref's: every pair put to the teacher, skipped or not
    (``learn_reward``: ``self.total_feedback += self.reward_model.mb_size``; the last session asks what is
    left, ``set_batch(max_feedback - total_feedback)``), and no session once it is spent (``run``: ``if
    self.total_feedback < self.cfg.max_feedback``), so ``ceil(labels / queries)`` sessions. ``answered``:
    only the pairs the teacher answered, so a seed whose teacher skips is asked again until it has
    ``labels`` answers. The two agree for a teacher that never skips (the oracle)."""

    @property
    def queries(self) -> int:
        return self.per_session or max(1, self.labels // 10)

    def validate(self) -> None:
        _check(self.labels >= 1, "feedback.labels", self.labels, ">= 1")
        _check(self.per_session >= 0, "feedback.per_session", self.per_session, ">= 0 (0: labels // 10)")
        _check(self.interval >= 1, "feedback.interval", self.interval, ">= 1")
        _check(self.budget in ("answered", "asked"), "feedback.budget", self.budget, "answered, asked")

    @property
    def sessions(self) -> int | None:
        """Sessions the budget allows: ``ceil(labels / queries)`` when it counts asked pairs, else None
        (a skipping teacher may need more)."""
        return -(-self.labels // self.queries) if self.budget == "asked" else None


def session_index(cfg, round_index):
    """The index (0-based) of the feedback session on the schedule at round ``round_index`` (if it has one)."""
    step = round_index * cfg.train.steps_per_round
    return (step - cfg.feedback_start) // cfg.feedback.interval


def session_due(cfg, round_index):
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
