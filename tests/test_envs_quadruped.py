"""quadruped_walk and quadruped_run against dm_control 1.0.50: model, observation, reward, sensors, reset, episode.

The reference is dm_control's own environment (``suite.load("quadruped", ...)``, float64 MuJoCo). States come
from dm_control episodes under uniformly random actions; our steps start from the same physics states (qpos,
qvel, actuator activations, warm start) with the same controls.

- On the same state, every observation entry that depends on positions and velocities (joint angles and
  velocities, activations, velocimeter, upright, gyro) and the reward agree within 1e-5.
- The accelerometer and the toe force and torque sensors depend on the step's accelerations and constraint
  forces: they are compared after one control step from the same state and controls, with dm_control's solver
  settings (float32 MJX against float64 MuJoCo, so to a relative 1e-3 on average).
- The reset: the closed-form height equals dm_control's search on the same orientations, and the distribution
  of the reset observation and height matches dm_control's (KS tests).

Compiles (2 CPU cores, ``make test``'s fast compiles): the batched reset (about 15 s), the batched step with the
default and with dm_control's solver (25-30 s each) and the observation (a few seconds), all at one batch size.
``make test-heavy`` also steps a whole 1000-step dm_control episode side by side.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from scipy import stats

from rebel_jax.envs import TASKS, make_env, models, quadruped
from rebel_jax.envs.dmc import mj_model

suite = pytest.importorskip("dm_control.suite")
dm_quadruped = pytest.importorskip("dm_control.suite.quadruped")

B = 256  # states per batch: every compiled function is built for this size once
TASK = "quadruped_walk"  # walk and run share the physics (checked below); run's own step is not compiled
QUADRUPEDS = ["quadruped_walk", "quadruped_run"]

# The observation's parts (dm_control's order) and which of them a physics state alone determines.
PARTS = {
    "joint_angles": slice(0, 16),
    "joint_velocities": slice(16, 32),
    "activations": slice(32, 44),
    "torso_velocity": slice(44, 47),
    "torso_upright": slice(47, 48),
    "accelerometer": slice(48, 51),
    "gyro": slice(51, 54),
    "force_torque": slice(54, 78),
}
STATE_PARTS = ["joint_angles", "joint_velocities", "activations", "torso_velocity", "torso_upright", "gyro"]
ACC_PARTS = ["accelerometer", "force_torque"]


def _dm_env(task: str, seed: int):
    return suite.load("quadruped", task.split("_", 1)[1], task_kwargs={"random": seed})


def _dm_obs(observation) -> np.ndarray:
    return np.concatenate([np.atleast_1d(v) for v in observation.values()])


def _control(actions: np.ndarray, ctrlrange: np.ndarray) -> np.ndarray:
    """dm_control's controls of actions in [-1, 1] (what :meth:`DMCEnv.control` computes), in float64."""
    low, high = ctrlrange.T
    return low + (np.asarray(actions, np.float64) + 1) / 2 * (high - low)


def _trajectory(task: str, seed: int, steps: int) -> dict[str, np.ndarray]:
    """A dm_control episode's first ``steps`` transitions under uniform random actions: each state (qpos, qvel,
    act, warm start), its action (in [-1, 1]), the next observation and reward, and the floor's contacts."""
    env, rng = _dm_env(task, seed), np.random.default_rng(seed)
    env.reset()
    m, d = env.physics.model, env.physics.data
    out = {k: [] for k in ("qpos", "qvel", "act", "warm", "action", "obs", "reward")}
    touching = set()
    for _ in range(steps):
        for name, value in (("qpos", d.qpos), ("qvel", d.qvel), ("act", d.act), ("warm", d.qacc_warmstart)):
            out[name].append(value.copy())
        action = rng.uniform(-1, 1, m.nu).astype(np.float32)
        ts = env.step(_control(action, m.actuator_ctrlrange))
        out["action"].append(action), out["obs"].append(_dm_obs(ts.observation)), out["reward"].append(ts.reward)
        touching |= {m.id2name(int(g), "geom").split("_")[0] for c in d.contact[: d.ncon] for g in (c.geom1, c.geom2)}
    return {**{k: np.array(v) for k, v in out.items()}, "touching": touching}


@pytest.fixture(scope="module")
def states():
    """B states of two dm_control episodes, B/2 transitions each: one on its toes (seed 0), one on its back (seed 4;
    a random policy's episodes are one or the other, depending on the initial orientation)."""
    parts = [_trajectory(TASK, seed, B // 2) for seed in (0, 4)]
    joined = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "touching"}
    # The states exercise the contacts of a random policy: toes, shins, thighs and the torso on the floor.
    assert {"floor", "toe", "shin", "thigh", "torso"} <= set.union(*(p["touching"] for p in parts))
    return joined


def _batch(env, states: dict[str, np.ndarray]):
    """MJX data (batched) holding the physics states, from the env's host template (nothing compiled)."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    n = len(states["qpos"])
    data = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (n, *np.shape(x))), env._data0)
    return data.replace(
        qpos=f32(states["qpos"]), qvel=f32(states["qvel"]), act=f32(states["act"]), qacc_warmstart=f32(states["warm"])
    )


def _parts(obs: np.ndarray, names: list[str]) -> np.ndarray:
    return np.concatenate([np.asarray(obs)[..., PARTS[n]] for n in names], axis=-1)


# -- the model and the task's constants --------------------------------------------------------------------------


@pytest.mark.parametrize("task", QUADRUPEDS)
def test_model_names_and_sensors_are_dm_controls(task):
    """Beyond the compiled fields (tests/test_envs_dm_control.py): every named element in dm_control's order, and
    the sensor addresses and joints the observation reads."""
    ours, ref = mj_model(task), _dm_env(task, 0).physics.model._model
    for kind in ("body", "geom", "joint", "site", "sensor", "actuator", "tendon", "equality", "camera"):
        obj = getattr(mujoco.mjtObj, f"mjOBJ_{kind.upper()}")
        count = getattr(ref, {"equality": "neq", "camera": "ncam", "joint": "njnt"}.get(kind, f"n{kind}"))
        names = lambda m, obj=obj, count=count: [mujoco.mj_id2name(m, obj, i) for i in range(count)]  # noqa: E731
        assert names(ours) == names(ref), kind
    for field in (
        "tendon_adr",
        "tendon_num",
        "wrap_objid",
        "wrap_prm",
        "eq_type",
        "eq_obj1id",
        "eq_solref",
        "eq_solimp",
    ):
        np.testing.assert_allclose(getattr(ours, field), getattr(ref, field), err_msg=field)
    for field in ("actuator_dyntype", "actuator_dynprm", "actuator_gainprm", "actuator_biasprm", "actuator_trntype"):
        np.testing.assert_allclose(getattr(ours, field), getattr(ref, field), err_msg=field)
    adr = lambda name: ours.sensor_adr[mujoco.mj_name2id(ours, mujoco.mjtObj.mjOBJ_SENSOR, name)]  # noqa: E731
    assert quadruped._ACCELEROMETER.start == adr("imu_accel") and quadruped._GYRO.start == adr("imu_gyro")
    assert quadruped._VELOCIMETER.start == adr("velocimeter")
    toes = [f"{kind}_toe_{leg}" for kind in ("force", "torque") for leg, _, _ in models.QUADRUPED_LEGS]
    assert [adr(n) for n in toes] == list(range(quadruped._TOE_FORCE_TORQUE.start, quadruped._TOE_FORCE_TORQUE.stop, 3))
    hinges = np.nonzero(ours.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)[0]
    assert list(ours.jnt_qposadr[hinges]) == list(range(*quadruped._HINGE_QPOS.indices(ours.nq)))
    assert list(ours.jnt_dofadr[hinges]) == list(range(*quadruped._HINGE_QVEL.indices(ours.nv)))
    env = make_env(task)
    assert (env.observation_size, env.action_size, env.episode_length) == (78, 12, 1000)
    assert env.dt == pytest.approx(_dm_env(task, 0).control_timestep()) and env.spec.n_substeps == 4


@pytest.mark.parametrize("seeds,episodes", [((0, 4), 1), pytest.param((1,), 100, marks=pytest.mark.heavy)])
def test_left_out_pairs_never_near_in_dm_control(seeds, episodes):
    """The simulated model leaves out exactly the geom pairs between the task's ``never_near`` bodies (the lower legs
    against the torso and eyes: 36 of MJX's 159), and in dm_control those pairs never reach MuJoCo's narrow phase:
    over episodes of uniformly random actions (``make test``: one on its toes, one on its back; ``make test-heavy``:
    100 episodes, 100,000 control steps), its contact filter, called for every pair whose bounding boxes overlap,
    saw none of them (while it saw thousands of others)."""
    from mujoco.mjx._src import collision_driver

    full, simulated = mj_model(TASK), mj_model(TASK, simulated=True)
    pairs = lambda m: {tuple(p[:2]) for v in collision_driver._geom_groups(m).values() for p in v}  # noqa: E731
    body = lambda g: mujoco.mj_id2name(full, mujoco.mjtObj.mjOBJ_BODY, full.geom_bodyid[g])  # noqa: E731
    never = {frozenset(b) for b in TASKS[TASK].never_near}
    left_out = pairs(full) - pairs(simulated)
    assert pairs(simulated) <= pairs(full) and len(left_out) == 36
    assert left_out == {p for p in pairs(full) if frozenset(map(body, p)) in never}
    near, seen = [], [0]

    def contact_filter(m, d, g1, g2):
        seen[0] += 1
        if frozenset((body(g1), body(g2))) in never:
            near.append((g1, g2))
        return 0  # filter nothing

    mujoco.set_mjcb_contactfilter(contact_filter)
    try:
        for seed in seeds:
            env, rng = _dm_env(TASK, seed), np.random.default_rng(seed)
            for _ in range(episodes):
                ts = env.reset()
                while not ts.last():
                    ts = env.step(_control(rng.uniform(-1, 1, 12), env.physics.model.actuator_ctrlrange))
    finally:
        mujoco.set_mjcb_contactfilter(None)
    assert not near and seen[0] > 10_000


def test_run_is_walk_with_its_own_floor_and_speed():
    """quadruped_run's physics is quadruped_walk's (the floor's size only draws it), so its step is not compiled
    here; its observation and reward are tested on the same states below."""
    walk, run = (mj_model(t) for t in QUADRUPEDS)
    floor = mujoco.mj_name2id(walk, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    assert walk.geom_size[floor, 0] == 10 and run.geom_size[floor, 0] == 100  # 20 s times 0.5 and 5 m/s
    run.geom_size[floor] = walk.geom_size[floor]
    for field in ("body_mass", "body_inertia", "geom_size", "geom_friction", "dof_damping", "actuator_gainprm"):
        np.testing.assert_array_equal(getattr(run, field), getattr(walk, field), err_msg=field)
    a, b = TASKS["quadruped_walk"], TASKS["quadruped_run"]
    assert dataclasses.replace(b, name=a.name, xml=a.xml, reward_fn=a.reward_fn) == a


def test_actions_in_minus_one_to_one_span_each_control_range():
    """dmc2gym's and DrQ-v2's mapping: -1 and 1 to the ends of each range; the identity where ranges are [-1, 1]."""
    quad, walker = make_env(TASK), make_env("walker_walk")
    low, high = mj_model(TASK).actuator_ctrlrange.T
    for action, expected in ((-1.0, low), (1.0, high), (0.0, (low + high) / 2)):
        np.testing.assert_allclose(quad.control(jnp.full(12, action)), expected, rtol=1e-6, atol=1e-7)
    assert np.any(high != 1) and np.any(low != -1)  # the quadruped's lift and extend ranges
    x = jnp.linspace(-1, 1, 6)
    assert walker.control(x) is x


# -- the reset --------------------------------------------------------------------------------------------------


def test_reset_height_equals_dm_controls_search():
    """The closed form against ``_find_non_contacting_height`` (MuJoCo's collision detection at each cm), on 300
    orientations; and the zero pose has no self-contact, which the closed form assumes."""
    env = _dm_env(TASK, 0)
    physics = env.physics
    geoms = quadruped._body_geoms(mj_model(TASK))
    height = jax.jit(jax.vmap(lambda q: quadruped.non_contacting_height(geoms, quadruped._quat_to_mat(q))))
    rng = np.random.RandomState(0)
    quats = rng.randn(300, 4)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    ref = []
    for q in quats:
        dm_quadruped._find_non_contacting_height(physics, q)
        ref.append(physics.named.data.qpos["root"][2])
    np.testing.assert_allclose(height(jnp.asarray(quats, jnp.float32)), ref, rtol=0, atol=1e-6)
    assert np.ptp(ref) > 0.3  # from lying on its back to standing on its toes
    with physics.reset_context():
        physics.named.data.qpos["root"][2] = 5.0  # far above the floor, joints at zero
    assert physics.data.ncon == 0


def test_reset_matches_dm_controls_distribution(compiled_env):
    """KS tests on the reset observation (its only random entry is the torso's uprightness) and height; every
    other entry is dm_control's: the zero pose at rest in free fall (no velocity, acceleration or contact force)."""
    reset = compiled_env(TASK).batch_reset(jax.random.split(jax.random.PRNGKey(1), B))
    ours, heights = np.asarray(reset.obs), np.asarray(reset.pipeline_state.qpos[:, 2])
    env = _dm_env(TASK, 1)
    ref, ref_heights = [], []
    for _ in range(B):
        ref.append(_dm_obs(env.reset().observation))
        ref_heights.append(env.physics.named.data.qpos["root"][2])
    ref = np.array(ref)
    constant = [i for i in range(ref.shape[1]) if i != PARTS["torso_upright"].start]
    assert np.abs(ref[:, constant]).max() < 1e-9
    np.testing.assert_allclose(ours[:, constant], ref[:, constant], atol=1e-5)
    for name, a, b in (("upright", ours[:, 47], ref[:, 47]), ("height", heights, ref_heights)):
        p = stats.ks_2samp(a, b).pvalue
        assert p > 1e-3, f"reset {name} distribution differs from dm_control's (KS p={p:.2g})"
    # The height is the first 1 cm grid point at which the pose touches nothing, as dm_control's search finds it.
    steps = heights / quadruped.HEIGHT_STEP
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-3)
    np.testing.assert_array_equal(reset.info["steps"], 0)


# -- observation and reward on the same states; one step from the same states -------------------------------------


@pytest.mark.parametrize("task", QUADRUPEDS)
def test_observation_and_reward_equal_dm_control_on_same_states(compiled_env, states, task):
    """Within 1e-5 on every entry that the physics state determines, and on the reward (``Move``: upright times
    move, with the task's speed)."""
    ref, obs_ref, reward_ref = _dm_env(task, 0), [], []
    for q, v, act in zip(states["qpos"], states["qvel"], states["act"], strict=True):
        with ref.physics.reset_context():
            ref.physics.data.qpos[:], ref.physics.data.qvel[:], ref.physics.data.act[:] = q, v, act
        obs_ref.append(_dm_obs(ref.task.get_observation(ref.physics)))
        reward_ref.append(ref.task.get_reward(ref.physics))
    c = compiled_env(task)
    ours = c.observe(_batch(c.env, states), jnp.zeros(B, jnp.int32), jnp.zeros(B))
    np.testing.assert_allclose(_parts(ours.obs, STATE_PARTS), _parts(np.array(obs_ref), STATE_PARTS), rtol=0, atol=1e-5)
    np.testing.assert_allclose(ours.reward, reward_ref, rtol=0, atol=1e-5)
    assert 0.05 < np.mean(np.array(reward_ref) > 0) and np.ptp(reward_ref) > 0.1  # rewards of every kind


@pytest.mark.parametrize(
    "solver,mean_tol,max_tol,reward_tol",
    [
        # make test-heavy, both: the step's compile (make test compares the observation and reward at the same states
        # and the reset distribution with dm_control's); the dm_control case checks the same code more tightly
        pytest.param("dm_control", 1e-4, 1e-2, 1e-5, marks=pytest.mark.heavy),
        pytest.param("default", 1e-2, 5.0, 0.05, marks=pytest.mark.heavy),
    ],
)
def test_one_control_step_matches_dm_control(compiled_env, states, solver, mean_tol, max_tol, reward_tol):
    """From the same B states and controls, one control step (4 physics steps) lands where dm_control's does, and
    its accelerometer and toe force and torque sensors read what dm_control's last substep computed.

    Errors are relative to max(1, |value|). With dm_control's solver settings they are float32's (measured: mean
    1e-5 and largest 2e-3 on the sensors, largest 2e-4 elsewhere, rewards within 8e-6; in float64 MJX equals
    MuJoCo to 1e-11). The default solver stops after 4 Newton iterations, so on contact-rich steps velocities and
    sensors carry its error (measured: mean 4e-3, largest 3 on a toe torque, rewards within 7e-3; walker's in
    BENCHMARKS.md, "Choice of solver"). The capsule-plane contacts needed MuJoCo's contact frames
    (``_mjx.mujoco_contact_frames``): with MJX's, this test failed at dm_control's settings (largest error 1.7).
    """
    c = compiled_env(TASK, solver)
    start = compiled_env(TASK).observe(_batch(c.env, states), jnp.zeros(B, jnp.int32), jnp.zeros(B))
    nxt = c.batch_step(start, jnp.asarray(states["action"]))
    obs, ref = np.asarray(nxt.obs), states["obs"]
    rel = np.abs(obs - ref) / np.maximum(1.0, np.abs(ref))
    assert rel.mean() < mean_tol and rel.max() < max_tol, (rel.mean(), rel.max())
    assert np.abs(np.asarray(nxt.reward) - states["reward"]).max() < reward_tol
    np.testing.assert_array_equal(nxt.info["steps"], 1)
    if solver == "dm_control":
        # The sensors are read at dm_control's moments: the same values, not merely the same kind of values.
        acc, acc_ref = _parts(obs, ACC_PARTS), _parts(ref, ACC_PARTS)
        assert np.abs(acc_ref).max() > 1.0  # contacts push on the toes; the torso accelerates
        scale = np.maximum(1.0, np.abs(acc_ref))
        assert (np.abs(acc - acc_ref) / scale).mean() < 1e-4
        np.testing.assert_allclose(_parts(obs, STATE_PARTS), _parts(ref, STATE_PARTS), rtol=1e-3, atol=1e-3)


@pytest.mark.heavy  # make test-heavy: the batched compile; make test checks the same wrappers on walker (test_envs.py)
def test_batched_episode_bookkeeping_and_finite_values(compiled_env):
    """The default solver's batched reset and step: documented shapes, finite values, rewards in [0, 1], the time
    limit at 1000 steps."""
    c = compiled_env(TASK)
    state = c.batch_reset(jax.random.split(jax.random.PRNGKey(0), B))
    actions = jax.random.uniform(jax.random.PRNGKey(1), (B, 12), minval=-1, maxval=1)
    for _ in range(2):
        state = c.batch_step(state, actions)
    assert state.obs.shape == (B, 78) and state.reward.shape == (B,) == state.done.shape
    assert np.all(np.isfinite(state.obs)) and np.all((state.reward >= 0) & (state.reward <= 1))
    np.testing.assert_array_equal(state.done, 0.0)
    state = state.replace(info=dict(state.info, steps=jnp.full((B,), 999, jnp.int32)))
    state = c.batch_step(state, actions)
    np.testing.assert_array_equal(state.done, 1.0)
    np.testing.assert_array_equal(state.info["truncation"], 1.0)


# -- a whole episode --------------------------------------------------------------------------------------------


@pytest.mark.heavy
def test_an_episode_side_by_side_with_dm_control():
    """In ``make test-heavy`` (a compile at XLA's full optimisation and 1000 steps with dm_control's solver;
    ``make test`` checks the same step on 256 states of two episodes): a whole dm_control episode under random
    actions, every transition also stepped by MJX from dm_control's state. The per-step errors stay float32's
    and the episode's return is dm_control's."""
    episode = _trajectory(TASK, 6, 1000)  # it lands on its toes, then ends on its back
    env = make_env(TASK, solver="dm_control")
    data = _batch(env, episode)
    start = jax.jit(jax.vmap(env.observe))(data, jnp.zeros(1000, jnp.int32), jnp.zeros(1000))
    nxt = jax.jit(jax.vmap(env.step))(start, jnp.asarray(episode["action"]))
    rel = np.abs(np.asarray(nxt.obs) - episode["obs"]) / np.maximum(1.0, np.abs(episode["obs"]))
    assert rel.mean() < 1e-4 and rel.max() < 1e-2, (rel.mean(), rel.max())
    np.testing.assert_allclose(np.sum(nxt.reward), np.sum(episode["reward"]), rtol=1e-4)
    np.testing.assert_allclose(nxt.reward, episode["reward"], atol=1e-3)
