"""The tasks as brax environments: the registry, brax's training wrappers on them, against our own code.

brax's wrappers are tested on the probe (compiles in seconds) against plain Python loops over our
own task. The registry test checks each registered MJX task's spec, solver and shapes without compiling;
one heavy test (``make test-heavy``: two walker compiles, about 40 s on 2 cores) rolls the registered
walker_walk, wrapped by brax, against our task.
"""

from __future__ import annotations

import brax.envs
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training

from rebel_jax.envs import (
    METAWORLD_TASKS,
    SOLVERS,
    TASKS,
    AutoResetWrapper,
    DMCEnv,
    PointProbe,
    State,
    make_env,
    not_runnable,
    probe,
    registry,
)
from rebel_jax.envs.metaworld import MetaWorldEnv

B = 3  # environments per batch
L = 3  # episode length of the episode tests


def _loop(env, keys, actions) -> dict[str, np.ndarray]:
    """Each environment alone, step by step in Python: (steps, envs, ...) arrays of every step's state."""
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    rows = []
    for i, key in enumerate(keys):
        state, states = reset(key), []
        for action in actions[:, i]:
            state = step(state, action)
            states.append(state)
        rows.append(states)
    return {
        "obs": np.array([[s.obs for s in r] for r in rows]).swapaxes(0, 1),
        "reward": np.array([[s.reward for s in r] for r in rows]).swapaxes(0, 1),
        "done": np.array([[s.done for s in r] for r in rows]).swapaxes(0, 1),
        "truncation": np.array([[s.info["truncation"] for s in r] for r in rows]).swapaxes(0, 1),
        "steps": np.array([[s.info["steps"] for s in r] for r in rows]).swapaxes(0, 1),
        "distance": np.array([[s.metrics["distance"] for s in r] for r in rows]).swapaxes(0, 1),
    }


def _rollout(env, key, actions) -> tuple[State, State]:
    """A batched env's reset and its states after each action, (steps, envs, ...), in one compiled scan."""

    def run(key, actions):
        first = env.reset(key)
        return first, jax.lax.scan(lambda s, a: (env.step(s, a),) * 2, first, actions)[1]

    return jax.jit(run)(key, actions)


def _actions(steps: int, size: int, seed: int = 1) -> jax.Array:
    return jax.random.uniform(jax.random.PRNGKey(seed), (steps, B, size), minval=-1.5, maxval=1.5)


def test_every_task_is_registered_with_brax_without_a_time_limit():
    assert State is brax.envs.State  # one State type: ours is brax's
    names = registry.brax_names()
    assert set(names) == {f"rebel_{t}" for t in (*TASKS, *METAWORLD_TASKS)} | {"rebel_probe_point"}
    traced = set()  # one reset traced per physics model (walker, cheetah, quadruped): a trace takes seconds
    for task in TASKS:
        env = brax.envs.get_environment(f"rebel_{task}")
        assert isinstance(env, brax.envs.Env) and isinstance(env, DMCEnv)
        assert env.spec is TASKS[task] and env.solver == SOLVERS["default"] and env.episode_length is None
        ours = make_env(task)
        assert (env.observation_size, env.action_size, env.dt) == (ours.observation_size, ours.action_size, ours.dt)
        model = getattr(TASKS[task].xml, "func", TASKS[task].xml)  # quadruped's is a partial per speed
        if model not in traced:
            traced.add(model)
            state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))  # traced, not compiled
            assert isinstance(state, brax.envs.State) and state.obs.shape == (ours.observation_size,)
            assert state.info == {}  # the step count is EpisodeWrapper's
    assert len(traced) == 3
    assert brax.envs.get_environment("rebel_cheetah_run", solver="dm_control").solver == SOLVERS["dm_control"]
    for task in METAWORLD_TASKS:
        if why := not_runnable(task):  # its JAX step is refused, in one line; it runs with impl='warp'
            with pytest.raises(ValueError, match="impl='warp'"):
                brax.envs.get_environment(f"rebel_{task}")
            assert "\n" not in why
            continue
        env = brax.envs.get_environment(f"rebel_{task}")
        assert isinstance(env, MetaWorldEnv) and env.episode_length is None and env.goal_observable
        state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
        assert state.obs.shape == (39,) and "steps" not in state.info and "success" in state.info
        assert not brax.envs.get_environment(f"rebel_{task}", goal_observable=False).goal_observable
    point = brax.envs.get_environment("rebel_probe_point")
    assert isinstance(point, PointProbe) and isinstance(point, brax.envs.Env) and point.episode_length is None


def test_brax_episode_and_vmap_wrappers_equal_our_episode_end_stepped_one_by_one():
    """``brax.envs.create`` (EpisodeWrapper inside VmapWrapper) on the registered probe, past the time limit."""
    key, actions = jax.random.PRNGKey(0), _actions(L + 2, 2)
    wrapped = brax.envs.create("rebel_probe_point", episode_length=L, auto_reset=False, batch_size=B)
    assert isinstance(wrapped, training.VmapWrapper) and isinstance(wrapped.env, training.EpisodeWrapper)
    first, states = _rollout(wrapped, key, actions)
    # VmapWrapper splits the key into B, as our trainer does: the same keys give the same episodes.
    ref = _loop(make_env("probe_point", episode_length=L), jax.random.split(key, B), np.asarray(actions))
    np.testing.assert_allclose(states.obs, ref["obs"], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(states.reward, ref["reward"], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(states.done, ref["done"])
    np.testing.assert_array_equal(states.info["truncation"], ref["truncation"])
    np.testing.assert_array_equal(states.info["steps"], ref["steps"])
    assert ref["done"][L - 2].max() == 0 and ref["done"][L - 1].min() == 1  # the limit is inside the test
    # EpisodeWrapper's episode sums: the step after a done one starts a new sum.
    for name, ours in [("sum_reward", ref["reward"]), ("distance", ref["distance"])]:
        total, previous_done = np.zeros(B), np.zeros(B)
        for t in range(L + 2):
            total = total * (1 - previous_done) + ours[t]
            previous_done = ref["done"][t]
            np.testing.assert_allclose(states.info["episode_metrics"][name][t], total, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(states.info["episode_metrics"]["length"][L - 1], L)
    np.testing.assert_array_equal(first.info["steps"], 0)


def test_vmap_wrapper_equals_each_env_stepped_alone():
    """brax's VmapWrapper, as the trainer uses it, on our task with its own time limit: every field."""
    key, actions = jax.random.PRNGKey(4), _actions(L + 1, 2, seed=5)
    env = make_env("probe_point", episode_length=L)
    first, states = _rollout(training.VmapWrapper(env, batch_size=B), key, actions)
    keys = jax.random.split(key, B)
    for i in range(B):
        alone = jax.jit(env.reset)(keys[i])
        jax.tree.map(lambda a, b, i=i: np.testing.assert_allclose(a[i], b, rtol=1e-6, atol=1e-7), first, alone)
        for t in range(L + 1):
            alone = jax.jit(env.step)(alone, actions[t, i])
            jax.tree.map(
                lambda a, b, i=i, t=t: np.testing.assert_allclose(a[t, i], b, rtol=1e-6, atol=1e-7), states, alone
            )
    assert states.info["steps"].dtype == jnp.int32  # our task's own count, untouched by the wrapper


def test_brax_auto_reset_repeats_the_first_state_where_ours_draws_a_fresh_one():
    """Why the tasks keep our AutoResetWrapper: brax's would fix each env's start state for the whole run."""
    episodes = 4
    actions = _actions(L * episodes, 2, seed=2)
    theirs = brax.envs.create("rebel_probe_point", episode_length=L, auto_reset=True, batch_size=B)
    first, states = _rollout(theirs, jax.random.PRNGKey(0), actions)
    ours_first, ours = _rollout(
        AutoResetWrapper(make_env("probe_point", episode_length=L), B), jax.random.PRNGKey(0), actions
    )
    ends = np.arange(L - 1, L * episodes, L)  # the steps that end an episode
    np.testing.assert_array_equal(states.done[ends], 1.0)
    np.testing.assert_array_equal(ours.done[ends], 1.0)
    # brax: every episode restarts at the env's first reset state.
    np.testing.assert_array_equal(states.obs[ends], np.broadcast_to(first.obs, states.obs[ends].shape))
    # ours: each restart is a new draw from the reset distribution (positions in [-1, 1]^2, at rest).
    starts = np.concatenate([ours_first.obs[None], ours.obs[ends]])
    np.testing.assert_array_equal(starts[..., 2:], 0.0)
    assert np.all(np.abs(starts[..., :2]) <= 1.0)
    assert len(np.unique(starts[..., :2].reshape(-1, 2), axis=0)) == (episodes + 1) * B
    # Ours keeps the episode's last observation, and the reward of the step that reached it.
    np.testing.assert_array_equal(ours.info["steps"][ends], 0)
    np.testing.assert_allclose(ours.reward[ends], probe.reward_of(ours.info["final_obs"][ends][..., :2]), rtol=1e-6)
    assert not np.allclose(ours.info["final_obs"][ends], ours.obs[ends])


@pytest.mark.heavy
@pytest.mark.parametrize("task", ["walker_walk"])
def test_registered_mjx_task_wrapped_by_brax_equals_our_task(task):
    """``brax.envs.create("rebel_walker_walk", ...)`` against ``make_env("walker_walk")``: same keys, same actions."""
    key, actions = jax.random.PRNGKey(7), _actions(L, 6, seed=8)
    wrapped = brax.envs.create(f"rebel_{task}", episode_length=L - 1, auto_reset=False, batch_size=B)
    first, states = _rollout(wrapped, key, actions)
    ours_first, ours = _rollout(training.VmapWrapper(make_env(task, episode_length=L - 1), B), key, actions)
    for a, b in [(first, ours_first), (states, ours)]:
        np.testing.assert_allclose(a.pipeline_state.qpos, b.pipeline_state.qpos, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(a.pipeline_state.qvel, b.pipeline_state.qvel, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(a.obs, b.obs, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(a.reward, b.reward, rtol=1e-5, atol=1e-6)
        assert set(a.metrics) == set(b.metrics)
        for name in b.metrics:
            np.testing.assert_allclose(a.metrics[name], b.metrics[name], rtol=1e-5, atol=1e-5, err_msg=name)
        np.testing.assert_array_equal(a.done, b.done)
        np.testing.assert_array_equal(a.info["truncation"], b.info["truncation"])
        np.testing.assert_array_equal(a.info["steps"], b.info["steps"])
    np.testing.assert_array_equal(ours.done[:, 0], [0.0, 1.0, 1.0])  # the time limit is inside the test
    assert not np.allclose(ours.obs[-1, 0], ours.obs[-1, 1])  # distinct keys, distinct episodes
