"""The Method interface: what sets one preference-learning method apart, with PEBBLE's behaviour as every default.

A method is an object whose hooks the trainer (:class:`rebel_jax.train.Trainer`, on state and pixel tasks alike)
calls at fixed places of a run. Every hook receives the trainer, so it can read the run's config
(``trainer.cfg``), sizes and helpers; it returns values and never mutates anything. A method overrides
only what differs from PEBBLE (Lee et al., ICML 2021; rll-research/BPref@f3ece2e):

- **its config**: ``config_field`` names the section of :class:`rebel_jax.config.Config` it reads (``surf``,
  ``rebel``), checked by :meth:`validate`;
- **its state**: :meth:`knob` (a traced per-column value a sweep can vmap over, e.g. REBEL's lambda),
  :meth:`crop` (extra steps stored on each side of a segment), :meth:`pool_size` (unlabelled pairs kept per
  session) and :meth:`trajectory_size` (the evaluation episodes' trajectories kept for the reward loss);
- **its loss terms** over the label store, one list for state and pixel tasks: :meth:`reward_terms`, each term
  ``(params, batch, key) -> (loss, metrics)`` over a :class:`rebel_jax.reward_model.PrefBatch` (the pairs and
  the members' per-step rewards on them);
- **its schedule of reward steps** in a session: :meth:`train_reward` (PEBBLE's early-stopped epochs by
  default; SURF's fixed iterations), through :mod:`rebel_jax.reward_train`;
- **hooks with no effect by default**, one each for state and pixel tasks: :meth:`query_segments` (which
  segments the queries come from), :meth:`sample_batch` (the agent's minibatch from the replay) and
  :meth:`batch_reward` (an intrinsic reward added to the learned one in that minibatch). Their defaults make the
  trainer's own calls (the same functions, arguments and keys); the trainer's ``sample_segments``,
  ``sample_pairs``, ``sample`` and ``reward_members`` serve both kinds of task.

A new method is one file with a subclass, registered in :data:`rebel_jax.methods.REGISTRY` (or at run time
with :func:`rebel_jax.methods.register`); ``docs/adding_a_method.md`` walks through one.
"""

from __future__ import annotations

from typing import Any, ClassVar

import jax
import jax.numpy as jnp

from rebel_jax import reward_model, reward_train


class Method:
    """PEBBLE: the Bradley-Terry loss on the labelled pairs, trained in early-stopped epochs each session."""

    name: ClassVar[str] = "pebble"
    config_field: ClassVar[str | tuple[str, ...] | None] = None
    """The section of the run's config this method reads (None: none of its own; a tuple: several)."""

    def sections(self) -> tuple[str, ...]:
        """The config sections of :attr:`config_field`, as a tuple."""
        field = self.config_field
        return () if field is None else (field,) if isinstance(field, str) else tuple(field)

    # -- config and sizes ------------------------------------------------------------------
    def validate(self, cfg: Any) -> None:
        """Checks the method's own settings in the run's config (raises ``ConfigError``)."""
        del cfg  # Unused.

    def crop(self, cfg: Any) -> int:
        """Steps stored on each side of a segment beyond ``query.segment_length`` (a temporal crop's room)."""
        del cfg  # Unused.
        return 0

    def pool_size(self, cfg: Any) -> int:
        """Unlabelled pairs the method keeps per session (0: no pool)."""
        del cfg  # Unused.
        return 0

    def knob(self, cfg: Any) -> jax.Array | None:
        """A traced value per column (``TrainState.lam``), so that a sweep vmaps over it; None: no knob."""
        del cfg  # Unused.
        return None

    def trajectory_size(self, cfg: Any, episode_length: int, pixels: bool) -> tuple[int, int] | None:
        """``(episodes, steps)`` of the evaluation episodes the run keeps for the method's loss; None: none kept.

        Args:
          episode_length: agent steps per episode.
          pixels: whether the task observes frame stacks.
        """
        del cfg, episode_length, pixels  # Unused.
        return None

    def episode_lengths(self, cfg: Any) -> dict[str, int]:
        """Setting -> length in agent steps of what the method reads from single episodes (each must fit one)."""
        del cfg  # Unused.
        return {}

    # -- the reward loss and its schedule ----------------------------------------------------
    def reward_terms(self, trainer: Any, ts: Any, key: jax.Array, agent_step: jax.Array | None) -> list:
        """The reward loss's terms (:data:`rebel_jax.reward_model.LossTerm`), states and pixels alike: the
        Bradley-Terry loss on the labelled pairs.

        Args:
          trainer: the trainer (``trainer.reward_cfg`` the reward ensemble's settings).
          ts: the state before the session, ``ts.reward`` holding this session's labels (and pool).
          key: the session's key for the terms' own draws (e.g. REBEL's trajectories).
          agent_step: () the seed's agent steps so far on a pixel task (DrQ-v2's step); None on a state task.
        """
        del ts, key, agent_step  # Unused.
        return [reward_model.bt_loss(trainer.reward_cfg)]

    def train_reward(
        self,
        trainer: Any,
        ts: Any,
        stored: reward_model.RewardState,
        keys: dict[str, jax.Array],
        kept: jax.Array,
        agent_step: jax.Array | None,
    ) -> tuple[reward_model.RewardState, dict]:
        """One session's reward training: up to ``max_epochs`` epochs of the reward settings, stopped early at
        their ``stop_accuracy``; none without a kept answer (the members and their optimiser state come back
        unchanged).

        Args:
          trainer: the trainer.
          ts: the state before the session.
          stored: the reward state with this session's labels.
          keys: ``terms``, ``train`` and ``pool`` keys of the session.
          kept: () the number of answers kept this session.
          agent_step: as :meth:`reward_terms`.

        Returns:
          The trained reward state and ``reward_train.train``'s metrics (``epochs``, ``train_accuracy``, ``loss``).
        """
        rcfg = trainer.reward_cfg
        terms = self.reward_terms(trainer, ts.replace(reward=stored), keys["terms"], agent_step)
        epochs = jnp.where(kept > 0, rcfg.max_epochs, 0)
        return reward_train.train(rcfg, stored, keys["train"], terms, max_epochs=epochs)

    # -- hooks with no effect by default ----------------------------------------------------
    def query_segments(self, trainer: Any, ts: Any, key: jax.Array, first: jax.Array) -> tuple:
        """The session's query pairs, of the stored length (``trainer.stored_length``): by ``query.sampling``,
        uniform at the first feedback session (``trainer.select_queries``). On state tasks two
        ``queries.Segments``; on pixel tasks two sets of replay places (``pixel_reward.SegmentPlaces``) over the
        last ``query.recent_episodes`` complete episodes."""
        return trainer.select_queries(ts, key, first)

    def sample_batch(self, trainer: Any, ts: Any, buffer: Any, key: jax.Array) -> Any:
        """The agent's minibatch for one update of a vector step: uniform over the replay, with the learned
        reward (``trainer.sample``): SAC's transitions on state tasks, DrQ-v2's n-step transitions on pixel tasks.
        The trainer draws a vector step's minibatches together before its updates (this call vmapped over their
        keys). The updates after the critic's reset sample uniformly whatever the method (QPA's
        ``update_after_reset`` does, huxiao09/QPA@7e9e49e:agent/sac.py:334-337).

        Args:
          ts: the state before the step (``ts.reward`` the ensemble and its labels).
          buffer: the replay with the step's transitions written.
        """
        del ts  # Unused.
        return trainer.sample(buffer, key, True)

    def batch_reward(self, trainer: Any, ts: Any, batch: Any, agent_step: jax.Array) -> Any:
        """The minibatch's reward as the agent sees it (an intrinsic bonus goes here); unchanged by default.
        Called on every minibatch of the updates on the learned reward, a vector step's together (vmapped over them)
        before its updates (on pixel tasks the updates after the critic's reset included).

        Args:
          ts: the state whose ensemble (``ts.reward.params``) labelled the replay.
          batch: the minibatch; on pixel tasks ``reward`` is the discounted sum of the learned rewards of its n steps.
          agent_step: () the seed's agent steps so far, over its training environments (unbatched on state tasks).
        """
        del trainer, ts, agent_step  # Unused.
        return batch
