"""Every task resets and steps under jit; batching, episode bookkeeping and errors."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.envs import TASKS, AutoResetWrapper, make_env

B = 32  # One batch size for every batched call, so each compiled function is shared.
OBS_SIZE = {"walker_stand": 24, "walker_walk": 24, "walker_run": 24, "cheetah_run": 17}


# The walker tasks share one model, reset and observation and differ only in their reward, so
# only walker_walk's step is compiled for them (each compile of a step takes about a minute on
# a CPU); walker_stand and walker_run observe its states with their own reward (see below).
PHYSICS = ["cheetah_run", "walker_walk"]
SAME_PHYSICS_AS_WALK = ["walker_run", "walker_stand"]
QUADRUPED = ["quadruped_run", "quadruped_walk"]  # tests/test_envs_quadruped.py (12 actions, MuJoCo's sensors)


def test_every_task_is_tested_here():
    assert set(PHYSICS) | set(SAME_PHYSICS_AS_WALK) | set(QUADRUPED) == set(TASKS)


# make test-heavy: cheetah's batched compile (about 25 s); its reset and step are checked against dm_control in
# tests/test_envs_dm_control.py.
@pytest.mark.parametrize(
    "task", [pytest.param(t, marks=pytest.mark.heavy) if t == "cheetah_run" else t for t in PHYSICS]
)
def test_batched_reset_and_step_are_finite_with_documented_shapes(compiled_env, task):
    c = compiled_env(task)
    state = c.batch_reset(jax.random.split(jax.random.PRNGKey(0), B))
    actions = jax.random.uniform(jax.random.PRNGKey(1), (B, 6), minval=-1, maxval=1)
    for _ in range(3):
        state = c.batch_step(state, actions)
    assert c.env.observation_size == OBS_SIZE[task]
    assert c.env.action_size == 6
    assert state.obs.shape == (B, OBS_SIZE[task])
    assert state.reward.shape == (B,) and state.done.shape == (B,)
    assert np.all(np.isfinite(state.obs)) and np.all(np.isfinite(state.reward))
    assert np.all((state.reward >= 0) & (state.reward <= 1))
    np.testing.assert_array_equal(state.info["steps"], 3)
    # Distinct keys give distinct initial states.
    assert not np.allclose(state.obs[0], state.obs[1])


@pytest.mark.parametrize("task", SAME_PHYSICS_AS_WALK)
def test_other_walker_tasks_share_walker_walks_physics(task):
    spec, walk = TASKS[task], TASKS["walker_walk"]
    assert spec.xml() == walk.xml() and spec.obs_fn is walk.obs_fn
    assert (spec.total_mass, spec.n_substeps, spec.settle_steps, spec.obs_size, spec.randomize_rotational) == (
        walk.total_mass,
        walk.n_substeps,
        walk.settle_steps,
        walk.obs_size,
        walk.randomize_rotational,
    )
    keys = jax.random.split(jax.random.PRNGKey(0), B)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (B, 6), minval=-1, maxval=1)
    env = make_env(task)
    assert env.observation_size == OBS_SIZE[task] and env.action_size == 6
    # The task's own reset and step trace, with the documented shapes (no compile).
    shapes = jax.eval_shape(jax.vmap(env.step), jax.eval_shape(jax.vmap(env.reset), keys), actions)
    assert shapes.obs.shape == (B, OBS_SIZE[task]) and shapes.reward.shape == (B,) == shapes.done.shape


@pytest.mark.heavy
@pytest.mark.parametrize("task", SAME_PHYSICS_AS_WALK)
def test_other_walker_tasks_are_walker_walk_with_their_own_reward(compiled_env, task):
    """In ``make test-heavy``: each compile of a task's observation takes about 30 s on 2 cores, and no experiment
    uses these tasks (``make test`` runs the check above, that they share walker_walk's physics)."""
    keys = jax.random.split(jax.random.PRNGKey(0), B)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (B, 6), minval=-1, maxval=1)
    # walker_walk's states after 3 steps, observed by this task: the same observation, its own reward.
    w = compiled_env("walker_walk")
    state = w.batch_reset(keys)
    for _ in range(3):
        state = w.batch_step(state, actions)
    mine = compiled_env(task).observe(state.pipeline_state, state.info["steps"], state.done)
    np.testing.assert_allclose(mine.obs, state.obs, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(mine.info["steps"], 3)
    assert np.all(np.isfinite(mine.reward)) and np.all((mine.reward >= 0) & (mine.reward <= 1))
    # dm_control's walker rewards: stand = stand_reward; walk and run = stand_reward * (5 move + 1) / 6
    # with move speeds 1 and 8, so run <= walk <= stand on the same states.
    stand = np.asarray(state.metrics["stand_reward"])
    np.testing.assert_allclose(mine.metrics["stand_reward"], stand, rtol=1e-6, atol=1e-6)
    if task == "walker_stand":
        np.testing.assert_allclose(mine.reward, stand, rtol=1e-6, atol=1e-6)
        assert np.all(mine.reward >= state.reward - 1e-6) and np.any(mine.reward > state.reward + 1e-3)
    else:
        assert np.all(mine.reward <= state.reward + 1e-6) and np.any(mine.reward < state.reward - 1e-3)


def test_cheetah_starts_upright_and_walker_at_any_pitch(compiled_env):
    """dm_control draws the walker's root pitch over a full turn but not the cheetah's (a past bug)."""
    keys = jax.random.split(jax.random.PRNGKey(3), B)
    cheetah = compiled_env("cheetah_run").batch_reset(keys)
    pitch = np.asarray(cheetah.pipeline_state.qpos[:, 2])  # rootx, rootz, rooty
    assert np.all(np.abs(pitch) < np.pi / 2), pitch  # settled on its feet, never on its back
    walker = compiled_env("walker_walk").batch_reset(keys)
    pitch = np.asarray(walker.pipeline_state.qpos[:, 2])  # rootz, rootx, rooty
    assert np.all(np.abs(pitch) <= np.pi) and np.mean(np.abs(pitch) > np.pi / 2) > 0.25, pitch


@pytest.mark.heavy  # make test-heavy: compiles the unbatched reset and step (test_envs_dm_control
# checks the batched step state by state against dm_control in make test)
def test_vmapped_step_equals_stepping_each_env_alone(compiled_env):
    c = compiled_env("walker_walk")
    keys = jax.random.split(jax.random.PRNGKey(2), B)
    actions = jax.random.uniform(jax.random.PRNGKey(3), (B, 6), minval=-1, maxval=1)
    batched = c.batch_step(c.batch_reset(keys), actions)
    for i in range(3):
        alone = c.step(c.reset(keys[i]), actions[i])
        np.testing.assert_allclose(batched.obs[i], alone.obs, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(batched.reward[i], alone.reward, rtol=1e-5, atol=1e-6)


def test_time_limit_truncates_without_terminating(compiled_env):
    c = compiled_env("walker_walk")
    state = c.batch_reset(jax.random.split(jax.random.PRNGKey(0), B))
    # Jump to the end of the episode instead of stepping 998 times.
    state = state.replace(info=dict(state.info, steps=jnp.full((B,), c.env.episode_length - 2, jnp.int32)))
    state = c.batch_step(state, jnp.zeros((B, 6)))
    np.testing.assert_array_equal(state.done, 0.0)
    np.testing.assert_array_equal(state.info["truncation"], 0.0)
    state = c.batch_step(state, jnp.zeros((B, 6)))
    np.testing.assert_array_equal(state.done, 1.0)
    np.testing.assert_array_equal(state.info["truncation"], 1.0)  # a time limit, not a termination


def test_auto_reset_restarts_finished_episodes_and_keeps_final_obs():
    wrapped = AutoResetWrapper(make_env("probe_point", episode_length=2), num_envs=2)  # the wrapper, not the physics
    step = jax.jit(wrapped.step)
    state = jax.jit(wrapped.reset)(jax.random.PRNGKey(0))
    first_obs = state.obs
    state = step(state, jnp.ones((2, 2)))
    state = step(state, jnp.ones((2, 2)))
    np.testing.assert_array_equal(state.done, 1.0)
    np.testing.assert_array_equal(state.info["steps"], 0)  # restarted
    assert not np.allclose(state.info["final_obs"], state.obs)  # the episode's last obs is kept
    assert not np.allclose(state.obs, first_obs)  # a fresh draw, not the first state again
    assert not np.allclose(state.obs[0], state.obs[1])  # each environment draws its own restart
    state = step(state, jnp.ones((2, 2)))
    np.testing.assert_array_equal(state.done, 0.0)
    np.testing.assert_array_equal(state.info["steps"], 1)


def test_unknown_task_lists_valid_tasks():
    with pytest.raises(ValueError, match="walker_walk.*") as err:
        make_env("walker_fly")
    for task in TASKS:
        assert task in str(err.value)


def test_wrong_action_shape_says_what_was_expected():
    env = make_env("cheetah_run")
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"shape \(6,\), got \(5,\)"):
        jax.eval_shape(env.step, state, jnp.zeros(5))


def test_unknown_solver_is_rejected():
    with pytest.raises(ValueError, match="dm_control"):
        make_env("walker_walk", solver="fastest")


# A falling box and sphere on a plane: contacts, so MJX's Newton solver iterates; compiles in seconds.
_CONTACT_XML = """
<mujoco>
  <option timestep="0.005" iterations="4" ls_iterations="8"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body pos="0 0 0.12"><freejoint/><geom type="box" size="0.1 0.1 0.1"/></body>
    <body pos="0.5 0 0.12"><freejoint/><geom type="sphere" size="0.1"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.heavy
def test_newton_trips_equal_mjx_while_loop_on_a_contact_batch():
    """``_mjx.newton_trips`` replaces MJX's Newton ``while_loop`` by known trips with the same results.

    In ``make test-heavy`` (three long compiles; the solver presets use MJX's while loop): ``make test``
    checks their wiring in the traced walker step (``test_walker_step_has_a_while_loop_only_with_mjx_newton_loop``).
    """
    import mujoco
    from mujoco import mjx

    from rebel_jax.envs._mjx import newton_trips

    model = mujoco.MjModel.from_xml_string(_CONTACT_XML)
    m = mjx.put_model(model)
    qvel = jax.random.normal(jax.random.PRNGKey(0), (4, model.nv))
    data = jax.vmap(lambda v: mjx.make_data(m).replace(qvel=v))(qvel)

    def steps(d):
        return jax.lax.fori_loop(0, 30, lambda _, x: jax.vmap(mjx.step, (None, 0))(m, x), d)

    def with_trips(d, unroll):
        with newton_trips(model.opt.iterations, unroll=unroll) as replaced:
            out = steps(d)
        assert replaced == [model.opt.iterations]  # the one Newton loop of mjx.step, traced once
        return out

    expected = jax.jit(steps)(data)
    assert float(jnp.min(expected.qpos[:, 2])) < 0.11  # the box rests on the plane: the solver had work
    trips, unrolled = (jax.jit(with_trips, static_argnums=1)(data, unroll) for unroll in (False, True))
    for name in ("qpos", "qvel", "qacc", "qfrc_constraint"):
        np.testing.assert_array_equal(getattr(trips, name), getattr(expected, name), err_msg=name)
        # XLA fuses the unrolled trips differently: float32 rounding, grown over 30 steps of contact.
        np.testing.assert_allclose(getattr(unrolled, name), getattr(expected, name), rtol=1e-4, atol=1e-4, err_msg=name)


@pytest.mark.parametrize("loop", ["while", "trips"])
def test_walker_step_has_a_while_loop_only_with_mjx_newton_loop(loop):
    """The traced walker step: MJX's Newton ``while_loop`` under ``while``, known trips only under ``trips``."""
    env = make_env("walker_walk", solver=f"default:{loop}")
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    jaxpr = str(jax.make_jaxpr(env.step)(state, jnp.zeros(6)))
    assert ("while[" in jaxpr) == (loop == "while")


def test_solver_strings_name_the_newton_loop():
    from rebel_jax.envs import SOLVERS, parse_solver

    assert parse_solver("default") == SOLVERS["default"]
    assert parse_solver("default:trips") == dataclasses.replace(SOLVERS["default"], newton_loop="trips")
    assert parse_solver("2/5/noeulerdamp:unrolled").newton_loop == "unrolled"
    with pytest.raises(ValueError, match="NEWTON_LOOP"):
        parse_solver("default:fast")


def test_plain_cholesky_factors_and_solves_as_lapack_does():
    """``_mjx.plain_cholesky``'s factor and solve (plain JAX operations) against SciPy's LAPACK on a batch of
    random symmetric positive definite matrices of the quadruped's size (22 degrees of freedom)."""
    import scipy.linalg

    from rebel_jax.envs._mjx import _cho_factor, _cho_solve

    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, 22, 40))
    a = x @ x.transpose(0, 2, 1) + 0.1 * np.eye(22)
    b = rng.normal(size=(5, 22))
    u, lower = _cho_factor(jnp.asarray(a, jnp.float32))
    assert lower is False
    ref = np.stack([scipy.linalg.cholesky(m, lower=False) for m in a])
    np.testing.assert_allclose(u, ref, rtol=0, atol=1e-5 * np.abs(ref).max())
    solved = _cho_solve((u, False), jnp.asarray(b, jnp.float32))
    np.testing.assert_allclose(solved, np.linalg.solve(a, b[..., None])[..., 0], rtol=1e-4, atol=1e-4)


def test_cpu_physics_makes_no_lapack_call():
    """On the CPU the task's step traces MJX's Cholesky factorizations as plain JAX operations
    (``_mjx.plain_cholesky``): jaxlib 0.10.2's CPU LAPACK kernels can hang on large batches. MJX's own step,
    traced the same way outside the env, does call LAPACK, so the check can fail."""
    from mujoco import mjx

    env = make_env("walker_walk")
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    ours = jax.jit(env.step).lower(state, jnp.zeros(env.action_size)).as_text()
    mjxs = jax.jit(lambda d: mjx.step(env.sys, d)).lower(state.pipeline_state).as_text()
    assert "lapack" in mjxs and "lapack" not in ours
