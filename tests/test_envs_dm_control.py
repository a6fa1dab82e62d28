"""Equivalence with dm_control: compiled models, observations, rewards, dynamics, resets."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from rebel_jax.envs import TASKS
from rebel_jax.envs.dmc import mj_model

suite = pytest.importorskip("dm_control.suite")

B = 32  # the batch size of tests/test_envs.py, so compiled functions are shared
SAME_RESET = {"walker_stand": "walker_walk", "walker_run": "walker_walk"}

MODEL_FIELDS = [
    "body_mass", "body_inertia", "body_pos", "body_quat", "body_ipos", "body_iquat", "body_parentid",
    "geom_type", "geom_size", "geom_pos", "geom_quat", "geom_bodyid", "geom_friction", "geom_contype",
    "geom_conaffinity", "geom_condim", "geom_solref", "geom_solimp",
    "jnt_type", "jnt_range", "jnt_limited", "jnt_axis", "jnt_pos", "jnt_stiffness", "jnt_solref", "jnt_solimp",
    "dof_damping", "dof_armature", "dof_frictionloss",
    "actuator_gear", "actuator_ctrlrange", "actuator_ctrllimited", "actuator_trnid",
    "sensor_type", "sensor_objid", "qpos0",
]  # fmt: skip


def _dm_env(task: str, seed: int = 0):
    domain, name = task.split("_")
    return suite.load(domain, name, task_kwargs={"random": seed})


def _dm_obs(timestep) -> np.ndarray:
    return np.concatenate([np.atleast_1d(v) for v in timestep.observation.values()])


@pytest.mark.parametrize("task", sorted(TASKS))
def test_compiled_model_equals_dm_control(task):
    ours, ref = mj_model(task), _dm_env(task).physics.model._model
    for field in MODEL_FIELDS:
        a, b = getattr(ours, field), getattr(ref, field)
        assert a.shape == b.shape, field
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=1e-9, err_msg=field)
    assert ours.opt.timestep == ref.opt.timestep
    assert (ours.nq, ours.nv, ours.nu, ours.nbody, ours.ngeom) == (ref.nq, ref.nv, ref.nu, ref.nbody, ref.ngeom)
    assert ours.opt.integrator == ref.opt.integrator and ours.opt.cone == ref.opt.cone
    # Control time step: dm_control's n_sub_steps physics steps per control step.
    from rebel_jax.envs import make_env

    assert make_env(task).dt == pytest.approx(_dm_env(task).control_timestep())


def _reference_trajectory(task: str, steps: int, seed: int = 0):
    """dm_control states, actions, next observations and rewards under random actions."""
    env, rng = _dm_env(task, seed), np.random.default_rng(seed)
    env.reset()
    qpos, qvel, warm, actions, obs, rewards = [], [], [], [], [], []
    for _ in range(steps):
        d = env.physics.data
        qpos.append(d.qpos.copy()), qvel.append(d.qvel.copy()), warm.append(d.qacc_warmstart.copy())
        actions.append(rng.uniform(-1, 1, 6))
        ts = env.step(actions[-1])
        obs.append(_dm_obs(ts)), rewards.append(ts.reward)
    f32 = lambda x: jnp.asarray(np.array(x), jnp.float32)
    return f32(qpos), f32(qvel), f32(warm), f32(actions), np.array(obs), np.array(rewards)


def _batch_with_states(c, qpos, qvel, warm):
    """A batch of ``c``'s reset states (``c`` a :class:`CompiledEnv`) holding the given physics states.

    The tests pass the default solver's env (its reset compiled for the other tests) whatever the
    solver they step: a step reads qpos, qvel, qacc_warmstart and the action (the solver's settings
    are in the model), and the data has the same structure for every solver. This saves compiling
    the dm_control solver's reset, about a minute on 2 cores.
    """
    base = c.batch_reset(jax.random.split(jax.random.PRNGKey(0), qpos.shape[0]))
    d = base.pipeline_state.replace(qpos=qpos, qvel=qvel, qacc_warmstart=warm)
    return base.replace(pipeline_state=d)


@pytest.mark.parametrize(
    # walker_stand and walker_run (used by no experiment; each observation compile is ~30 s) in make test-heavy; the
    # quadruped's observation reads sensors: tests/test_envs_quadruped.py tests it
    "task",
    [pytest.param(t, marks=pytest.mark.heavy) if t in SAME_RESET else t for t in sorted(TASKS) if "quadruped" not in t],
)
def test_observation_and_reward_equal_dm_control_on_same_states(compiled_env, task):
    qpos, qvel, _, _, _, _ = _reference_trajectory(task, B)
    ref, obs_ref, rew_ref = _dm_env(task), [], []
    for q, v in zip(np.asarray(qpos, np.float64), np.asarray(qvel, np.float64), strict=True):
        with ref.physics.reset_context():
            ref.physics.data.qpos[:], ref.physics.data.qvel[:] = q, v
        obs_ref.append(np.concatenate([np.atleast_1d(x) for x in ref.task.get_observation(ref.physics).values()]))
        rew_ref.append(ref.task.get_reward(ref.physics))
    # The walker tasks' reset is walker_walk's (tests/test_envs.py): a base of the right structure
    # without compiling their own.
    base = compiled_env(SAME_RESET.get(task, task)).batch_reset(jax.random.split(jax.random.PRNGKey(0), qpos.shape[0]))
    d = base.pipeline_state.replace(qpos=qpos, qvel=qvel)
    state = compiled_env(task).observe(d, base.info["steps"], base.done)
    np.testing.assert_allclose(state.obs, np.array(obs_ref), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(state.reward, np.array(rew_ref), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("task", ["walker_walk", "cheetah_run"])
@pytest.mark.parametrize("solver,mean_tol,max_tol", [("dm_control", 1e-4, 2e-3), ("default", 1e-2, 0.5)])
def test_one_control_step_matches_dm_control(compiled_env, task, solver, mean_tol, max_tol):
    """From the same 32 states and actions, one control step lands where dm_control's does.

    With dm_control's solver settings MJX agrees to float32 precision; the faster default
    (4 Newton / 8 line-search iterations) leaves a small mean and a bounded worst-case
    one-step error in contact-rich steps (figures in BENCHMARKS.md).
    """
    qpos, qvel, warm, actions, obs_ref, rew_ref = _reference_trajectory(task, B)
    states = _batch_with_states(compiled_env(task), qpos, qvel, warm)
    nxt = compiled_env(task, solver).batch_step(states, actions)
    scale = np.maximum(1.0, np.abs(obs_ref))  # velocities reach tens of units
    rel = np.abs(np.asarray(nxt.obs) - obs_ref) / scale
    assert rel.mean() < mean_tol and rel.max() < max_tol, (rel.mean(), rel.max())
    assert np.max(np.abs(np.asarray(nxt.reward) - rew_ref)) < max_tol


@pytest.mark.parametrize("task", ["walker_walk", "cheetah_run"])
def test_reset_distribution_matches_dm_control(compiled_env, task):
    n, reset = 6 * B, compiled_env(task).batch_reset
    ours = np.concatenate([np.asarray(reset(jax.random.split(jax.random.PRNGKey(i), B)).obs) for i in range(6)])
    ref_env = _dm_env(task, seed=1)
    ref = np.array([_dm_obs(ref_env.reset()) for _ in range(n)])
    assert ours.shape == ref.shape
    for i in range(ref.shape[1]):
        if np.ptp(ref[:, i]) == 0:  # e.g. zero initial velocities
            np.testing.assert_allclose(ours[:, i], ref[:, i], atol=1e-5)
        else:
            p = stats.ks_2samp(ours[:, i], ref[:, i]).pvalue
            assert p > 1e-5, f"obs[{i}] distribution differs (KS p={p:.2g})"
