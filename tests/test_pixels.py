"""Pixel tasks: observation shape and dtype, action repeat, the kept state, the frame stack across auto-reset.

The wrapper's behaviour is tested on a one-capsule MJX task built with the same ``DMCEnv`` code
(no contacts or constraints, so it compiles in seconds); the real pixel tasks are traced
(``jax.eval_shape``), not compiled.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.envs import PIXEL_TASKS, TASKS, AutoResetWrapper, PixelEnv, dmc, make_env, render

_TINY_XML = """
<mujoco>
  <visual><headlight ambient=".4 .4 .4" diffuse=".8 .8 .8" specular=".1 .1 .1"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".1 .2 .3" rgb2=".2 .3 .4" width="8" height="8"/>
    <material name="grid" texture="grid" texrepeat="1 1" texuniform="true" reflectance=".2"/>
    <material name="self" rgba=".7 .5 .3 1"/>
  </asset>
  <option timestep="0.05" gravity="0 0 0"><flag contact="disable" constraint="disable"/></option>
  <worldbody>
    <geom name="floor" type="plane" size="20 .8 .2" material="grid"/>
    <body name="torso" pos="0 0 .5">
      <light name="light" pos="0 0 2" mode="trackcom"/>
      <camera name="side" pos="0 -2 0" quat="0.707 0.707 0 0" mode="trackcom"/>
      <joint name="rootx" type="slide" axis="1 0 0"/>
      <joint name="rootz" type="slide" axis="0 0 1" limited="true" range="-.2 .2"/>
      <geom name="torso" type="capsule" fromto="-.3 0 0 .3 0 0" size=".05" mass=".5" material="self"/>
    </body>
  </worldbody>
  <actuator><motor joint="rootx" gear="20" ctrlrange="-1 1" ctrllimited="true"/></actuator>
</mujoco>
"""


def _tiny_task() -> dmc.TaskSpec:
    def reward(d):
        return d.qvel[0], {"speed": d.qvel[0]}

    return dmc.TaskSpec(
        "tiny", lambda: _TINY_XML, None, 2, 0, 4, lambda d: jnp.concatenate([d.qpos, d.qvel]), reward, False
    )


@pytest.fixture(scope="module")
def tiny_run(request):
    """Two agent steps of two batched tiny pixel tasks whose episodes last 2 agent steps (4 frames)."""
    mp = pytest.MonkeyPatch()
    mp.setitem(dmc.TASKS, "tiny", _tiny_task())
    request.addfinalizer(mp.undo)
    env = PixelEnv(dmc.make_env("tiny", episode_length=4), action_repeat=2, frames=3, size=8, shadows=False)
    batched = AutoResetWrapper(env, num_envs=2)
    step = jax.jit(batched.step)
    states = [jax.jit(batched.reset)(jax.random.PRNGKey(0))]
    for _ in range(2):
        states.append(step(states[-1], jnp.full((2, 1), ACTION)))
    frames = [jax.jit(jax.vmap(env.render))(s) for s in states]  # one compile: same shapes
    return env, states, frames


ACTION = 0.7


def test_every_task_the_camera_can_draw_has_a_pixel_task():
    drawn = set(render.SUPPORTED_GEOMS)  # the geom types the pure-JAX camera draws
    drawable = [t for t in TASKS if set(np.unique(dmc.mj_model(t).geom_type).tolist()) <= drawn]
    assert "walker_walk" in drawable and "quadruped_walk" not in drawable
    assert sorted(PIXEL_TASKS) == sorted(f"{t}_pixels" for t in drawable)
    with pytest.raises(ValueError, match="walker_walk_pixels"):
        make_env("walker_walk_pixel")


@pytest.mark.parametrize("task", ["walker_walk_pixels", "cheetah_run_pixels"])
def test_pixel_task_observation_shape_and_dtype(task):
    env = make_env(task)
    state_task = make_env(task.removesuffix("_pixels"))
    assert isinstance(env, PixelEnv) and env.action_size == 6
    assert env.observation_shape == (84, 84, 9) and env.observation_size == 84 * 84 * 9
    assert env.episode_length == 500 and env.dt == pytest.approx(2 * state_task.dt)
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    nxt = jax.eval_shape(env.step, state, jnp.zeros(6))
    for s in (state, nxt):
        assert s.obs.shape == (84, 84, 9) and s.obs.dtype == jnp.uint8
        assert s.info["state_obs"].shape == (state_task.observation_size,)
        assert s.reward.shape == () and s.done.shape == ()


def test_reset_stacks_the_first_frame_and_keeps_the_state(tiny_run):
    env, (state, *_), (frame, *_) = tiny_run
    np.testing.assert_array_equal(state.obs, np.tile(frame, (1, 1, 1, 3)))
    d = state.pipeline_state
    np.testing.assert_allclose(state.info["state_obs"], np.concatenate([d.qpos, d.qvel], -1))
    assert not np.array_equal(state.info["state_obs"][0], state.info["state_obs"][1])  # two resets


def test_step_repeats_the_action_and_keeps_the_true_state(tiny_run):
    env, (state, nxt, _), (_, frame, _) = tiny_run
    # No gravity, contacts or damping: each physics step adds dt * gear * action / mass to the speed.
    m = env.mj_model
    dv = m.opt.timestep * 20.0 * ACTION / m.body_mass[1]
    substeps = env.env.spec.n_substeps
    np.testing.assert_allclose(nxt.pipeline_state.qvel[:, 0], 2 * substeps * dv, rtol=1e-4)
    # The reward is the sum over the repeated frames of the speed.
    np.testing.assert_allclose(nxt.reward, substeps * dv + 2 * substeps * dv, rtol=1e-4)
    np.testing.assert_array_equal(nxt.info["steps"], 2)  # environment frames
    d = nxt.pipeline_state
    np.testing.assert_allclose(nxt.info["state_obs"], np.concatenate([d.qpos, d.qvel], -1))
    # The stack shifts by one frame and ends with the frame of the new state.
    np.testing.assert_array_equal(nxt.obs[..., :6], state.obs[..., 3:])
    np.testing.assert_array_equal(nxt.obs[..., 6:], frame)
    assert nxt.obs.dtype == jnp.uint8 and nxt.obs.shape == (2, 8, 8, 9)
    assert not np.array_equal(nxt.obs[..., 6:], nxt.obs[..., :3]), "the capsule moved in the image"


def test_frame_stack_restarts_at_the_auto_reset(tiny_run):
    env, (_, first, last), (*_, fresh) = tiny_run
    assert env.episode_length == 2  # 4 environment frames
    assert np.all(first.done == 0) and np.all(last.done == 1)
    # The episode's last stack continues the previous one ...
    np.testing.assert_array_equal(last.info["final_obs"][..., :6], first.obs[..., 3:])
    # ... and the returned observation is a fresh episode's first frame, three times.
    np.testing.assert_array_equal(last.obs, np.tile(fresh, (1, 1, 1, 3)))
    assert not np.array_equal(last.obs, last.info["final_obs"])
    np.testing.assert_array_equal(last.info["steps"], 0)
    np.testing.assert_allclose(last.info["state_obs"][:, 2:], 0.0)  # a fresh episode starts at rest
