"""Checkpoints of the full train state (networks, optimisers, buffer, env, PRNG key) with orbax.

Orbax writes each checkpoint into a temporary directory and renames it only once every
array is on disk, so a save interrupted by a kill never appears as a valid step. A step
that is on disk but cannot be read back (a file truncated or deleted afterwards) is moved
aside to ``<directory>_damaged/`` by :meth:`Checkpointer.restore`, which then falls back to
the previous step. A step that reads but holds a state of other leaves or shapes than asked for
(written by other code) is neither: :class:`CheckpointMismatch` says so, and nothing is moved.

With several processes (``--distributed``) every process calls :meth:`Checkpointer.save` and
:meth:`Checkpointer.restore` with the same steps: each writes and reads its own devices' part of
the arrays, and orbax's primary process (process 0) writes the metadata and commits the step.
The saved arrays are whole arrays, so a checkpoint restores on any number of processes and
devices (tested: saved from 2 processes, resumed in 1, and back).
"""

from __future__ import annotations

import pathlib
import sys
import time
from collections.abc import Callable

import jax
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils


def _nonempty_leaves(tree) -> dict[str, jax.Array]:
    """Leaves by flat index, without zero-size arrays (which orbax refuses; MJX data has some)."""
    return {str(i): x for i, x in enumerate(jax.tree.leaves(tree)) if x.size}


class CheckpointMismatch(ValueError):
    """A checkpoint's saved leaves differ in number or shape from the state it is restored into."""


def mismatch(stored: dict[str, tuple[int, ...]], like) -> list[str]:
    """The differences between a step's :meth:`Checkpointer.stored_shapes` and the leaves of ``like``."""
    wanted = {k: tuple(x.shape) for k, x in _nonempty_leaves(like).items()}
    if stored.keys() != wanted.keys():
        return [f"{len(stored)} leaves saved, {len(wanted)} now"]
    return [f"leaf {k}: saved {stored[k]}, now {wanted[k]}" for k in sorted(wanted, key=int) if stored[k] != wanted[k]]


class Checkpointer:
    """Saves and restores a pytree under ``directory/<round>``, keeping the latest few."""

    def __init__(self, directory: pathlib.Path, max_to_keep: int = 2):
        self.directory = pathlib.Path(directory).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
        handler = ocp.StandardCheckpointHandler()
        self.manager = ocp.CheckpointManager(self.directory, options=options, item_handlers=handler)

    def save(self, step: int, state) -> None:
        """Saves ``state`` as ``step`` and waits until it is complete on disk."""
        self.manager.save(step, args=ocp.args.StandardSave(_nonempty_leaves(state)))
        self.manager.wait_until_finished()

    def latest(self) -> int | None:
        """The newest complete step, or None."""
        return self.manager.latest_step()

    def steps(self) -> list[int]:
        """Every complete step on disk, oldest first."""
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
        if step is not None:
            return step, self._restore(like, step, adapt)
        for candidate in reversed(self.steps()):
            try:
                return candidate, self._restore(like, candidate, adapt)
            except CheckpointMismatch:
                raise
            except Exception as err:  # noqa: BLE001 - orbax and tensorstore raise many kinds
                reason = str(err).strip().splitlines()[0][:200] if str(err).strip() else ""
                moved = self._set_aside(candidate)
                if jax.process_index() == 0:
                    print(
                        f"warning: checkpoint {candidate} in {self.directory} is unreadable "
                        f"({type(err).__name__}: {reason}); moved it to {moved} and trying the previous one",
                        file=sys.stderr,
                    )
        raise FileNotFoundError(f"no readable checkpoint in {self.directory}")

    def _restore(self, like, step: int, adapt: Callable | None):
        stored = self.stored_shapes(step)
        if adapt is not None and stored.keys() == _nonempty_leaves(like).keys():  # The same leaves: adapt shapes.
            like = adapt(like, stored)
        differences = mismatch(stored, like)
        if differences:
            shown = "; ".join(differences[:3]) + (f"; {len(differences) - 3} more" if len(differences) > 3 else "")
            raise CheckpointMismatch(f"checkpoint {step} in {self.directory} holds another state ({shown})")
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _nonempty_leaves(like))
        saved = self.manager.restore(step, args=ocp.args.StandardRestore(abstract))
        leaves, treedef = jax.tree.flatten(like)
        return jax.tree.unflatten(treedef, [saved.get(str(i), x) for i, x in enumerate(leaves)])

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
        self.manager.close()
