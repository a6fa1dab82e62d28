"""Seeds across devices: the seed axis of a vmapped run, sharded with ``jax.sharding``.

One GPU runs many seeds by ``vmap``. With several devices (``jax.devices()``; on several
hosts after ``jax.distributed.initialize()``, which makes every host's devices visible),
the leading seed axis of every array in the run's state is split over a 1-D ``Mesh`` named
``seeds``; ``jit`` then runs each device's seeds where they live, with no communication.

Multi-host: start the same command on every host with ``--distributed`` (which calls
``jax.distributed.initialize()``; on SLURM or with ``JAX_COORDINATOR_ADDRESS``,
``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID`` set it needs no arguments). The number of
seeds must be a multiple of the total device count.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec


def seed_sharding(num_seeds: int, devices: list | None = None) -> NamedSharding | None:
    """A sharding of the leading seed axis over ``devices`` (all by default); None for one device.

    Raises:
      ValueError: if ``num_seeds`` is not a multiple of the number of devices.
    """
    devices = jax.devices() if devices is None else devices
    if len(devices) == 1:
        return None
    if num_seeds % len(devices):
        raise ValueError(f"--seeds={num_seeds} must be a multiple of the {len(devices)} devices to shard over")
    return NamedSharding(Mesh(np.array(devices), ("seeds",)), PartitionSpec("seeds"))


def shard_seeds(tree, sharding: NamedSharding | None):
    """Places every leaf of ``tree`` (leading axis = seeds) according to ``sharding``."""
    return tree if sharding is None else jax.device_put(tree, sharding)
