"""Checkpoints of the full train state (networks, optimisers, buffer, env, PRNG key) with orbax.

Orbax writes each checkpoint into a temporary directory and renames it only once every
array is on disk, so a save interrupted by a kill never appears as a valid step. Then
:meth:`Checkpointer.save` writes ``checksums.json`` into the step: each file's size and CRC-32
(orbax keeps none: a data file with one bit flipped can restore silently with wrong values). A step
whose files differ from their checksums (:class:`CheckpointDamaged`, found before orbax reads
anything) or that cannot be read back is moved aside to ``<directory>_damaged/`` by
:meth:`Checkpointer.restore`, which then falls back to the previous step. A step without
``checksums.json`` (a kill just after orbax's rename, or a deleted file) is damaged too, unless the checkpointer is
told that its run was written before checksums existed (``require_checksums=False``), when it is read unchecked.
A step that reads but holds a state of other leaves or shapes than asked for
(written by other code) is neither: :class:`CheckpointMismatch` says so, and nothing is moved.
:meth:`Checkpointer.restore_leaves` reads only some leaves of a step (a policy's parameters, say,
without the replay buffer saved beside them).

With several processes (``--distributed``) every process calls :meth:`Checkpointer.save` and
:meth:`Checkpointer.restore` with the same steps: each writes and reads its own devices' part of
the arrays, and orbax's primary process (process 0) writes the metadata and commits the step.
The saved arrays are whole arrays, so a checkpoint restores on any number of processes and
devices (tested: saved from 2 processes, resumed in 1, and back).

``save(step, state, wait=False)`` returns once the arrays are on the host (orbax's asynchronous save): the files
are written while the caller goes on, and the next call of the checkpointer completes the step and its checksums
(the trainer's rounds overlap the writing of the checkpoint before them; a state run's replay is about 1 GB).

A save that fails (disk full, a directory made read-only) raises :class:`CheckpointSaveError`, an ``OSError``
naming the step and the cause, once orbax's threads have ended: the steps already on disk are untouched, and the
process can exit. Orbax creates a step's directory in the calling thread (not in a background thread, whose
failure left the threads waiting for it forever), and its own tracebacks of a failure, logged from its threads, are
left out (:class:`_OrbaxTracebacks`), as are tensorstore's reports of writes that end after orbax closed the failed
save's event loop (:func:`_closed_loop_callbacks`): the error raised says it once.
"""

from __future__ import annotations

import json
import logging
import os
import pathlib
import re
import sys
import time
import traceback
import warnings
import zlib
from collections.abc import Callable

import jax
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils


def _nonempty_leaves(tree) -> dict[str, jax.Array]:
    """Leaves by flat index, without zero-size arrays (which orbax refuses; MJX data has some)."""
    return {str(i): x for i, x in enumerate(jax.tree.leaves(tree)) if x.size}


class CheckpointMismatch(ValueError):
    """A checkpoint's saved leaves differ in number or shape from the state it is restored into."""


class CheckpointDamaged(OSError):
    """A checkpoint's files differ from the sizes and CRC-32s written when it was saved."""


class CheckpointSaveError(OSError):
    """A checkpoint could not be written: ``errno``, ``strerror`` (the cause) and ``filename`` (the step)."""


def save_error(step: int, step_dir: pathlib.Path, err: Exception) -> CheckpointSaveError:
    """``err`` (an ``OSError``, or tensorstore's ``ValueError`` that carries an ``os_error_code``) as one
    :class:`CheckpointSaveError`: the errno, its text, and the path that failed (else the step's directory)."""
    code = err.errno if isinstance(err, OSError) else None
    found = re.search(r"os_error_code='?(\d+)", str(err))
    if code is None and found:
        code = int(found[1])
    cause = os.strerror(code) if code else (str(err).strip().splitlines() or [type(err).__name__])[0][:200]
    where = getattr(err, "filename", None) or step_dir
    return CheckpointSaveError(code, f"checkpoint {step} not saved: {cause}", str(where))


class _OrbaxTracebacks(logging.Filter):
    """Drops the tracebacks of a failed save or restore that orbax logs from its threads, and that asyncio logs for
    orbax's tasks whose exception nobody read (the caller gets the error)."""

    def filter(self, record: logging.LogRecord) -> bool:
        orbax = f"{os.sep}orbax{os.sep}"
        if not record.exc_info or not record.exc_info[2]:
            return True
        frames = traceback.extract_tb(record.exc_info[2])
        return not (orbax in record.pathname or any(orbax in frame.filename for frame in frames))


def _closed_loop_callbacks(hook: Callable) -> Callable:
    """``sys.unraisablehook`` without the "Event loop is closed" errors of tensorstore writes that end after orbax
    closed the event loop of a failed save (each one a traceback, dozens per failed save)."""

    def unraisablehook(unraisable) -> None:
        value = unraisable.exc_value
        frames = traceback.extract_tb(unraisable.exc_traceback) if unraisable.exc_traceback else []
        closed = isinstance(value, RuntimeError) and str(value) == "Event loop is closed"
        if not (closed and frames and f"{os.sep}asyncio{os.sep}" in frames[-1].filename):
            hook(unraisable)

    unraisablehook.quiet_closed_loops = True
    return unraisablehook


def _quiet_orbax_failures() -> None:
    # A failed save leaves orbax's pending writes (coroutines) unawaited; Python reports each when it collects it,
    # at times after the run's one-line error.
    warnings.filterwarnings("ignore", message=r"coroutine .* was never awaited", category=RuntimeWarning)
    if not getattr(sys.unraisablehook, "quiet_closed_loops", False):
        sys.unraisablehook = _closed_loop_callbacks(sys.unraisablehook)
    for name in ("absl", "asyncio"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, _OrbaxTracebacks) for f in logger.filters):
            logger.addFilter(_OrbaxTracebacks())


CHECKSUMS = "checksums.json"
# Bytes read at a time. The checksum pass over a pixel run's 2.26 GB step took 0.41 s on the development machine's
# CPU, the files in the page cache (BENCHMARKS.md, "Checkpoint checksums on the host").
_CHUNK = 1 << 24


def file_checksums(step_dir: pathlib.Path) -> dict[str, list[int]]:
    """``{path relative to step_dir: [size, CRC-32]}`` of every file of a step but :data:`CHECKSUMS`."""
    sums, buffer = {}, bytearray(_CHUNK)  # one buffer read into, not a new bytes object per chunk
    view = memoryview(buffer)
    for path in sorted(p for p in step_dir.rglob("*") if p.is_file() and p.name != CHECKSUMS):
        crc, size = 0, 0
        with path.open("rb", buffering=0) as f:
            while read := f.readinto(view):
                crc, size = zlib.crc32(view[:read], crc), size + read
        sums[path.relative_to(step_dir).as_posix()] = [size, crc]
    return sums


def checksum_differences(step_dir: pathlib.Path) -> list[str]:
    """How a step's files differ from its :data:`CHECKSUMS` (empty if they match or it has none)."""
    written = step_dir / CHECKSUMS
    if not written.is_file():
        return []
    try:
        saved = json.loads(written.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        return [f"{CHECKSUMS}: unreadable ({err})"]
    now = file_checksums(step_dir)
    missing = [f"{name}: missing" for name in saved if name not in now]
    added = [f"{name}: not saved" for name in now if name not in saved]
    changed = [
        f"{name}: {saved[name][0]} bytes saved, {now[name][0]} now"
        if saved[name][0] != now[name][0]
        else f"{name}: CRC-32 {saved[name][1]:08x} saved, {now[name][1]:08x} now"
        for name in saved.keys() & now.keys()
        if saved[name] != now[name]
    ]
    return missing + sorted(changed) + added


def mismatch(stored: dict[str, tuple[int, ...]], like, only: set[str] | None = None) -> list[str]:
    """The differences between a step's :meth:`Checkpointer.stored_shapes` and the leaves of ``like``.

    With ``only`` (flat indices), the shapes of only those leaves are compared (the number of leaves always).
    """
    wanted = {k: tuple(x.shape) for k, x in _nonempty_leaves(like).items()}
    if stored.keys() != wanted.keys():
        return [f"{len(stored)} leaves saved, {len(wanted)} now"]
    compared = sorted(wanted if only is None else wanted.keys() & only, key=int)
    return [f"leaf {k}: saved {stored[k]}, now {wanted[k]}" for k in compared if stored[k] != wanted[k]]


def leaf_indices(like, select: Callable):
    """``select(like)`` with each leaf replaced by its flat index in ``like`` (as :meth:`Checkpointer.save` keys it).

    Raises:
      ValueError: if ``select`` computes new leaves instead of picking parts of ``like``.
    """
    leaves, treedef = jax.tree.flatten(like)
    indices = select(jax.tree.unflatten(treedef, range(len(leaves))))
    picked = select(like)

    def picks(i, x) -> bool:  # ``i`` is the index of the leaf ``x``
        return isinstance(i, int) and 0 <= i < len(leaves) and leaves[i] is x

    if jax.tree.structure(indices) != jax.tree.structure(picked) or not all(
        picks(i, x) for i, x in zip(jax.tree.leaves(indices), jax.tree.leaves(picked), strict=True)
    ):
        raise ValueError("select must pick parts of the state (leaves as they are), not compute new ones")
    return indices


def _first_few(differences: list[str]) -> str:
    """The first three of ``differences`` and how many more there are."""
    more = len(differences) - 3
    return "; ".join(differences[:3]) + (f"; {more} more" if more > 0 else "")


def _restore_target(x) -> jax.ShapeDtypeStruct:
    """A leaf like ``x`` as orbax is to restore it: on ``x``'s sharding, else on this process's first device."""
    sharding = getattr(x, "sharding", None) or jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)


class Checkpointer:
    """Saves and restores a pytree under ``directory/<round>``, keeping the latest few."""

    def __init__(
        self, directory: pathlib.Path, max_to_keep: int = 2, require_checksums: bool = True, set_aside: bool = True
    ):
        """Args:
        directory: where the steps are.
        max_to_keep: the newest steps kept.
        require_checksums: a step without ``checksums.json`` is damaged (False only for a run written before
          checksums existed, which its ``meta.json`` says).
        set_aside: move an unreadable step to ``<directory>_damaged/`` (False: leave it, for a reader that must not
          change the run, such as ``python -m rebel_jax.run.video``).
        """
        self.directory = pathlib.Path(directory).absolute()
        self.require_checksums = require_checksums
        self.set_aside = set_aside
        _quiet_orbax_failures()
        synchronous_dirs = ocp.AsyncOptions(create_directories_asynchronously=False)
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True, async_options=synchronous_dirs)
        handler = ocp.StandardCheckpointHandler()
        self.manager = ocp.CheckpointManager(self.directory, options=options, item_handlers=handler)
        self._unfinished: tuple[int, bool] | None = None  # (step, whether orbax saved it): see :meth:`save`

    def save(self, step: int, state, wait: bool = True) -> None:
        """Saves ``state`` as ``step``; with ``wait``, until it is complete on disk with its checksums.

        The previous save is finished first (:meth:`finish`). Without ``wait`` the call returns once orbax has
        copied the arrays to the host (its save's blocking part): the files are written in orbax's threads while
        the caller goes on (the next round may donate the arrays), and the next :meth:`save`, :meth:`finish`,
        :meth:`latest` or :meth:`close` completes the step, writes its checksums and raises its error, if any.
        A step already on disk is left as it is (orbax skips it).

        Raises:
          CheckpointSaveError: if this step or the unfinished one before it could not be written (the steps on
            disk before it are kept).
        """
        self.finish()
        step_dir = self.directory / str(step)
        try:
            saved = self.manager.save(step, args=ocp.args.StandardSave(_nonempty_leaves(state)))
        except Exception as err:  # noqa: BLE001 - orbax and tensorstore raise many kinds
            raise save_error(step, step_dir, err) from err
        self._unfinished = (step, saved)
        if wait:
            self.finish()

    def finish(self) -> None:
        """Waits for the save in flight (if any) to be on disk, then writes its step's ``checksums.json``.

        Raises:
          CheckpointSaveError: if that step could not be written.
        """
        if self._unfinished is None:
            return
        (step, saved), self._unfinished = self._unfinished, None
        step_dir = self.directory / str(step)
        try:
            self.manager.wait_until_finished()
            if saved and jax.process_index() == 0:  # Every process's files are in the step once orbax renamed it.
                partial = step_dir / (CHECKSUMS + ".part")
                partial.write_text(json.dumps(file_checksums(step_dir)))
                os.replace(partial, step_dir / CHECKSUMS)
        except Exception as err:  # noqa: BLE001 - orbax and tensorstore raise many kinds
            raise save_error(step, step_dir, err) from err
        if saved and jax.process_count() > 1:
            multihost_utils.sync_global_devices(f"checkpoint {step} checksummed")

    def latest(self) -> int | None:
        """The newest complete step (the save in flight finished first), or None."""
        self.finish()
        return self.manager.latest_step()

    def steps(self) -> list[int]:
        """Every complete step on disk, oldest first (the save in flight finished first)."""
        self.finish()
        return sorted(self.manager.all_steps())

    def stored_shapes(self, step: int) -> dict[str, tuple[int, ...]]:
        """The shape of each saved leaf of ``step``, by flat index (as saved; zero-size leaves are not)."""
        return {k: tuple(v.shape) for k, v in self.manager.item_metadata(step).items()}

    def restore(self, like, step: int | None = None, adapt: Callable | None = None):
        """Restores ``step`` (default: the newest readable one) into arrays shaped, typed and sharded as ``like``.

        Without ``step``, an unreadable newest step is moved to ``<directory>_damaged/`` with a
        warning on stderr, and the one before it is tried, and so on.

        Args:
          like: the tree to restore into.
          step: the step; default the newest readable one.
          adapt: ``adapt(like, shapes)`` gives the tree to restore a step into from its stored
            :meth:`stored_shapes` (e.g. a smaller replay buffer, for a run that is being extended).

        Returns:
          (step, state).

        Raises:
          FileNotFoundError: if there is no complete step, or none could be read.
          CheckpointMismatch: if a step's saved leaves differ from ``like``'s (after ``adapt``) in
            number or shape; no step is moved aside then.
        """
        return self._newest_readable(lambda s: self._restore(like, s, adapt), step)

    def restore_leaves(self, like, select: Callable, step: int | None = None):
        """Restores ``select(like)``'s leaves of ``step`` (default: the newest readable one); the others are not read.

        ``select`` picks a part of the state, e.g. ``trainer.policy_params``: a policy's parameters are read
        without the replay buffer saved beside them. The step must hold a state of ``like``'s leaves, and the
        selected ones must have ``like``'s shapes (the others may differ: a run extended to a larger buffer,
        say). Unreadable steps are moved aside as by :meth:`restore`, but a step whose other leaves are
        damaged still reads.

        Args:
          like: the whole state the step was saved from (arrays or ``jax.ShapeDtypeStruct``).
          select: ``select(state)`` gives a subtree of ``state`` (attribute and key access only).
          step: the step; default the newest readable one.

        Returns:
          (step, ``select(state)``), as arrays shaped and typed as ``select(like)``'s leaves, on their sharding
          (on this process's first device for leaves without one).

        Raises:
          FileNotFoundError: if there is no complete step, or none could be read.
          CheckpointMismatch: if a step's saved leaves differ from ``like``'s in number, or the selected ones in
            shape; no step is moved aside then.
          ValueError: if ``select`` computes new leaves instead of picking parts of ``like``.
        """
        indices = leaf_indices(like, select)
        return self._newest_readable(lambda s: self._restore_leaves(like, indices, s), step)

    def _newest_readable(self, read: Callable, step: int | None):
        """(step, ``read(step)``) of ``step``, or of the newest step that reads, moving the unreadable ones aside."""
        if step is not None:
            return step, read(step)
        for candidate in reversed(self.steps()):
            try:
                return candidate, read(candidate)
            except CheckpointMismatch:
                raise
            except Exception as err:  # noqa: BLE001 - orbax and tensorstore raise many kinds
                reason = str(err).strip().splitlines()[0][:200] if str(err).strip() else ""
                done = f"moved it to {self._set_aside(candidate)}" if self.set_aside else "left it in place"
                if jax.process_index() == 0:
                    print(
                        f"warning: checkpoint {candidate} in {self.directory} is unreadable "
                        f"({type(err).__name__}: {reason}); {done} and trying the previous one",
                        file=sys.stderr,
                    )
        raise FileNotFoundError(f"no readable checkpoint in {self.directory}")

    def _check_files(self, step: int) -> None:
        """Raises :class:`CheckpointDamaged` naming the first few files of ``step`` that differ from its checksums."""
        step_dir = self.directory / str(step)
        if self.require_checksums and not (step_dir / CHECKSUMS).is_file():
            raise CheckpointDamaged(f"{CHECKSUMS} is missing (its save did not finish, or it was deleted)")
        differences = checksum_differences(step_dir)
        if differences:
            raise CheckpointDamaged(f"files differ from their checksums ({_first_few(differences)})")

    def _restore(self, like, step: int, adapt: Callable | None):
        self._check_files(step)
        stored = self.stored_shapes(step)
        if adapt is not None and stored.keys() == _nonempty_leaves(like).keys():  # The same leaves: adapt shapes.
            like = adapt(like, stored)
        self._refuse_mismatch(step, mismatch(stored, like))
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _nonempty_leaves(like))
        saved = self.manager.restore(step, args=ocp.args.StandardRestore(abstract))
        leaves, treedef = jax.tree.flatten(like)
        return jax.tree.unflatten(treedef, [saved.get(str(i), x) for i, x in enumerate(leaves)])

    def _restore_leaves(self, like, indices, step: int):
        """The leaves at flat ``indices`` (a tree of ints) of ``step``, read with orbax's partial restore."""
        self._check_files(step)  # all of them: OCDBT packs leaves into shared data files
        leaves = jax.tree.leaves(like)
        keys = {str(i) for i in jax.tree.leaves(indices) if leaves[i].size}
        self._refuse_mismatch(step, mismatch(self.stored_shapes(step), like, only=keys))
        target = {k: _restore_target(leaves[int(k)]) for k in keys}
        args = ocp.args.PyTreeRestore(
            item=target, restore_args=ocp.checkpoint_utils.construct_restore_args(target), partial_restore=True
        )
        # What StandardCheckpointHandler saved, PyTreeCheckpointHandler (which it wraps) reads, leaf by leaf.
        handler = ocp.PyTreeCheckpointHandler()
        try:
            item = self.directory / str(step) / ocp.checkpoint_manager.DEFAULT_ITEM_NAME
            saved = handler.restore(item, args=args) if target else {}
        finally:
            handler.close()
        return jax.tree.map(lambda i: saved.get(str(i), leaves[i]), indices)

    def _refuse_mismatch(self, step: int, differences: list[str]) -> None:
        """Raises :class:`CheckpointMismatch` naming the first few of a step's ``differences``, if any."""
        if differences:
            shown = _first_few(differences)
            raise CheckpointMismatch(f"checkpoint {step} in {self.directory} holds another state ({shown})")

    def _set_aside(self, step: int) -> pathlib.Path:
        """Moves a damaged step out of orbax's directory (so that a new save of that step is not skipped).

        With several processes, process 0 moves it while the others wait.
        """
        damaged = self.directory.with_name(self.directory.name + "_damaged")
        target = damaged / f"{step}-{time.strftime('%Y%m%d-%H%M%S')}"
        if jax.process_index() == 0:
            damaged.mkdir(exist_ok=True)
            (self.directory / str(step)).rename(target)
        if jax.process_count() > 1:
            multihost_utils.sync_global_devices(f"checkpoint {step} set aside")
        self.manager.reload()
        return target

    def close(self) -> None:
        """Finishes the save in flight (raising its error, if any), then ends orbax's threads."""
        try:
            self.finish()
        finally:
            self.manager.close()
