"""The tasks in brax's environment registry: ``brax.envs.get_environment("rebel_walker_walk")``.

Importing :mod:`rebel_jax.envs` registers each task of :data:`rebel_jax.envs.TASKS` as
``rebel_<task>`` (``rebel_walker_stand``, ``rebel_walker_walk``, ``rebel_walker_run``,
``rebel_cheetah_run``, ``rebel_quadruped_walk``, ``rebel_quadruped_run``) and the test probe as
``rebel_probe_point``. A registered task follows
brax's convention: it has no time limit of its own (``episode_length=None``: ``done`` stays 0 and
``info`` holds no step count), and ``brax.envs.create(name, episode_length=1000, ...)`` adds
brax's ``EpisodeWrapper``, which keeps the step count and sets ``done`` and ``truncation`` at
the limit, as our own time limit does (tested in ``tests/test_brax.py``). Keyword arguments of
``get_environment`` / ``create`` reach the task: ``solver`` and ``unroll_substeps`` (see
:func:`rebel_jax.envs.dmc.make_env`). Meta-World's tasks register as ``rebel_metaworld_<task>`` and take
``goal_observable``, ``impl`` (``jax`` by default; a task whose JAX step is refused runs with ``impl="warp"``)
and ``worlds``.

Each episode starts from the task's reset distribution only if the caller resets it: brax's
``AutoResetWrapper`` (which ``create`` adds unless ``auto_reset=False``) restarts every episode
from the first reset state, and :class:`rebel_jax.envs.AutoResetWrapper` draws a fresh one.
"""

from __future__ import annotations

from collections.abc import Callable

from brax import envs as brax_envs

from rebel_jax.envs import dmc, metaworld
from rebel_jax.envs.probe import PointProbe

PREFIX = "rebel_"


def _task_factory(task: str) -> Callable[..., dmc.DMCEnv]:
    def make(
        solver: str | dmc.Solver = "default",
        unroll_substeps: bool = False,
        all_contacts: bool = False,
        impl: str = "jax",
        worlds: int = 1,
    ) -> dmc.DMCEnv:
        return dmc.make_env(task, solver, None, unroll_substeps, all_contacts, impl, worlds)

    make.__name__ = make.__qualname__ = f"{PREFIX}{task}"
    make.__doc__ = f"{task} without a time limit, for brax's registry (see {__name__})."
    return make


def _metaworld_factory(task: str) -> Callable[..., metaworld.MetaWorldEnv]:
    def make(goal_observable: bool = True, impl: str = "jax", worlds: int = 1) -> metaworld.MetaWorldEnv:
        if reason := metaworld.refusal(task, impl):
            raise ValueError(reason)
        return metaworld.MetaWorldEnv(task, None, goal_observable, impl, worlds)

    make.__name__ = make.__qualname__ = f"{PREFIX}{metaworld.PREFIX}{task}"
    make.__doc__ = f"Meta-World's {task} without a time limit, for brax's registry (see {__name__})."
    return make


def _probe() -> PointProbe:
    """probe_point without a time limit, for brax's registry."""
    return PointProbe(episode_length=None)


def brax_names() -> dict[str, Callable[..., object]]:
    """The names this module registers with brax, and their constructors."""
    names: dict[str, Callable[..., object]] = {f"{PREFIX}{task}": _task_factory(task) for task in dmc.TASKS}
    names[f"{PREFIX}probe_point"] = _probe
    for task in metaworld.TASKS:
        names[f"{PREFIX}{metaworld.PREFIX}{task}"] = _metaworld_factory(task)
    return names


def register() -> None:
    """Registers :func:`brax_names` with brax (``brax.envs.register_environment``); idempotent."""
    for name, make in brax_names().items():
        # brax calls the registered object with the keyword arguments; a function serves as a class.
        brax_envs.register_environment(name, make)  # type: ignore[arg-type]
