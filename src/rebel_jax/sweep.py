"""Seeds across devices and processes: the seed axis of a vmapped run, sharded with ``jax.sharding``.

One GPU runs many seeds by ``vmap``. With several devices (``jax.devices()``; with several
processes after :func:`initialize`, every process's devices), the leading seed axis of every
array in the run's state is split over a 1-D ``Mesh`` named ``seeds``;
``train.compiled(trainer, sharding)`` then runs each device's seeds where they live
(``shard_map``), with no communication.

Several processes (hosts, or one process per GPU) run the same command with ``--distributed``
(:func:`initialize`); each process holds its own devices' seeds. The host loop then needs the
few helpers below: :func:`to_host` gathers per-seed metrics from every process,
:func:`from_primary` makes every process take process 0's decision (e.g. a time limit), and
:func:`is_primary` says which process writes the run's files. Collectives between processes
are used only by these helpers (on CPU through gloo, JAX's default CPU collectives).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

DISTRIBUTED_ENV = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
"""Where :func:`initialize` reads the coordinator's ``host:port``, the process count and this process's id."""


def initialize(environ=os.environ) -> None:
    """``jax.distributed.initialize`` with the settings of :data:`DISTRIBUTED_ENV`.

    JAX itself reads only ``JAX_COORDINATOR_ADDRESS`` (0.10.2), so the count and the id are read
    here. Settings left unset are detected by JAX (SLURM, Open MPI, Kubernetes, Cloud TPU).
    Must run before any computation.

    Raises:
      ValueError: if ``JAX_NUM_PROCESSES`` or ``JAX_PROCESS_ID`` is not an integer, or JAX finds no
        value for a setting left unset.
    """
    address, count, index = (environ.get(name) or None for name in DISTRIBUTED_ENV)
    try:
        count = None if count is None else int(count)
        index = None if index is None else int(index)
    except ValueError as err:
        raise ValueError(f"JAX_NUM_PROCESSES and JAX_PROCESS_ID must be integers ({err})") from err
    jax.distributed.initialize(coordinator_address=address, num_processes=count, process_id=index)


def is_primary() -> bool:
    """Whether this is process 0, the one that writes the run's logs (all processes write checkpoints)."""
    return jax.process_index() == 0


def seed_sharding(num_seeds: int, devices: list | None = None) -> NamedSharding | None:
    """A sharding of the leading seed axis over ``devices`` (all, of every process, by default); None for one device.

    Raises:
      ValueError: if ``num_seeds`` is not a multiple of the number of devices.
    """
    devices = jax.devices() if devices is None else devices
    if len(devices) == 1:
        return None
    if num_seeds % len(devices):
        raise ValueError(f"--seeds={num_seeds} must be a multiple of the {len(devices)} devices to shard over")
    return NamedSharding(Mesh(np.array(devices), ("seeds",)), PartitionSpec("seeds"))


def per_device(fn: Callable, sharding: NamedSharding, batched: tuple[bool, ...]) -> Callable:
    """``fn`` (a seed-vmapped function) run by ``shard_map`` on each device's block of seeds, with no communication.

    Zero-size arrays (MJX's data holds several, e.g. the constraint rows of a model without
    constraints) stay outside the ``shard_map``: they are passed in and returned as new empty
    arrays. XLA's GPU compiler (JAX 0.11.2) crashed with a segmentation fault on a ``shard_map``
    whose outputs mixed zero-size and other arrays (an MJX reset's ``State``, on 2 GPUs).

    Args:
      fn: the function; its outputs carry the seed axis first.
      sharding: the seed axis's sharding (:func:`seed_sharding`).
      batched: for each positional argument of ``fn``, whether it carries the seed axis (else it is
        the same on every device).
    """
    mesh, seeds, same = sharding.mesh, sharding.spec, PartitionSpec()
    blocks = mesh.size

    def run(*args):
        leaves, treedef = jax.tree.flatten(args)
        per_arg = [len(jax.tree.leaves(a)) for a in args]
        split = np.repeat(np.asarray(batched, bool), per_arg)
        kept = [i for i, x in enumerate(leaves) if x.size]
        outputs, out_treedef = jax.tree.flatten(jax.eval_shape(fn, *args))
        kept_out = [i for i, x in enumerate(outputs) if x.size]

        def block(*kept_leaves):
            full = [
                jnp.zeros((x.shape[0] // blocks, *x.shape[1:]) if split[i] else x.shape, x.dtype)
                for i, x in enumerate(leaves)
            ]
            for i, x in zip(kept, kept_leaves, strict=True):
                full[i] = x
            out = jax.tree.leaves(fn(*jax.tree.unflatten(treedef, full)))
            return [out[i] for i in kept_out]

        in_specs = tuple(seeds if split[i] else same for i in kept)
        mapped = jax.shard_map(block, mesh=mesh, in_specs=in_specs, out_specs=[seeds] * len(kept_out), check_vma=False)
        result = [jnp.zeros(x.shape, x.dtype) for x in outputs]
        for i, x in zip(kept_out, mapped(*[leaves[i] for i in kept]), strict=True):
            result[i] = x
        return jax.tree.unflatten(out_treedef, result)

    return run


def shard_seeds(tree, sharding: NamedSharding | None):
    """Places every leaf of ``tree`` (leading axis = seeds) according to ``sharding``.

    With several processes, every process passes the same whole ``tree`` and keeps its own devices' part.
    """
    return tree if sharding is None else jax.device_put(tree, sharding)


def to_host(tree):
    """``tree`` as NumPy arrays, every seed included: a gather from all processes when there are several.

    With several processes every process must call it (it is a collective), in the same order.
    """
    if jax.process_count() == 1:
        return jax.device_get(tree)
    return multihost_utils.process_allgather(tree, tiled=True)


def from_primary(tree):
    """Process 0's value of ``tree`` (a pytree of int or float scalars), on every process, as Python scalars.

    For host-side decisions that must agree across processes (a time limit read from each
    process's clock). A collective with several processes, like :func:`to_host`.
    """
    if jax.process_count() == 1:
        return tree
    return jax.tree.map(lambda x: np.asarray(x).item(), multihost_utils.broadcast_one_to_all(tree))


def barrier(name: str) -> None:
    """Waits until every process reaches the barrier ``name`` (nothing to wait for with one process)."""
    if jax.process_count() > 1:
        multihost_utils.sync_global_devices(name)
