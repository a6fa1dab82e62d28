"""The compiled programs of a run: jitted, seed-vmapped ``init``, ``round`` and ``evaluate`` of a
:class:`~rebel_jax.train.trainer.Trainer`, on one device or sharded over several (:mod:`rebel_jax.train.placement`)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
from jax.sharding import NamedSharding

from rebel_jax.train import placement
from rebel_jax.train.trainer import Trainer


def compiled(trainer: Trainer, sharding: NamedSharding | None = None) -> tuple[Callable, Callable, Callable]:
    """Jitted, seed-vmapped ``init(keys)``, ``round(states, r)`` and ``evaluate(params, keys, random_actions)``.

    The round donates its input state so the replay buffer is updated in place. ``random_actions``
    (unbatched, default False) evaluates uniform random actions on the same initial states instead; a sequence
    of flags, e.g. ``(False, True)``, evaluates each of them in one program, as one batch of episodes (an
    episode's physics takes about as long at twice the batch), and returns one column per flag. On a task that
    reports success, ``evaluate(..., success=True)`` returns (returns, success rates) of those shapes
    (``Trainer.evaluate``). On one device, ``evaluate.compile_ahead(policy, keys, random_actions, success=False)``
    compiles its program for those arguments' shapes (while a round runs, say) and returns it as a function of
    ``(policy, keys)``.

    Args:
      trainer: the run's trainer.
      sharding: the seed axis's sharding over several devices (``placement.seed_sharding``), or None
        for one device. Each device then runs the one-device program on its own seeds
        (:func:`rebel_jax.train.placement.per_device`), with no communication between devices. Per seed the
        result is the same as on one device: under ``vmap`` a seed whose loop has stopped (the
        reward model's early stopping) is masked, whichever seeds share its batch.
    """
    init = jax.vmap(trainer.init)
    round_fn = jax.vmap(trainer.round, in_axes=(0, None))
    if sharding is None:
        init, round_fn = jax.jit(init), jax.jit(round_fn, donate_argnums=0)
    else:
        init = placement.per_device(init, sharding, batched=(True,))
        round_fn = placement.per_device(round_fn, sharding, batched=(True, False), donate_argnums=(0,))

    @functools.cache  # each program built when first asked for
    def evaluation(success: bool, each: bool) -> Callable:
        """The seed-vmapped evaluation: of one flag, (seeds,); of each of several flags, (seeds, n)."""
        one = functools.partial(trainer.evaluate, success=True) if success else trainer.evaluate
        fn = jax.vmap(jax.vmap(one, in_axes=(None, None, 0)) if each else one, in_axes=(0, 0, None))
        if sharding is None:
            return jax.jit(fn)
        return placement.per_device(fn, sharding, batched=(True, True, False))

    def program(random_actions: bool | Sequence[bool], success: bool) -> tuple[Callable, jax.Array]:
        flags = jnp.asarray(random_actions, bool)
        return evaluation(bool(success), bool(flags.ndim)), flags

    def evaluate(policy, keys: jax.Array, random_actions: bool | Sequence[bool] = False, success: bool = False):
        run, flags = program(random_actions, success)
        return run(policy, keys, flags)

    def compile_ahead(
        policy, keys: jax.Array, random_actions: bool | Sequence[bool] = False, success: bool = False
    ) -> Callable:
        """``evaluate``'s program for these arguments (or their shapes) compiled now: ``f(policy, keys)``."""
        run, flags = program(random_actions, success)
        executable = run.lower(policy, keys, flags).compile()
        return lambda policy, keys: executable(policy, keys, flags)

    if sharding is None:  # per_device programs compile on each device at their first call
        evaluate.compile_ahead = compile_ahead
    return init, round_fn, evaluate
