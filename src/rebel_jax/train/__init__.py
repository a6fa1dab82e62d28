"""The trainer: one seed's run as pure functions, vmapped over seeds and settings, and its compiled programs.

- :mod:`~rebel_jax.train.trainer`: :class:`Trainer`, which composes a task, an agent, a replay, a reward model with
  its feedback session, and a method into ``init``, the scanned ``round`` and ``evaluate``;
- :mod:`~rebel_jax.train.state`: :class:`TrainState`, what a seed carries from round to round, and the seeds' keys;
- :mod:`~rebel_jax.train.programs`: those functions jitted and vmapped over seeds (:func:`compiled`);
- :mod:`~rebel_jax.train.placement`: the seed axis over devices and hosts;
- :mod:`~rebel_jax.train.episodes`: what a round keeps of its episodes.

May import: :mod:`rebel_jax.config` and the layers below it (``core``, ``envs``, ``agents``, ``preference``,
``methods``). Only ``__main__`` (``python -m rebel_jax.train``) imports :mod:`rebel_jax.run`.
"""

from rebel_jax.train.programs import compiled
from rebel_jax.train.state import METHOD_KEY, TrainState, grow_replay, replay_rows, seed_keys
from rebel_jax.train.trainer import Trainer

__all__ = ["METHOD_KEY", "TrainState", "Trainer", "compiled", "grow_replay", "replay_rows", "seed_keys"]
