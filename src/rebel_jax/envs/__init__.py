"""dm_control-equivalent locomotion tasks on MJX, and a pure-JAX probe task for tests.

Every task is a ``brax.envs.Env`` with brax's ``State``; importing this package registers them
with brax as ``rebel_<task>`` (:mod:`rebel_jax.envs.registry`).
"""

from __future__ import annotations

import rebel_jax.envs._mjx  # noqa: F401 - first: imports mujoco.mjx without its warp noise
from rebel_jax.envs import dmc, metaworld, pixels, registry
from rebel_jax.envs.dmc import IMPLS, SOLVERS, TASKS, DMCEnv, Solver, State, parse_solver  # State: brax's
from rebel_jax.envs.pixel_probe import PixelProbe
from rebel_jax.envs.pixels import PixelEnv
from rebel_jax.envs.probe import PointProbe
from rebel_jax.envs.wrappers import AutoResetWrapper, VmapWrapper  # VmapWrapper: brax's

registry.register()

PROBES = {"probe_point": PointProbe, "probe_point_pixels": PixelProbe}
"""Pure-JAX tasks that compile in seconds, for tests of the training loop (not dm_control tasks)."""

PIXEL_TASKS = tuple(f"{t}{pixels.SUFFIX}" for t, spec in TASKS.items() if spec.has_pixels)
"""Each state task that the pure-JAX camera can draw, seen through camera 0 (:class:`PixelEnv`):
``walker_walk_pixels``, ... The camera (:mod:`rebel_jax.envs.render`) draws planes, spheres and capsules only, so
the quadruped (ellipsoid and cylinder geoms) has no pixel version."""

METAWORLD_TASKS = tuple(f"{metaworld.PREFIX}{t}" for t in metaworld.TASKS)
"""Meta-World's manipulation tasks (:mod:`rebel_jax.envs.metaworld`): ``metaworld_drawer-open``. State only. Their
physics runs MJX's JAX step (``impl='jax'``) or MuJoCo Warp's (``impl='warp'``); a task whose step one engine does
not run faithfully (:data:`rebel_jax.envs.metaworld.STEP_REFUSED`) is refused with it (:func:`not_runnable`)."""


def not_runnable(name: str, impl: str = "jax") -> str | None:
    """Why the Meta-World task ``name`` cannot run with the physics step ``impl``: a one-line reason, or None."""
    return metaworld.refusal(name.removeprefix(metaworld.PREFIX), impl) if name.startswith(metaworld.PREFIX) else None


def no_pixel_version(name: str) -> str | None:
    """Why ``name``, a state task's name with the pixel suffix, is no task: a one-line reason, or None where
    ``name`` is not such a name."""
    state = name.removesuffix(pixels.SUFFIX)
    if name != state and state in METAWORLD_TASKS:
        return f"{state} has no pixel version: Meta-World's tasks are state tasks here (observations of 39 numbers)"
    if name == state or state not in TASKS or TASKS[state].has_pixels:
        return None
    return (
        f"{state} has no pixel version: the pure-JAX camera draws planes, spheres and capsules only, and its model "
        f"has other geoms; pixel tasks: {', '.join(PIXEL_TASKS)}"
    )


def make_env(
    name: str,
    solver: str | Solver = "default",
    episode_length: int | None = 1000,
    unroll_substeps: bool = False,
    all_contacts: bool = False,
    impl: str = "jax",
    worlds: int = 1,
) -> DMCEnv | PixelEnv | PointProbe | metaworld.MetaWorldEnv:
    """Builds a task by name: one of :data:`TASKS` (see :func:`rebel_jax.envs.dmc.make_env`), :data:`PIXEL_TASKS`,
    :data:`METAWORLD_TASKS` (:func:`rebel_jax.envs.metaworld.make_env`) or :data:`PROBES`.

    A probe has no physics engine: ``solver`` and ``impl`` are checked but unused, and so are ``unroll_substeps``,
    ``all_contacts`` and ``worlds``.
    A pixel task's ``episode_length`` counts environment frames, as its state task's does. ``None``: no
    time limit (brax's convention, for ``brax.envs.wrappers.training.EpisodeWrapper``).
    """
    if name in PIXEL_TASKS:
        return PixelEnv(
            dmc.make_env(
                name.removesuffix(pixels.SUFFIX), solver, episode_length, unroll_substeps, all_contacts, impl, worlds
            )
        )
    if name in PROBES:
        parse_solver(solver)
        dmc.check_impl(impl)
        del unroll_substeps, all_contacts, worlds  # Unused.
        return PROBES[name](episode_length)
    reason = no_pixel_version(name)
    if name in METAWORLD_TASKS:
        return _metaworld_env(name, solver, episode_length, impl, worlds)
    if reason:
        raise ValueError(reason)
    if name not in TASKS:
        valid = ", ".join(sorted([*TASKS, *PIXEL_TASKS, *METAWORLD_TASKS]))
        raise ValueError(f"unknown task {name!r}; valid tasks: {valid}, probes: {', '.join(PROBES)}")
    return dmc.make_env(name, solver, episode_length, unroll_substeps, all_contacts, impl, worlds)


def _metaworld_env(
    name: str, solver: str | Solver, episode_length: int | None, impl: str, worlds: int
) -> metaworld.MetaWorldEnv:
    """A Meta-World task: it runs its model's own solver settings (Newton, 50 iterations, as Meta-World), so
    ``solver`` is checked but unused; a pairing of task and ``impl`` that :data:`metaworld.STEP_REFUSED` lists is
    refused in one line."""
    parse_solver(solver)
    dmc.check_impl(impl)
    if reason := not_runnable(name, impl):
        raise ValueError(reason)
    return metaworld.make_env(name, episode_length, impl=impl, worlds=worlds)


__all__ = [
    "METAWORLD_TASKS",
    "IMPLS",
    "PIXEL_TASKS",
    "PROBES",
    "SOLVERS",
    "TASKS",
    "AutoResetWrapper",
    "DMCEnv",
    "PixelEnv",
    "PixelProbe",
    "PointProbe",
    "Solver",
    "State",
    "VmapWrapper",
    "make_env",
    "no_pixel_version",
    "not_runnable",
    "parse_solver",
]
