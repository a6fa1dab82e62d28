"""The Python API: a whole run as one jittable, vmappable function of a PRNG key.

``make_train(cfg)`` returns ``train(key) -> (state, metrics)``: one seed's run, its rounds a ``lax.scan``
whose round index stays unbatched under ``jax.vmap``, so that ``jax.jit(jax.vmap(make_train(cfg)))(keys)``
runs many seeds in one program (PureJaxRL's, luchris429/purejaxrl@146b485:purejaxrl/ppo.py:62).
``metrics`` stacks each round's metrics on a leading round axis. Scripted teachers only: a person labels
between rounds, which the command line's host loop does (``python -m rebel_jax.train --teacher human``).

``make_trainer(cfg)`` gives the run's trainer (one for state and pixel tasks), whose ``init``, ``round`` and
``evaluate`` the command line drives one round at a time (with checkpoints, logs and progress between rounds).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from rebel_jax.config import Config
from rebel_jax.train import Trainer


def make_trainer(cfg: Config, host_teacher: bool = False, columns: int = 1) -> Trainer:
    """The trainer of ``cfg`` (:class:`~rebel_jax.train.Trainer`, state or pixel task; ``host_teacher``: the
    sessions run on the host, state tasks only; ``columns``: the most columns one device runs)."""
    return Trainer(cfg, host_teacher=host_teacher, columns=columns)


def make_train(cfg: Config, columns: int = 1) -> Callable[[jax.Array], tuple]:
    """``train(key) -> (state, metrics)``: the run of ``cfg`` for one seed, every round, as a pure function;
    ``columns``: the most seeds one device runs of it (with ``env.impl='warp'`` it sizes the contact buffer).

    Example::

        train = jax.jit(jax.vmap(make_train(cfg)))
        state, metrics = train(jax.random.split(jax.random.key(0), 4))  # 4 seeds
        metrics["eval_return"]  # (4, rounds)
    """
    trainer = make_trainer(cfg, columns=columns)

    def train(key: jax.Array):
        def one_round(state, round_index):
            return trainer.round(state, round_index)

        return jax.lax.scan(one_round, trainer.init(key), jnp.arange(cfg.train.num_rounds))

    return train
