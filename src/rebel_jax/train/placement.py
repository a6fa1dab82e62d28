"""Seeds across devices and processes: the seed axis of a vmapped run, sharded with ``jax.sharding``.

One GPU runs many seeds by ``vmap``. With several devices (``jax.devices()``; with several
processes after :func:`initialize`, every process's devices), the leading seed axis of every
array in the run's state is split over a 1-D ``Mesh`` named ``seeds``;
``train.compiled(trainer, sharding)`` then runs each device's seeds where they live, as the
one-device program (:func:`per_device`), with no communication.

Several processes (hosts, or one process per GPU) run the same command with ``--distributed``
(:func:`initialize`); each process holds its own devices' seeds. The host loop then needs the
few helpers below: :func:`to_host` gathers per-seed metrics from every process,
:func:`from_primary` makes every process take process 0's decision (e.g. a time limit), and
:func:`is_primary` says which process writes the run's files. Collectives between processes
are used only by these helpers (on CPU through gloo, JAX's default CPU collectives).
"""

from __future__ import annotations

import concurrent.futures
import os
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import compute_on as jax_compute_on
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


def per_device(
    fn: Callable, sharding: NamedSharding, batched: tuple[bool, ...], donate_argnums: tuple[int, ...] = ()
) -> Callable:
    """``fn`` (a seed-vmapped function) run on each device's block of seeds as its own one-device program.

    Each addressable device of ``sharding`` runs ``jax.jit(fn)`` on its block of the seed axis (the
    ``addressable_shards`` of each argument), with no communication; the blocks' results are joined
    into global arrays with ``sharding`` (``jax.make_array_from_single_device_arrays``). Each device's
    program is launched from a thread of its own: launched one after the other from one thread, the
    devices took turns (on 2 GPUs a round of 10 seeds took twice as long as 5 seeds on one; the launch
    of a round's program returned only when it had run). Every device runs the
    program compiled for one device, the program a single-GPU run uses: the SPMD forms (``shard_map``,
    or ``jax.jit`` with the seed sharding on its inputs) crashed XLA's GPU compiler with a segmentation
    fault on 2 GPUs (JAX 0.11.2; ``benchmarks/sharded_compile.py`` compiles each form). The first call
    compiles each device's copy in its thread, at the same time; on GPUs the persistent compilation cache
    (on by default, :mod:`rebel_jax.run.compile_cache`) keys a one-device program without its device, so a
    later run loads every device's copy from one entry.

    Called on tracers (``jax.eval_shape``, ``jax.make_jaxpr``) it is ``fn`` itself: the same shapes.

    Args:
      fn: the function; its outputs carry the seed axis first.
      sharding: the seed axis's sharding (:func:`seed_sharding`).
      batched: for each positional argument of ``fn``, whether it carries the seed axis (else it is
        the same on every device).
      donate_argnums: arguments whose buffers each device's program may reuse (e.g. the replay buffer).
    """
    program = jax.jit(fn, donate_argnums=donate_argnums)
    devices = list(sharding.addressable_devices_indices_map((sharding.mesh.size,)))
    launcher = concurrent.futures.ThreadPoolExecutor(len(devices), thread_name_prefix="per_device")

    def run(*args):
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(args)):
            return fn(*args)
        args = tuple(shard_seeds(a, sharding) if seeded else a for a, seeded in zip(args, batched, strict=True))
        blocks = [_device_blocks(args, batched, device) for device in devices]  # all before a donation deletes any
        results = list(launcher.map(lambda b: program(*b), blocks))
        return jax.tree.map(
            lambda *xs: jax.make_array_from_single_device_arrays(
                (xs[0].shape[0] * sharding.mesh.size, *xs[0].shape[1:]), sharding, list(xs)
            ),
            *results,
        )

    return run


def _device_blocks(args: tuple, batched: tuple[bool, ...], device) -> tuple:
    """``args`` as ``device`` holds them: its block of each seeded array, a copy of each other array."""

    def block(x, seeded: bool):
        if not isinstance(x, jax.Array):
            return x  # NumPy or Python values: uncommitted, they follow the committed arguments.
        if not seeded:
            return jax.device_put(x, device)
        return next(s.data for s in x.addressable_shards if s.device == device)

    return tuple(jax.tree.map(lambda x, s=seeded: block(x, s), a) for a, seeded in zip(args, batched, strict=True))


def padded_columns(columns: int, devices: int) -> int:
    """The columns a run computes over ``devices``: ``columns`` rounded up to a multiple of ``devices``. The
    extra ones (:func:`pad_columns`) repeat the last column and are dropped from every output, so 5 seeds run on
    2 GPUs as 3 + 3 columns, one of them wasted."""
    return -(-columns // devices) * devices


def pad_columns(tree, total: int):
    """Every leaf of ``tree`` (columns on its leading axis) with its last column repeated up to ``total``."""

    def pad(x):
        extra = total - x.shape[0]
        return x if extra == 0 else jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)])

    return jax.tree.map(pad, tree)


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


def on_second_stream(f: Callable) -> Callable:
    """``f`` annotated to run on the GPU's second stream (XLA's ``gpu_stream:1``), beside the work of the first
    that does not read its outputs; its outputs stay in device memory. Other backends ignore the annotation.

    The keyword form (``compute_type``, ``out_memory_spaces``) is JAX 0.10's ``compute_on2`` and JAX 0.11's
    ``compute_on`` (0.11 dropped the positional form and the name ``compute_on2``)."""
    annotate = getattr(jax_compute_on, "compute_on2", None) or jax_compute_on.compute_on
    return annotate(f, compute_type="gpu_stream:1", out_memory_spaces=jax.memory.Space.Device)
