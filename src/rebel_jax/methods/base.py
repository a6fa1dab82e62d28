"""The Method interface: what sets one preference-learning method apart, with PEBBLE's behaviour as every default.

A method is an object whose hooks the trainer (:class:`rebel_jax.train.Trainer`, on state and pixel tasks alike)
calls at fixed places of a run. Every hook receives the trainer, so it can read the run's config
(``trainer.cfg``), sizes and helpers; it returns values and never mutates anything. A method overrides
only what differs from PEBBLE (Lee et al., ICML 2021; rll-research/BPref@f3ece2e):

- **its settings**: :attr:`Method.config`, a frozen dataclass declared next to the method's code. The run's config
  holds one instance of it under the method's name (``cfg.section(name)``, or ``self.settings(cfg)``); the command
  line makes its ``--NAME.*`` flags from its fields and docstrings, ``config.json`` records it and ``--resume``
  checks it. :meth:`validate` checks it with the rest of the config;
- **its state**: :meth:`init_state`, any pytree made from a key, carried per seed in ``TrainState.method``
  (vmapped over seeds and settings, sharded over devices, checkpointed and resumed exactly). The hooks that may
  change it get it and return it: :meth:`pretrain_step` and :meth:`train_reward`; the others read it
  (``ts.method``). Sizes and traced knobs: :meth:`knob` (a per-column value a sweep vmaps over, e.g. REBEL's
  lambda), :meth:`crop`, :meth:`pool_size`, :meth:`trajectory_size`;
- **its metrics**: every key a hook or a loss term returns beyond the trainer's own reaches ``metrics.jsonl``,
  TensorBoard and the run's summary as ``NAME/KEY``, per seed and as the mean over seeds (NaN in rounds
  without a feedback session, or outside pre-training for :meth:`pretrain_step`'s);
- **its loss terms** over the label store, one list for state and pixel tasks: :meth:`reward_terms`, each term
  ``(params, batch, key) -> (loss, metrics)`` over a :class:`rebel_jax.preference.reward_model.PrefBatch` (the pairs and
  the members' per-step rewards on them);
- **its reward training** in a session: :meth:`train_reward` (PEBBLE's early-stopped epochs by default; SURF's
  fixed iterations), through :mod:`rebel_jax.preference.reward_train`, whose loops take the method's optimiser
  (:meth:`reward_optimizer`, any ``optax`` transformation) and a weight per labelled pair (``pair_weight``);
- **the unsupervised phase**: :meth:`pretrain_step` may update the reward ensemble and the method's state from
  each vector step's minibatches and their intrinsic reward (none by default);
- **hooks with no effect by default**, one each for state and pixel tasks: :meth:`query_segments` (which
  segments the queries come from), :meth:`sample_batch` (the agent's minibatch from the replay) and
  :meth:`batch_reward` (an intrinsic reward added to the learned one in that minibatch). Their defaults make the
  trainer's own calls (the same functions, arguments and keys); the trainer's ``sample_segments``,
  ``sample_pairs``, ``sample`` and ``reward_members`` serve both kinds of task.

A new method is one file with a subclass. Register it in :data:`rebel_jax.methods.REGISTRY` with
:func:`rebel_jax.methods.register`, or, from a package of your own, through a ``rebel_jax.methods`` entry point
(``python -m rebel_jax.train NAME`` finds it); ``docs/adding_a_method.md`` walks through two.
"""

from __future__ import annotations

from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import optax

from rebel_jax.preference import reward_model, reward_train


class Method:
    """PEBBLE: the Bradley-Terry loss on the labelled pairs, trained in early-stopped epochs each session."""

    name: ClassVar[str] = "pebble"
    config: ClassVar[type | None] = None
    """The method's settings: a frozen dataclass whose defaults are the method's published ones (None: none of its
    own). Its section of the run's config is named as the method."""

    pixels: ClassVar[bool] = True
    """Whether the method runs on pixel tasks too (RIME and MRN: state tasks only)."""
    uses: ClassVar[tuple[str, ...]] = ()
    """Other methods' settings this method reads (a method built on two others, say)."""

    def sections(self) -> tuple[str, ...]:
        """The config sections this method reads beside the preference methods' common ones: its own, if any, and
        those of :attr:`uses`."""
        return (() if self.config is None else (self.name,)) + tuple(self.uses)

    def settings(self, cfg: Any) -> Any:
        """This method's settings in the run's config ``cfg`` (an instance of :attr:`config`)."""
        return cfg.section(self.name)

    def init_state(self, trainer: Any, key: jax.Array) -> Any:
        """The method's own state of one seed, a pytree (None: none). Made once per seed at the run's start."""
        del trainer, key  # Unused.
        return None

    def reward_optimizer(self, trainer: Any) -> optax.GradientTransformation | None:
        """The reward members' optimiser, an ``optax`` transformation (None: Adam at the reward settings' ``lr``).
        Ignored with ``per_member_adam`` (SURF's pixel ensemble steps each member with torch's Adam)."""
        del trainer  # Unused.
        return None

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
        """The reward loss's terms (:data:`rebel_jax.preference.reward_model.LossTerm`), states and pixels alike: the
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
        first: jax.Array,
    ) -> tuple[reward_model.RewardState, Any, dict]:
        """One session's reward training: up to ``max_epochs`` epochs of the reward settings, stopped early at
        their ``stop_accuracy``; none without a kept answer (the members and their optimiser state come back
        unchanged).

        Args:
          trainer: the trainer (``trainer.reward_optimizer`` the method's optimiser).
          ts: the state before the session (``ts.method`` the method's state).
          stored: the reward state with this session's labels.
          keys: ``terms``, ``train`` and ``pool`` keys of the session.
          kept: () the number of answers kept this session.
          agent_step: as :meth:`reward_terms`.
          first: () whether this is the run's first feedback session.

        Returns:
          The trained reward state, the method's state after the session, and the metrics: ``reward_train.train``'s
          (``epochs``, ``train_accuracy``, ``loss``) and any of the method's own (logged as ``NAME/KEY``).
        """
        del first  # Unused.
        rcfg = trainer.reward_cfg
        terms = self.reward_terms(trainer, ts.replace(reward=stored), keys["terms"], agent_step)
        epochs = jnp.where(kept > 0, rcfg.max_epochs, 0)
        reward, metrics = reward_train.train(
            rcfg, stored, keys["train"], terms, max_epochs=epochs, optimizer=trainer.reward_optimizer
        )
        return reward, ts.method, metrics

    def pretrain_step(self, trainer: Any, ts: Any, batches: Any, key: jax.Array) -> tuple[Any, Any, Any, dict] | None:
        """A step of the unsupervised phase (state tasks), after each vector step's minibatches have been drawn and
        given PEBBLE's intrinsic reward, before the agent's updates on them: ``batches`` those minibatches (stacked,
        ``reward`` the intrinsic one), ``ts.entropy_stats`` the kNN distances' running statistics after them.

        Returns:
          The minibatches the agent then trains on (a method may change their reward), the reward state, the
          method's state and metrics after the step; None (the default): no step, and the trainer's program is as
          if the hook did not exist.
        """
        del trainer, ts, batches, key  # Unused.
        return None

    def resets_critic(self, cfg: Any) -> bool:
        """Whether the first feedback session re-initialises the critic (B-Pref's ``reset_critic`` after the
        unsupervised phase; RIME keeps it) before its ``pretrain.reset_updates`` agent updates on the learned reward,
        which run either way (B-Pref's and RIME's ``update_after_reset``)."""
        del cfg  # Unused.
        return True

    def agent_step(self, trainer: Any, ts: Any, t: jax.Array, key: jax.Array) -> tuple[Any, dict] | None:
        """A step of the method's own after each vector step's updates of the feedback phase (MRN's bilevel reward
        update, say): ``ts`` the seed's state after the step, ``t`` the vector step's index (unbatched).

        Returns:
          The new state and the step's metrics (NaN where it did nothing, e.g. under its own ``lax.cond``); None
          (the default): no step, and the trainer's program is as if the hook did not exist.
        """
        del trainer, ts, t, key  # Unused.
        return None

    def has_agent_step(self) -> bool:
        """Whether :meth:`agent_step` is overridden (the trainer calls it only then)."""
        return type(self).agent_step is not Method.agent_step

    def has_pretrain_step(self) -> bool:
        """Whether :meth:`pretrain_step` is overridden (the trainer calls it only then)."""
        return type(self).pretrain_step is not Method.pretrain_step

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
