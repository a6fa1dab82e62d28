"""dm_control-equivalent locomotion tasks on MJX."""

from rebel_jax.envs.dmc import SOLVERS, TASKS, DMCEnv, Solver, State, make_env, parse_solver
from rebel_jax.envs.wrappers import AutoResetWrapper

__all__ = ["SOLVERS", "TASKS", "AutoResetWrapper", "DMCEnv", "Solver", "State", "make_env", "parse_solver"]
