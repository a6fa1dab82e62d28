"""Checkpoints of the full train state (networks, optimisers, buffer, env, PRNG key) with orbax.

Orbax writes each checkpoint into a temporary directory and renames it only once every
array is on disk, so a save interrupted by a kill never appears as a valid step.
"""

from __future__ import annotations

import pathlib

import jax
import orbax.checkpoint as ocp


def _nonempty_leaves(tree) -> dict[str, jax.Array]:
    """Leaves by flat index, without zero-size arrays (which orbax refuses; MJX data has some)."""
    return {str(i): x for i, x in enumerate(jax.tree.leaves(tree)) if x.size}


class Checkpointer:
    """Saves and restores a pytree under ``directory/<round>``, keeping the latest few."""

    def __init__(self, directory: pathlib.Path, max_to_keep: int = 2):
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
        self.manager = ocp.CheckpointManager(pathlib.Path(directory).absolute(), options=options)

    def save(self, step: int, state) -> None:
        """Saves ``state`` as ``step`` and waits until it is complete on disk."""
        self.manager.save(step, args=ocp.args.StandardSave(_nonempty_leaves(state)))
        self.manager.wait_until_finished()

    def latest(self) -> int | None:
        """The newest complete step, or None."""
        return self.manager.latest_step()

    def restore(self, like, step: int | None = None):
        """Restores ``step`` (default: latest) into arrays shaped, typed and sharded as ``like``."""
        step = self.latest() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no complete checkpoint in {self.manager.directory}")
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _nonempty_leaves(like))
        saved = self.manager.restore(step, args=ocp.args.StandardRestore(abstract))
        leaves, treedef = jax.tree.flatten(like)
        return step, jax.tree.unflatten(treedef, [saved.get(str(i), x) for i, x in enumerate(leaves)])

    def close(self) -> None:
        self.manager.close()
