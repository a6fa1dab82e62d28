"""dm_control-equivalent locomotion tasks on MJX, and a pure-JAX probe task for tests."""

from __future__ import annotations

import rebel_jax.envs._mjx  # noqa: F401 - first: imports mujoco.mjx without its warp noise
from rebel_jax.envs import dmc
from rebel_jax.envs.dmc import SOLVERS, TASKS, DMCEnv, Solver, State, parse_solver
from rebel_jax.envs.probe import PointProbe
from rebel_jax.envs.wrappers import AutoResetWrapper

PROBES = {"probe_point": PointProbe}
"""Pure-JAX tasks that compile in seconds, for tests of the training loop (not dm_control tasks)."""


def make_env(
    name: str, solver: str | Solver = "default", episode_length: int = 1000, unroll_substeps: bool = False
) -> DMCEnv | PointProbe:
    """Builds a task by name: one of :data:`TASKS` (see :func:`rebel_jax.envs.dmc.make_env`) or :data:`PROBES`.

    A probe has no physics engine: ``solver`` is checked but unused, and so is ``unroll_substeps``.
    """
    if name in PROBES:
        parse_solver(solver)
        del unroll_substeps  # Unused.
        return PROBES[name](episode_length)
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; valid tasks: {', '.join(sorted(TASKS))}, probes: {', '.join(PROBES)}")
    return dmc.make_env(name, solver, episode_length, unroll_substeps)


__all__ = [
    "PROBES",
    "SOLVERS",
    "TASKS",
    "AutoResetWrapper",
    "DMCEnv",
    "PointProbe",
    "Solver",
    "State",
    "make_env",
    "parse_solver",
]
