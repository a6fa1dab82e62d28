"""Meta-World's tasks (rebel_jax.envs.metaworld) against data recorded from Meta-World 3.1.1 itself.

The reference (tests/data/metaworld/<task>.npz) was recorded by tests/data/metaworld/make_reference.py in a separate
environment with metaworld==3.1.1 and its mujoco==3.3.0: resets, and episodes under random actions and under
Meta-World's scripted policies (which succeed, so success states are covered). The tests put our environment in each
recorded MuJoCo state and compare what Meta-World returned there.
"""

from __future__ import annotations

import importlib.util
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx
from scipy import stats

from rebel_jax.config import ConfigError, EnvConfig
from rebel_jax.envs import METAWORLD_TASKS, make_env, metaworld

DATA = pathlib.Path(__file__).parent / "data" / "metaworld"
TASKS = ["drawer-open", "button-press", "door-open", "sweep-into", "window-open", "door-unlock", "hammer"]
STEPPED = ["drawer-open", "sweep-into"]  # the tasks whose JAX physics step runs (metaworld.STEP_REFUSED)
INFO_KEYS = ("near_object", "grasp_success", "grasp_reward", "in_place_reward", "obj_to_target")
# Info flags read from contact forces (sweep-into's grasp_success: both pads push on the object). MJX collides the
# pads' boxes with the object's box with its own algorithm, so where a pad barely touches, its contact force can be
# zero in one engine and positive in the other: at most 1% of the states may differ (1 of 250 measured).
CONTACT_FLAGS = {"sweep-into": ("grasp_success",)}
CONTACT_FLAG_MISMATCHES = 0.01
OBS_TOL = 1e-5
# Meta-World's rewards lie in [0, 10], so 1e-5 of their range; float32 carries about 7 significant digits, and the
# rewards' long-tail terms amplify the observation's float32 rounding near their bounds (1.9e-5 measured).
REWARD_TOL = 1e-5 * 10


def _f32(x) -> np.ndarray:
    return np.asarray(x, np.float32)


@pytest.fixture(scope="module")
def reference():
    return {task: dict(np.load(DATA / f"{task}.npz")) for task in TASKS}


@pytest.fixture(scope="module")
def envs():
    return {task: metaworld.MetaWorldEnv(task) for task in TASKS}


class _Resets(dict):
    """Each task's recorded episodes' resets, compiled at the first test that asks for the task's."""

    def __init__(self, envs, reference):
        super().__init__()
        self.envs, self.reference = envs, reference

    def __missing__(self, task):
        self[task] = _episodes(self.envs[task], self.reference[task])
        return self[task]


@pytest.fixture(scope="module")
def resets(envs, reference):
    return _Resets(envs, reference)


def _episodes(env, ref):
    """The reset of each recorded episode at Meta-World's draws: its state, and its info (the episode's goal,
    fingertip centre and constants) per recorded row."""
    draws = ref["episode_draws"]
    assert draws.shape[1] >= 2  # Meta-World's reset runs reset_model twice (sweep-into may draw again in each)
    return jax.jit(jax.vmap(env.reset_to))(_f32(draws[:, -1]), _f32(draws[:, 0]))


def _states_at(env, ref, rows, resets, chunk: int = 256):
    """Our states at the recorded rows (steps after a reset: t > 0), in the episodes that ``resets`` began; at most
    about ``chunk`` rows at a time (sweep-into's states each run MJX's collision and solver: 2,000 at once ask for
    25 GB), in chunks of equal size but one row (one or two programs)."""
    info = jax.tree.map(lambda x: x[ref["episode"][rows]], resets.info)
    episode = {k: info[k] for k in ("target_pos", "init_tcp", "body_pos", "consts")}
    at = jax.jit(jax.vmap(env.state_at))
    parts = []
    for take in np.array_split(np.arange(len(rows)), -(-len(rows) // chunk)):
        part = rows[take]
        parts.append(
            at(
                _f32(ref["qpos"][part]),
                _f32(ref["qvel"][part]),
                _f32(ref["mocap_pos"][part]),
                _f32(ref["mocap_quat"][part]),
                _f32(ref["qacc_warmstart"][part]),
                _f32(ref["obs"][part - 1, :18]),
                jax.tree.map(lambda x, take=take: x[take], episode),
                _f32(ref["action"][part]),
            )
        )
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)


def _compare_at_states(env, ref, rows, resets):
    state = _states_at(env, ref, rows, resets)
    obs_err = np.abs(np.asarray(state.obs) - ref["obs"][rows]).max()
    reward_err = np.abs(np.asarray(state.reward) - ref["reward"][rows]).max()
    assert obs_err <= OBS_TOL, obs_err
    assert reward_err <= REWARD_TOL, reward_err
    np.testing.assert_array_equal(np.asarray(state.info["success"]), ref["success"][rows])
    contact_flags = CONTACT_FLAGS.get(env.spec.name, ())
    for key in INFO_KEYS:  # flags (0 or 1) and the reward's terms
        ours, theirs = np.asarray(state.metrics[key]), ref[key][rows]
        if key in contact_flags:
            assert theirs.sum() > 0 and (ours != theirs).mean() <= CONTACT_FLAG_MISMATCHES, (
                key,
                (ours != theirs).sum(),
            )
        else:
            np.testing.assert_allclose(ours, theirs, atol=REWARD_TOL / 5, err_msg=key)
    return obs_err, reward_err


# sweep-into's states run MJX's collision and solver for the contact forces its info reads: their compile (about a
# minute on 2 cores) puts it in make test-heavy; make test checks its reset, its reset distribution and its hand here.
# The other tasks likewise (a reset compile each): make test compares drawer-open's states and reset here, and every
# task's reset distribution and hand reset below; make test-heavy compares every task.
AT_STATES = [t if t == "drawer-open" else pytest.param(t, marks=pytest.mark.heavy) for t in TASKS]


@pytest.mark.parametrize("task", AT_STATES)
def test_observation_reward_success_equal_metaworld_on_same_states(envs, reference, resets, task):
    """Every 8th recorded state (250 of the 2,000 after a reset; sweep-into, whose states run MJX's collision and
    solver for the contact forces its info reads: every 32nd, 63), random and scripted, successes among them."""
    ref = reference[task]
    rows = np.where(ref["t"] > 0)[0][:: 32 if metaworld.TASKS[task].contacts else 8]
    assert ref["success"][rows].sum() > 0 and (ref["success"][rows] == 0).sum() > 0
    _compare_at_states(envs[task], ref, rows, resets[task])


@pytest.mark.heavy
@pytest.mark.parametrize("task", TASKS)
def test_observation_reward_success_equal_metaworld_on_all_recorded_states(envs, reference, resets, task):
    """All 2,000 recorded states after a reset (make test checks every 8th)."""
    ref = reference[task]
    _compare_at_states(envs[task], ref, np.where(ref["t"] > 0)[0], resets[task])


@pytest.mark.parametrize("task", AT_STATES)  # each task's reset compile: drawer-open's in make test, all in -heavy
def test_reset_equals_metaworlds_at_the_same_draws(reference, resets, task):
    """The reset's state, observation (drawer-open: the hand one physics step back, the object at Meta-World's first
    draw), goal and fingertip centre, at the draws Meta-World made in each recorded reset."""
    ref, state = reference[task], resets[task]
    rows = np.where(ref["t"] == 0)[0]
    np.testing.assert_allclose(np.asarray(state.obs), ref["obs"][rows], atol=OBS_TOL)
    np.testing.assert_allclose(np.asarray(state.info["target_pos"]), ref["episode_target_pos"], atol=OBS_TOL)
    np.testing.assert_allclose(np.asarray(state.info["init_tcp"]), ref["episode_init_tcp"], atol=OBS_TOL)
    for field in ("qpos", "qvel", "mocap_pos", "mocap_quat"):
        np.testing.assert_allclose(np.asarray(getattr(state.pipeline_state, field)), ref[field][rows], atol=OBS_TOL)
    np.testing.assert_array_equal(np.asarray(state.reward), 0.0)


@pytest.mark.parametrize("task", TASKS)
def test_reset_distribution_matches_metaworlds(envs, reference, task):
    """1,000 of our reset draws against Meta-World's 1,000 recorded ones, per coordinate (KS). The goal is a function
    of the draw (drawer-open: an offset; button-press: a site of the moved body), which
    test_reset_equals_metaworlds_at_the_same_draws checks at Meta-World's own draws."""
    env, ref = envs[task], reference[task]
    keys = jax.random.split(jax.random.PRNGKey(0), 1000)
    ours = np.asarray(jax.vmap(env.draw)(keys))
    theirs = ref["reset_rand_vec"]
    for i in range(ours.shape[1]):
        if np.ptp(theirs[:, i]) == 0:  # a fixed coordinate
            np.testing.assert_allclose(ours[:, i], theirs[0, i], atol=1e-6, err_msg=f"draw[{i}]")
        else:
            p = stats.ks_2samp(ours[:, i], theirs[:, i]).pvalue
            assert p > 1e-3, f"draw[{i}]: KS p={p:.2g}"
    if task == "door-unlock":  # its obj_init_pos is the lock's position (checked through the goal at the draws)
        return
    placed = theirs[:, :3].copy()  # Meta-World's object is at the draw
    n = env.spec.object_qpos  # a free object at the draw's first n numbers (sweep-into: its x and y, at the height
    if n:  # where the hand's reset left it; hammer: its x, y and z)
        placed[:, n:] = env.hand_reset.qpos[9 + n : 12]
    np.testing.assert_allclose(ref["reset_obj_init_pos"], placed)


@pytest.mark.parametrize("task", TASKS)
def test_hand_reset_is_the_same_in_every_recorded_reset(envs, reference, task):
    """The arm's reset state does not depend on where the reset puts the object (HandReset's premise)."""
    ref = reference[task]
    rows = np.where(ref["t"] == 0)[0]
    env = envs[task]
    for field in ("qpos", "qvel", "mocap_pos", "mocap_quat"):
        theirs, ours = ref[field][rows], np.broadcast_to(getattr(env.hand_reset, field), ref[field][rows].shape).copy()
        n = env.spec.object_qpos
        if field == "qpos" and n:  # the object's position is the draw's (sweep-into: x and y; hammer: x, y, z)
            ours[:, 9 : 9 + n] = theirs[:, 9 : 9 + n]
        np.testing.assert_array_equal(theirs, ours)


def test_task_names_pixels_and_impl_refused_in_one_line():
    assert "metaworld_drawer-open" in METAWORLD_TASKS
    with pytest.raises(ValueError, match="metaworld_drawer-open") as typo:
        make_env("metaworld_drawer-opne")
    assert "\n" not in str(typo.value)
    with pytest.raises(ValueError, match="no pixel version") as pixels:
        make_env("metaworld_drawer-open_pixels")
    assert "\n" not in str(pixels.value)
    with pytest.raises(ValueError, match="unknown physics impl"):
        make_env("metaworld_drawer-open", impl="wrap")
    why = r"metaworld_button-press cannot step with impl='jax': MJX's JAX step .* run it with impl='warp'"
    with pytest.raises(ValueError, match=why) as refused:
        make_env("metaworld_button-press")
    assert "\n" not in str(refused.value)
    with pytest.raises(ConfigError, match="cannot step with impl='jax'"):
        EnvConfig(task="metaworld_button-press").validate()
    with pytest.raises(ConfigError, match="metaworld_drawer-open"):
        EnvConfig(task="metaworld_drawer-opne").validate()
    EnvConfig(task="metaworld_drawer-open", episode_length=500).validate()


@pytest.mark.parametrize("task", [t for t, why in metaworld.STEP_REFUSED["jax"].items() if "with boxes" in why])
def test_step_refused_where_mjx_lacks_the_models_collisions(envs, task):
    """The tasks whose step is refused for MJX's missing cylinder-box collision: MJX's JAX step cannot build their
    model, and their step stops in one line."""
    with pytest.raises(NotImplementedError, match=r"mjGEOM_CYLINDER, \S*mjGEOM_BOX\) collisions not implemented"):
        mjx.put_model(metaworld.mj_model(task))
    with pytest.raises(ValueError, match=f"metaworld_{task} cannot step with impl='jax': MJX's JAX step") as refused:
        envs[task].step(None, jnp.zeros(4))
    assert "\n" not in str(refused.value)


def test_spaces_and_time_step(envs):
    env = envs["drawer-open"]
    assert (env.observation_size, env.action_size) == (39, 4)
    assert env.dt == pytest.approx(0.0125)
    assert env.mujoco_model.opt.cone == 1 and env.mujoco_model.opt.iterations == 50  # elliptic, the XML's


def test_hidden_goal_is_zeros_and_reward_unchanged(reference, resets):
    """``goal_observable=False``: the observation's goal is zeros, as in the PbRL code bases, and the rest of the
    observation and the reward are unchanged (the reward reads the goal itself)."""
    ref = reference["drawer-open"]
    hidden = metaworld.MetaWorldEnv("drawer-open", goal_observable=False)
    rows = np.where(ref["t"] > 0)[0][::50]
    unseen = _states_at(hidden, ref, rows, resets["drawer-open"])
    np.testing.assert_array_equal(np.asarray(unseen.obs[:, 36:]), 0.0)
    np.testing.assert_allclose(np.asarray(unseen.obs[:, :36]), ref["obs"][rows, :36], atol=OBS_TOL)
    np.testing.assert_allclose(np.asarray(unseen.reward), ref["reward"][rows], atol=REWARD_TOL)


needs_warp = pytest.mark.skipif(importlib.util.find_spec("warp") is None, reason="needs warp-lang")


@pytest.fixture(scope="module")
def warp_envs():
    return {task: metaworld.MetaWorldEnv(task, impl="warp", worlds=125) for task in TASKS}


SUCCESS_MISMATCHES = {"jax": 0.01, "warp": 0.0}
"""The fraction of stepped states whose success may differ from Meta-World's: MJX's JAX step collides the gripper's
convex meshes with its own algorithm (1 of 125 may flip), Warp's as MuJoCo does."""


@pytest.mark.heavy
@pytest.mark.parametrize(
    "impl, task", [("jax", t) for t in STEPPED] + [pytest.param("warp", t, marks=needs_warp) for t in TASKS]
)
def test_one_control_step_lands_where_mujoco_does(request, benchmark_script, reference, resets, impl, task):
    """One control step (5 physics steps, float32) of MJX's JAX step (the tasks it runs) or MuJoCo Warp's (all seven)
    from every 16th recorded state, against MuJoCo 3.17's own step in float64 from the same state; and the success
    flags against Meta-World's.

    The reference is this MuJoCo, not the recording: MuJoCo 3.3 (Meta-World's) and 3.17 themselves differ by up to
    0.034 in qpos on these steps where the fingers push an object, and by a median 1.8e-4 on sweep-into
    (benchmarks/results/metaworld_fidelity.json, ``mujoco_3_17_float64``). Largest differences measured there: Warp
    median 4.0e-5 and largest 7.2e-3 (door-unlock's lock); the JAX step median 2.0e-5 (drawer-open) and largest
    6.4e-3 (sweep-into). Compiling the JAX step takes about 10 minutes on 2 CPU cores, hence make test-heavy.
    """
    env = request.getfixturevalue("envs" if impl == "jax" else "warp_envs")[task]
    ref = reference[task]
    rows = np.where(ref["t"] > 0)[0]
    rows = rows[(ref["t"][rows] < metaworld.EPISODE_LENGTH)][::16]
    stepped = jax.jit(jax.vmap(env.step))(_states_at(env, ref, rows, resets[task]), _f32(ref["action"][rows + 1]))
    theirs, _ = benchmark_script("metaworld_fidelity").mujoco_step(task, ref, rows)  # MuJoCo 3.17, float64
    qpos_err = np.abs(np.asarray(stepped.pipeline_state.qpos) - theirs).max(1)
    assert np.median(qpos_err) <= 1e-4 and qpos_err.max() <= 2e-2, (np.median(qpos_err), qpos_err.max())
    mismatched = np.asarray(stepped.info["success"]) != ref["success"][rows + 1]
    assert mismatched.mean() <= SUCCESS_MISMATCHES[impl], mismatched.sum()


@pytest.mark.heavy
@needs_warp
def test_warp_reads_sweep_intos_contact_forces_as_metaworld_does(reference, resets):
    """Under ``impl='warp'`` sweep-into's info reads its contact forces from MuJoCo Warp's own ``forward``
    (``metaworld._warp_touching``), not MJX's JAX one: at every 4th recorded state (500), the observation, reward
    and success equal Meta-World's, and the contact flag (``grasp_success``) differs on at most 1% of the states,
    as the JAX step's does (``CONTACT_FLAGS``)."""
    task = "sweep-into"
    ref = reference[task]
    rows = np.where(ref["t"] > 0)[0][::4]
    assert ref["grasp_success"][rows].sum() > 10  # states where both pads push the object are among them
    _compare_at_states(metaworld.MetaWorldEnv(task, impl="warp", worlds=len(rows)), ref, rows, resets[task])


@pytest.mark.heavy
@needs_warp
def test_warp_replays_metaworlds_drawer_open_episodes(reference):
    """drawer-open's recorded episodes (random actions, and Meta-World's scripted policy's) played open-loop from
    their resets with Warp's step: each episode's return within 2% of Meta-World's, and the scripted episodes
    succeed at as many steps to within 5% of the episode (with the casing's geoms left at the XML's place in Warp's
    data, the drawer was pushed out of its casing and no scripted step succeeded).

    drawer-open because MuJoCo 3.17 replays its episodes as MuJoCo 3.3 recorded them (qpos within 2e-3 at every
    checked step); where the fingers push a button, a door or a lock, MuJoCo 3.17's own open-loop replay drifts from
    the recording by up to 0.4 (button-press), and the replays are compared with it in
    benchmarks/metaworld_fidelity.py instead (``episodes_warp``)."""
    task = "drawer-open"
    ref = reference[task]
    n = len(ref["episode_draws"])
    env = metaworld.MetaWorldEnv(task, impl="warp", worlds=n)
    rows = [(ref["episode"] == e) & (ref["t"] > 0) for e in range(n)]
    actions = _f32(np.stack([ref["action"][r] for r in rows], 1))

    def body(state, action):
        state = jax.vmap(env.step)(state, action)
        return state, (state.reward, state.info["success"])

    reward, success = jax.jit(lambda s, a: jax.lax.scan(body, s, a)[1])(_episodes(env, ref), actions)
    ours = np.asarray(reward).sum(0)
    theirs = np.array([ref["reward"][r].sum() for r in rows])
    np.testing.assert_allclose(ours, theirs, rtol=0.02)
    steps = actions.shape[0]
    for e in np.where(ref["episode_scripted"])[0]:
        assert abs(np.asarray(success)[:, e].sum() - np.nansum(ref["success"][rows[e]])) <= 0.05 * steps


@pytest.mark.heavy
@needs_warp
def test_warp_step_under_nested_vmap_equals_the_flat_batch(reference, resets):
    """Warp's step of states vmapped twice, the inner axis over actions with the state unbatched there (as the
    final evaluation runs the policy's and random actions from one reset), equals the step of the same worlds in
    one flat batch. MJX broadcasts a Warp data's unbatched fields but not its model's, and Warp reads a batched
    model field of world ``w`` at ``w % batch``: before the env tied the moved body's position to the data's batch,
    every world past the first seed's stepped with another reset's drawer (5 seeds' final evaluation: success 0.22
    where the rounds' evaluation read 1.0)."""
    task = "drawer-open"
    env, ref = metaworld.MetaWorldEnv(task, impl="warp", worlds=8), reference[task]
    # The scripted episodes' steps where the fingers hold the handle (reward above 4): contact with the drawer.
    rows = np.where((ref["t"] > 0) & (ref["t"] < metaworld.EPISODE_LENGTH) & (ref["reward"] > 4.0))[0]
    first, second = (rows[ref["episode"][rows] == e] for e in np.unique(ref["episode"][rows])[:2])
    rows = np.array([first[0], second[0], first[20], second[20]])  # neighbouring worlds from different resets
    assert not np.allclose(*ref["episode_body_pos"][ref["episode"][rows[:2]]])  # two drawer positions
    state = _states_at(env, ref, rows, resets[task])
    actions = _f32(np.stack([ref["action"][rows + 1], -ref["action"][rows + 1]], 1))  # (4 states, 2 actions, 4)
    nested = jax.jit(jax.vmap(jax.vmap(env.step, in_axes=(None, 0))))(state, actions)
    flat_state = jax.tree.map(lambda x: jnp.repeat(x, 2, axis=0), state)
    flat = jax.jit(jax.vmap(env.step))(flat_state, actions.reshape(8, 4))
    np.testing.assert_allclose(
        np.asarray(nested.pipeline_state.qpos).reshape(8, -1), np.asarray(flat.pipeline_state.qpos), atol=1e-5
    )
    np.testing.assert_allclose(np.asarray(nested.obs).reshape(8, -1), np.asarray(flat.obs), atol=1e-5)
