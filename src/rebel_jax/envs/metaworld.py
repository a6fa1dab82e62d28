"""Meta-World's manipulation tasks on MJX: the Sawyer arm driven through its mocap weld.

Each task is a ``brax.envs.Env`` with brax's ``State`` equal to Meta-World 3.1.1's ``<task>-v3`` environment
(``metaworld.env_dict.ALL_V3_ENVIRONMENTS``, reward version ``v2``, its default) as the preference-RL code bases
build it (rll-research/BPref@f3ece2e:utils.py, ``make_metaworld_env``): a fresh random object position at every
reset, 500-step episodes, a 4-number action (end-effector displacement of at most 1 cm per axis, and the gripper)
and a 39-number observation (hand position, gripper opening, object pose, the same 18 numbers of the previous step,
the goal).
``goal_observable=False`` zeroes the goal as those code bases' observation does (docs/tasks.md says why).

The models, meshes and textures are Meta-World's own (``metaworld_assets/``, MIT licence). The tests compare
observations, rewards, success flags, the reset distribution and single steps with data recorded from Meta-World
(``tests/data/metaworld/make_reference.py``, ``tests/test_envs_metaworld.py``).

References:
  Yu et al., "Meta-World: A Benchmark and Evaluation for Multi-Task and Meta Reinforcement Learning", CoRL 2019.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import pathlib
from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.base import Env, State
from mujoco import mjx

from rebel_jax.envs._mjx import build_warp_kernels, plain_cholesky, traced_constant, uncommitted

ASSETS = pathlib.Path(__file__).parent / "metaworld_assets"
"""Meta-World 3.1.1's ``metaworld/assets`` files that these tasks' models read (its LICENSE beside them)."""

PREFIX = "metaworld_"
"""Task names: ``metaworld_drawer-open``, ... (B-Pref's ``metaworld_<env>`` names without the version)."""

EPISODE_LENGTH = 500  # metaworld@3.1.1:metaworld/sawyer_xyz_env.py:153 (max_path_length)
FRAME_SKIP = 5  # sawyer_xyz_env.py:177
ACTION_SCALE = 1.0 / 100  # sawyer_xyz_env.py:182: metres of mocap displacement per unit of action
HAND_RESET_STEPS = 50  # sawyer_xyz_env.py:684 (_reset_hand)
MOCAP_QUAT = (1.0, 0.0, 1.0, 0.0)  # sawyer_xyz_env.py:336, set (unnormalised) at every step
WELD_DATA = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0)  # sawyer_xyz_env.py:139 (reset_mocap_welds)
HAND_SPACE = ((-0.525, 0.348, -0.0525), (0.525, 1.025, 0.7))  # sawyer_xyz_env.py:146-150 (_HAND_SPACE)
OBJ_PADDED = 14  # sawyer_xyz_env.py:244 (_obs_obj_max_len)
VALUE_AT_MARGIN = 0.1  # metaworld@3.1.1:metaworld/utils/reward_utils.py:10


def long_tail_tolerance(x: jax.Array, upper: float, margin: jax.Array) -> jax.Array:
    """Meta-World's ``reward_utils.tolerance(x, bounds=(0, upper), margin, sigmoid='long_tail')`` for ``x >= 0``
    and ``margin > 0`` (metaworld@3.1.1:metaworld/utils/reward_utils.py:63-65, 97-150); ``margin`` may be traced.

    Args:
      x: distances (>= 0).
      upper: the upper bound of the target interval.
      margin: where the output falls to 0.1.

    Returns:
      1 within ``[0, upper]``, else ``1 / ((d * scale)^2 + 1)`` of the scaled distance ``d = (x - upper) / margin``.
    """
    scale = np.sqrt(1.0 / VALUE_AT_MARGIN - 1.0)
    d = (x - upper) / margin
    return jnp.where(x <= upper, 1.0, 1.0 / ((d * scale) ** 2 + 1.0))


def hamacher_product(a: jax.Array, b: jax.Array) -> jax.Array:
    """Meta-World's ``reward_utils.hamacher_product`` (metaworld@3.1.1:metaworld/utils/reward_utils.py:240-244):
    ``a * b / (a + b - a * b)``, 0 where the denominator is not positive."""
    denominator = a + b - a * b
    return jnp.where(denominator > 0, a * b / jnp.where(denominator > 0, denominator, 1.0), 0.0)


def tolerance(x: jax.Array, lower: float, upper: float, margin: jax.Array) -> jax.Array:
    """Meta-World's ``reward_utils.tolerance(x, bounds=(lower, upper), margin, sigmoid='long_tail')`` for any ``x``
    and ``margin >= 0`` (metaworld@3.1.1:metaworld/utils/reward_utils.py:97-150); ``margin`` may be traced.

    Args:
      x: the input.
      lower, upper: the target interval's bounds (inclusive).
      margin: where the output falls to 0.1; 0: the output is 0 outside the bounds.

    Returns:
      1 within ``[lower, upper]``, else ``1 / ((d * scale)^2 + 1)`` of the distance to the nearest bound over
      ``margin`` (0 where ``margin`` is 0).
    """
    scale = np.sqrt(1.0 / VALUE_AT_MARGIN - 1.0)
    inside = (lower <= x) & (x <= upper)
    safe = jnp.where(margin == 0, 1.0, margin)
    d = jnp.where(x < lower, lower - x, x - upper) / safe
    return jnp.where(inside, 1.0, jnp.where(margin == 0, 0.0, 1.0 / ((d * scale) ** 2 + 1.0)))


def scipy_quat(xmat: jax.Array) -> jax.Array:
    """``scipy.spatial.transform.Rotation.from_matrix(xmat.reshape(3, 3)).as_quat()`` for a rotation matrix, as
    Meta-World's tasks that observe a geom's orientation compute it (scalar last, scipy's sign): the largest of the
    diagonal and the trace picks the formula (scipy@1.17.1:scipy/spatial/transform/_rotation_xp.py:86-161,
    ``_from_matrix_orthogonal``; NumPy input runs the same formulas in scipy's Cython backend).

    Args:
      xmat: a rotation matrix, flat (9,) as MuJoCo's ``geom_xmat`` or (3, 3).

    Returns:
      The unit quaternion ``(x, y, z, w)``.
    """
    m = xmat.reshape(3, 3)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    choice = jnp.argmax(jnp.array([m[0, 0], m[1, 1], m[2, 2], trace]))
    cases = []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        q = [None] * 4
        q[i] = 1.0 - trace + 2.0 * m[i, i]
        q[j] = m[j, i] + m[i, j]
        q[k] = m[k, i] + m[i, k]
        q[3] = m[k, j] - m[j, k]
        cases.append(jnp.stack(q))
    cases.append(jnp.stack([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 1.0 + trace]))
    q = jnp.stack(cases)[choice]
    return q / jnp.linalg.norm(q)


@dataclasses.dataclass(frozen=True)
class Context:
    """What a task's reward reads besides the observation.

    Attributes:
      tcp: the fingertips' centre now (``tcp_center``).
      target_pos: the episode's goal (``_target_pos``).
      init_tcp: the fingertips' centre after the reset (``init_tcp``).
      consts: the episode's other constants of the reset (task-specific, ``(k,)``).
      action: the action of the step that led here (zeros at a reset).
      extra: what else of the state the reward reads (``TaskSpec.extra``; ``(0,)`` for none).
    """

    tcp: jax.Array
    target_pos: jax.Array
    init_tcp: jax.Array
    consts: jax.Array
    action: jax.Array
    extra: jax.Array


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """One Meta-World task.

    Attributes:
      name: Meta-World's name without the version (``drawer-open``).
      xml: the model file, relative to ``metaworld_assets/sawyer_xyz``.
      hand_low, hand_high: the mocap's bounds (Meta-World's ``hand_low``/``hand_high``; its ``mocap_low``/``high``
        default to them).
      goal_low, goal_high: the goal's bounds (``goal_space``), to which the observation's goal is clipped; None:
        ``hand_low``/``hand_high`` (drawer-open's and button-press's ``goal_space``).
      reset_low, reset_high: the uniform reset draw (``_random_reset_space``).
      hand_init_pos: where the hand is driven at reset.
      moved_body: the body whose model position the reset sets to the draw (Meta-World writes
        ``model.body(...).pos``); None where the reset moves a free object's joint instead (``object_qpos``).
      reset_forward: the task's ``reset_model`` ends with ``set_state`` (which runs ``mj_forward``), so the reset's
        observation shows the state the episode starts from; otherwise it shows MuJoCo's stale kinematics
        (:meth:`MetaWorldEnv.reset`).
      goal: ``(model ids, rand_vec, data after the reset, kinematics current) -> (target_pos, consts (k,))``.
      objects: ``model ids -> (mjx.Data -> (positions (3k,), quaternions (4k,)))`` of the task's k objects (one,
        or hammer's two; Meta-World's ``_get_pos_objects`` and ``_get_quat_objects``).
      reward: ``(obs, Context) -> (reward, info)`` with ``success`` among the info.
      object_qpos: how many of the free object's position numbers (``qpos[9:9 + n]``) the reset sets to the draw's
        first ``n``, the rest of its pose as the hand's reset left it (Meta-World's ``_set_obj_xyz``,
        metaworld@3.1.1:metaworld/sawyer_xyz_env.py:351-361, and hammer's ``_set_hammer_xyz``): sweep-into 2 (x and
        y), hammer 3; 0: none.
      accept: ``rand_vec -> bool``: the reset draws again until it holds (Meta-World's rejection loops); None: once.
      extra: ``model ids -> (mjx.Data -> (k,))``: what else of the state the reward reads (``Context.extra``).
      contacts: the reward's info reads contact forces, so observing a stepped state runs ``mjx.forward`` (contacts
        and constraint forces) instead of only the kinematics; under ``impl='warp'`` Warp's own ``forward`` after
        the step, read by :func:`_warp_touching` and passed to ``extra`` as ``touching``.
      shown_consts: ``model ids -> (mjx.Data -> (k,))``: episode constants that Meta-World's ``reset_model`` reads
        from MuJoCo's stale kinematics (those its reset observation shows; tasks without ``reset_forward``),
        appended to ``consts``.
      goal_site: the reset writes the site ``goal`` at the goal (Meta-World's ``model.site("goal").pos =
        self._target_pos``), so that Meta-World draws it there; False: the site (if any) stays where the model puts
        it. It changes no physics: only the clips draw it (:func:`scene`).
    """

    name: str
    xml: str
    hand_low: tuple[float, float, float]
    hand_high: tuple[float, float, float]
    reset_low: tuple[float, ...]
    reset_high: tuple[float, ...]
    hand_init_pos: tuple[float, float, float]
    moved_body: str
    reset_forward: bool
    goal: Callable[[mujoco.MjModel], Callable[[jax.Array, mjx.Data], tuple[jax.Array, jax.Array]]]
    objects: Callable[[mujoco.MjModel], Callable[[mjx.Data], tuple[jax.Array, jax.Array]]]
    reward: Callable[[jax.Array, Context], tuple[jax.Array, dict[str, jax.Array]]]
    goal_low: tuple[float, float, float] | None = None
    goal_high: tuple[float, float, float] | None = None
    object_qpos: int = 0
    accept: Callable[[jax.Array], jax.Array] | None = None
    extra: Callable[[mujoco.MjModel], Callable[[mjx.Data], jax.Array]] | None = None
    contacts: bool = False
    shown_consts: Callable[[mujoco.MjModel], Callable[[mjx.Data], jax.Array]] | None = None
    goal_site: bool = False


def _body(model: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)


def _site(model: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)


def _flags(**values: jax.Array) -> dict[str, jax.Array]:
    return {k: v.astype(jnp.float32) for k, v in values.items()}


# drawer-open: metaworld@3.1.1:metaworld/envs/sawyer_drawer_open_v3.py
DRAWER_MAX_DIST = 0.2  # sawyer_drawer_open_v3.py:58 (maxDist)


def _drawer_goal(model: mujoco.MjModel) -> Callable[[jax.Array, mjx.Data], tuple[jax.Array, jax.Array]]:
    def goal(rand_vec: jax.Array, d: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """sawyer_drawer_open_v3.py:99-113: the goal 36 cm in front of the closed drawer's handle."""
        del d
        return rand_vec + jnp.array([0.0, -0.16 - DRAWER_MAX_DIST, 0.09]), jnp.zeros(1)

    return goal


def _offset_body(name: str, offset: tuple[float, float, float]):
    """The object of a task that observes one body: its position moved by ``offset`` in world axes, and its
    orientation (drawer-open's handle, sawyer_drawer_open_v3.py:93-97; button-press's button,
    sawyer_button_press_v3.py:92-96)."""

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], tuple[jax.Array, jax.Array]]:
        body = _body(model, name)

        def objects(d: mjx.Data) -> tuple[jax.Array, jax.Array]:
            return d.xpos[body] + jnp.array(offset), d.xquat[body]

        return objects

    return factory


def _drawer_reward(obs: jax.Array, c: Context) -> tuple[jax.Array, dict]:
    """sawyer_drawer_open_v3.py:115-158 (reward version v2) and its ``evaluate_state`` (:66-88)."""
    gripper, handle = obs[:3], obs[4:7]
    handle_error = jnp.linalg.norm(handle - c.target_pos)
    opening = long_tail_tolerance(handle_error, 0.02, DRAWER_MAX_DIST)
    handle_init = c.target_pos + jnp.array([0.0, DRAWER_MAX_DIST, 0.0])
    scale = jnp.array([3.0, 3.0, 1.0])
    caging_margin = jnp.linalg.norm((handle_init - c.init_tcp) * scale)
    caging = long_tail_tolerance(jnp.linalg.norm((handle - gripper) * scale), 0.01, caging_margin)
    reward = 5.0 * (caging + opening)
    gripper_error = jnp.linalg.norm(handle - gripper)
    info = _flags(
        success=handle_error <= 0.03,
        near_object=gripper_error <= 0.03,
        grasp_success=obs[3] > 0,
        grasp_reward=caging,
        in_place_reward=opening,
        obj_to_target=handle_error,
    )
    return reward, info


# button-press: metaworld@3.1.1:metaworld/envs/sawyer_button_press_v3.py


def _button_goal(model: mujoco.MjModel) -> Callable[[jax.Array, mjx.Data], tuple[jax.Array, jax.Array]]:
    hole, start = _site(model, "hole"), _site(model, "buttonStart")

    def goal(rand_vec: jax.Array, d: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """sawyer_button_press_v3.py:105-124: the goal is the site ``hole``; the button's travel to it from
        ``buttonStart`` along y (``_obj_to_target_init``) is the episode's constant."""
        del rand_vec
        target = d.site_xpos[hole]
        return target, jnp.abs(target[1] - d.site_xpos[start, 1])[None]

    return goal


def _button_reward(obs: jax.Array, c: Context) -> tuple[jax.Array, dict]:
    """sawyer_button_press_v3.py:126-166 (reward version v2) and its ``evaluate_state`` (:61-83)."""
    obj = obs[4:7]
    tcp_to_obj = jnp.linalg.norm(obj - c.tcp)
    tcp_to_obj_init = jnp.linalg.norm(obj - c.init_tcp)
    obj_to_target = jnp.abs(c.target_pos[1] - obj[1])
    tcp_closed = jnp.maximum(obs[3], 0.0)
    near_button = long_tail_tolerance(tcp_to_obj, 0.05, tcp_to_obj_init)
    button_pressed = long_tail_tolerance(obj_to_target, 0.005, c.consts[0])
    reward = 2.0 * hamacher_product(tcp_closed, near_button) + jnp.where(tcp_to_obj <= 0.05, 8.0 * button_pressed, 0.0)
    info = _flags(
        success=obj_to_target <= 0.02,
        near_object=tcp_to_obj <= 0.05,
        grasp_success=obs[3] > 0,
        grasp_reward=near_button,
        in_place_reward=button_pressed,
        obj_to_target=obj_to_target,
    )
    return reward, info


# door-open: metaworld@3.1.1:metaworld/envs/sawyer_door_v3.py
DOOR_GOAL_OFFSET = (-0.3, -0.45, 0.0)  # sawyer_door_v3.py:117


def _door_goal(model: mujoco.MjModel) -> Callable[[jax.Array, mjx.Data], tuple[jax.Array, jax.Array]]:
    def goal(rand_vec: jax.Array, d: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """sawyer_door_v3.py:116-117: the goal 30 cm left of and 45 cm in front of the door's hinge body."""
        del d
        return rand_vec + jnp.array(DOOR_GOAL_OFFSET), jnp.zeros(1)

    return goal


def _geom_object(name: str):
    """The object of a task that observes one geom: its position and scipy's quaternion of its orientation
    (door-open's ``handle``, sawyer_door_v3.py:97-103; sweep-into's ``objGeom`` orientation,
    sawyer_sweep_into_goal_v3.py:94-96, see :func:`_sweep_objects`)."""

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], tuple[jax.Array, jax.Array]]:
        geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)

        def objects(d: mjx.Data) -> tuple[jax.Array, jax.Array]:
            return d.geom_xpos[geom], scipy_quat(d.geom_xmat[geom])

        return objects

    return factory


def _joint_angle(name: str):
    """``extra``: the angle of one hinge (door-open's ``doorjoint``, sawyer_door_v3.py:187)."""

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], jax.Array]:
        adr = int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)])

        def extra(d: mjx.Data) -> jax.Array:
            return d.qpos[adr : adr + 1]

        return extra

    return factory


def _door_reward(obs: jax.Array, c: Context) -> tuple[jax.Array, dict]:
    """sawyer_door_v3.py:130-205 (reward version v2) and its ``evaluate_state`` (:67-91)."""
    theta = c.extra[0]
    grab = (jnp.clip(c.action[3], -1.0, 1.0) + 1.0) / 2.0  # :130-132 (_reward_grab_effort)
    # :134-178 (_reward_pos)
    hand = obs[:3]
    door = obs[4:7] + jnp.array([-0.05, 0.0, 0.0])
    threshold = 0.12
    radius = jnp.linalg.norm(hand[:2] - door[:2])
    floor = jnp.where(radius <= threshold, 0.0, 0.04 * jnp.log(jnp.maximum(radius - threshold, 1e-30)) + 0.4)
    above_floor = jnp.where(hand[2] >= floor, 1.0, tolerance(floor - hand[2], 0.0, 0.01, jnp.maximum(floor / 2.0, 0.0)))
    in_place = tolerance(jnp.linalg.norm(hand - door - jnp.array([0.05, 0.03, -0.01])), 0.0, threshold / 2.0, 0.5)
    ready_to_open = hamacher_product(above_floor, in_place)
    door_angle = -theta
    opened = 0.2 * (theta < -np.pi / 90.0) + 0.8 * tolerance(
        np.pi / 2.0 + np.pi / 6 - door_angle, 0.0, 0.5, np.pi / 3.0
    )
    success = jnp.abs(obs[4] - c.target_pos[0]) <= 0.08  # :79, :200
    reward = jnp.where(success, 10.0, 2.0 * hamacher_product(ready_to_open, grab) + 8.0 * opened)
    info = _flags(
        success=success,
        near_object=ready_to_open,
        grasp_success=grab >= 0.5,
        grasp_reward=grab,
        in_place_reward=opened,
        obj_to_target=jnp.zeros(()),
    )
    return reward, info


# sweep-into: metaworld@3.1.1:metaworld/envs/sawyer_sweep_into_goal_v3.py
SWEEP_GOAL = (0.0, 0.84, 0.02)  # sawyer_sweep_into_goal_v3.py:51 (goal)
SWEEP_OBJ_RADIUS = 0.02  # :17
SWEEP_TARGET_RADIUS = 0.05  # :224


def _sweep_accept(rand_vec: jax.Array) -> jax.Array:
    """sawyer_sweep_into_goal_v3.py:108-110: the object's draw at least 15 cm (in x and y) from the goal."""
    return jnp.linalg.norm(rand_vec[:2] - jnp.array(SWEEP_GOAL[:2])) >= 0.15


def _sweep_goal(model: mujoco.MjModel) -> Callable[[jax.Array, mjx.Data], tuple[jax.Array, jax.Array]]:
    def goal(rand_vec: jax.Array, d: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """sawyer_sweep_into_goal_v3.py:101-121: the goal is fixed (the hole); the episode's constant is the
        object's start (``obj_init_pos``: the draw's x and y, the height the hand's reset left the object at)."""
        del rand_vec
        return jnp.array(SWEEP_GOAL), d.qpos[9:12]

    return goal


def _sweep_objects(model: mujoco.MjModel) -> Callable[[mjx.Data], tuple[jax.Array, jax.Array]]:
    """sawyer_sweep_into_goal_v3.py:94-99: the body ``obj``'s position, its geom's orientation (scipy's quaternion)."""
    body = _body(model, "obj")
    geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "objGeom")

    def objects(d: mjx.Data) -> tuple[jax.Array, jax.Array]:
        return d.xpos[body], scipy_quat(d.geom_xmat[geom])

    return objects


def _pushes(pair: jax.Array, force: jax.Array, pad: int, obj: int) -> jax.Array:
    """Whether the summed normal force of the contacts between geoms ``pad`` and ``obj`` is positive: ``pair``
    (n, 2) each contact's geoms, ``force`` (n,) its normal force (0 where a row is no contact's normal)."""
    mine = ((pair[:, 0] == pad) & (pair[:, 1] == obj)) | ((pair[:, 0] == obj) & (pair[:, 1] == pad))
    return jnp.where(mine, force, 0.0).sum() > 0


def _pads_and_touching(model: mujoco.MjModel) -> Callable[..., jax.Array]:
    """``extra`` of sweep-into: the pads' body positions (6; ``get_body_com``) and whether both pads push on the
    object (1; ``touching_main_object``, metaworld@3.1.1:metaworld/sawyer_xyz_env.py:393-440: each pad's summed
    normal contact force with ``objGeom`` is positive). Reads the contacts and constraint forces of the last
    ``mjx.forward`` (zeros in a state that has not run one, such as the reset's), unless ``touching`` is given
    (MuJoCo Warp's, :func:`_warp_touching`)."""
    left, right = _body(model, "leftpad"), _body(model, "rightpad")
    obj, pads = _sweep_geoms(model)
    # MJX's contacts are a fixed set of candidates whose constraint rows are fixed (the first: an elliptic contact's
    # normal); the collision fills in their geoms.
    address = np.asarray(mjx.make_data(model)._impl.contact.efc_address)

    def extra(d: mjx.Data, touching: jax.Array | None = None) -> jax.Array:
        if touching is None:
            pair, force = d._impl.contact.geom, d._impl.efc_force[address]
            touching = _pushes(pair, force, pads[0], obj) & _pushes(pair, force, pads[1], obj)
        return jnp.concatenate([d.xpos[left], d.xpos[right], touching.astype(d.xpos.dtype)[None]])

    return extra


def _sweep_geoms(model: mujoco.MjModel) -> tuple[int, tuple[int, int]]:
    """sweep-into's object geom and its two pads' geoms."""
    geom = lambda n: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
    return geom("objGeom"), (geom("leftpad_geom"), geom("rightpad_geom"))


_CONTACT_ROWS = tuple(
    int(t)
    for t in (
        mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS,
        mujoco.mjtConstraint.mjCNSTR_CONTACT_PYRAMIDAL,
        mujoco.mjtConstraint.mjCNSTR_CONTACT_ELLIPTIC,
    )
)
"""The constraint rows' types of contacts (``efc_type``)."""


def _warp_touching(model: mujoco.MjModel) -> Callable[[mjx.Data], jax.Array]:
    """sweep-into's ``touching_main_object`` (see :func:`_pads_and_touching`) from a MuJoCo Warp data after its
    ``forward``.

    Warp keeps the contacts of every world of a batch in one buffer (unbatched under ``vmap``) and each world's
    constraint rows in its own (mujoco 3.17 mjx/warp/types.py ``_BATCH_DIM``); a world's contact row ``r`` names its
    contact (``efc.id``), whose first row (``contact.efc_address[:, 0]``, the normal of an elliptic cone) is ``r``
    (mjx/third_party/mujoco_warp/_src/constraint.py, the contact rows' kernels), so a world reads its own contacts
    through its rows."""
    obj, pads = _sweep_geoms(model)

    def touching(w: mjx.Data) -> jax.Array:
        impl = w._impl
        rows = jnp.arange(impl.efc__force.shape[-1])
        contact = jnp.isin(impl.efc__type, jnp.array(_CONTACT_ROWS)) & (rows < impl.nefc)
        con = jnp.where(contact, impl.efc__id, 0)
        normal = contact & (impl.contact__efc_address[con, 0] == rows)
        pair, force = impl.contact__geom[con], jnp.where(normal, impl.efc__force, 0.0)
        return _pushes(pair, force, pads[0], obj) & _pushes(pair, force, pads[1], obj)

    return touching


def _sweep_reward(obs: jax.Array, c: Context) -> tuple[jax.Array, dict]:
    """sawyer_sweep_into_goal_v3.py:219-257 (reward version v2), its ``_gripper_caging_reward`` (:123-217) and its
    ``evaluate_state`` (:67-92).

    Meta-World's ``init_left_pad``/``init_right_pad`` are views of the pads' current positions (gymnasium's
    ``get_body_com`` returns ``data.body(name).xpos`` itself, read once in ``SawyerXYZEnv.__init__``), so the caging
    margins read the pads where they are now, as here.
    """
    tcp, obj = c.tcp, obs[4:7]
    left_pad, right_pad, touching = c.extra[0:3], c.extra[3:6], c.extra[6] > 0
    obj_init = c.consts
    target = jnp.array([c.target_pos[0], c.target_pos[1], obj[2]])
    obj_to_target = jnp.linalg.norm(obj - target)
    tcp_to_obj = jnp.linalg.norm(obj - tcp)
    in_place = tolerance(obj_to_target, 0.0, SWEEP_TARGET_RADIUS, jnp.linalg.norm(obj_init - target))
    # _gripper_caging_reward (:135-217)
    pad_margin, grip_margin, xz_margin = 0.05, SWEEP_OBJ_RADIUS + 0.005, 0.01
    dy_left, dy_right = left_pad[1] - obj[1], obj[1] - right_pad[1]
    right_margin = jnp.abs(jnp.abs(obj[1] - right_pad[1]) - pad_margin)
    left_margin = jnp.abs(jnp.abs(obj[1] - left_pad[1]) - pad_margin)
    right_caging = tolerance(dy_right, SWEEP_OBJ_RADIUS, pad_margin, right_margin)
    left_caging = tolerance(dy_left, SWEEP_OBJ_RADIUS, pad_margin, left_margin)
    right_gripping = tolerance(dy_right, SWEEP_OBJ_RADIUS, grip_margin, right_margin)
    left_gripping = tolerance(dy_left, SWEEP_OBJ_RADIUS, grip_margin, left_margin)
    y_caging = hamacher_product(right_caging, left_caging)
    y_gripping = hamacher_product(right_gripping, left_gripping)
    xz = jnp.array([1.0, 0.0, 1.0])
    tcp_obj_xz = jnp.linalg.norm((tcp - obj) * xz)
    xz_caging_margin = jnp.linalg.norm((obj_init - c.init_tcp) * xz) - xz_margin
    xz_caging = tolerance(tcp_obj_xz, 0.0, xz_margin, xz_caging_margin)
    caging = hamacher_product(y_caging, xz_caging)
    gripping = jnp.where(caging > 0.95, y_gripping, 0.0)
    grasped = (caging + gripping) / 2.0
    reward = 2.0 * grasped + 6.0 * hamacher_product(grasped, in_place)
    reward = jnp.where(obj_to_target < SWEEP_TARGET_RADIUS, 10.0, reward)
    info = _flags(
        success=obj_to_target <= SWEEP_TARGET_RADIUS,
        near_object=tcp_to_obj <= 0.03,
        grasp_success=touching & (obs[3] > 0),
        grasp_reward=grasped,
        in_place_reward=in_place,
        obj_to_target=obj_to_target,
    )
    return reward, info


# window-open: metaworld@3.1.1:metaworld/envs/sawyer_window_open_v3.py
WINDOW_TARGET_RADIUS = 0.05  # sawyer_window_open_v3.py:27
WINDOW_HANDLE_RADIUS = 0.02  # :156


def _window_goal(model: mujoco.MjModel) -> Callable[[jax.Array, mjx.Data], tuple[jax.Array, jax.Array]]:
    def goal(rand_vec: jax.Array, d: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """sawyer_window_open_v3.py:117-119: the goal 20 cm right of the window's draw."""
        del d
        return rand_vec + jnp.array([0.2, 0.0, 0.0]), jnp.zeros(0)

    return goal


def _site_object(name: str):
    """The object of a task that observes one site's position and no orientation (zeros; window-open's
    ``handleOpenStart``, sawyer_window_open_v3.py:104-108)."""

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], tuple[jax.Array, jax.Array]]:
        site = _site(model, name)

        def objects(d: mjx.Data) -> tuple[jax.Array, jax.Array]:
            return d.site_xpos[site], jnp.zeros(4, d.site_xpos.dtype)

        return objects

    return factory


def _site_position(name: str):
    """``shown_consts``: one site's position (window-open's ``window_handle_pos_init``, sawyer_window_open_v3.py:122,
    read before any ``mj_forward``)."""

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], jax.Array]:
        site = _site(model, name)
        return lambda d: d.site_xpos[site]

    return factory


def _window_reward(obs: jax.Array, c: Context) -> tuple[jax.Array, dict]:
    """sawyer_window_open_v3.py:131-171 (reward version v2) and its ``evaluate_state`` (:76-102)."""
    obj = obs[4:7]  # the site handleOpenStart (_get_pos_objects), never clipped (unbounded)
    handle_init = c.consts[0:3]
    target_to_obj = jnp.abs(obj[0] - c.target_pos[0])
    obj_init_x = c.target_pos[0] - 0.2  # obj_init_pos[0]: the draw
    target_to_obj_init = jnp.abs(obj_init_x - c.target_pos[0])
    in_place = tolerance(target_to_obj, 0.0, WINDOW_TARGET_RADIUS, jnp.abs(target_to_obj_init - WINDOW_TARGET_RADIUS))
    tcp_to_obj = jnp.linalg.norm(obj - c.tcp)
    tcp_to_obj_init = jnp.linalg.norm(handle_init - c.init_tcp)
    reach = tolerance(tcp_to_obj, 0.0, WINDOW_HANDLE_RADIUS, jnp.abs(tcp_to_obj_init - WINDOW_HANDLE_RADIUS))
    reward = 10.0 * hamacher_product(reach, in_place)
    info = _flags(
        success=target_to_obj <= WINDOW_TARGET_RADIUS,
        near_object=tcp_to_obj <= 0.05,
        grasp_success=jnp.ones((), bool),
        grasp_reward=reach,
        in_place_reward=in_place,
        obj_to_target=target_to_obj,
    )
    return reward, info


# door-unlock: metaworld@3.1.1:metaworld/envs/sawyer_door_unlock_v3.py
UNLOCK_LOCK_LENGTH = 0.1  # sawyer_door_unlock_v3.py:50 (_lock_length)


def _unlock_goal(model: mujoco.MjModel) -> Callable[[jax.Array, mjx.Data], tuple[jax.Array, jax.Array]]:
    lock = _body(model, "lock_link")

    def goal(rand_vec: jax.Array, d: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """sawyer_door_unlock_v3.py:111-120: the goal 10 cm right of and 4 cm in front of the lock's body, after the
        reset turned the lock to 1.5708 rad (``set_state``: kinematics current)."""
        del rand_vec
        return d.xpos[lock] + jnp.array([0.1, -0.04, 0.0]), jnp.zeros(0)

    return goal


def _body_position(name: str):
    """``extra``: one body's current position (door-unlock's ``obj_init_pos``, which Meta-World takes as the view
    ``data.body("lock_link").xpos``, sawyer_door_unlock_v3.py:115, so it follows the lock at every step)."""

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], jax.Array]:
        body = _body(model, name)
        return lambda d: d.xpos[body]

    return factory


def _body_object(name: str):
    """The object of a task that observes a site's position and a body's quaternion (door-unlock: the site
    ``lockStartUnlock`` and the body ``door_link``, sawyer_door_unlock_v3.py:98-102)."""
    site_name, body_name = name.split(":")

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], tuple[jax.Array, jax.Array]]:
        site, body = _site(model, site_name), _body(model, body_name)

        def objects(d: mjx.Data) -> tuple[jax.Array, jax.Array]:
            return d.site_xpos[site], d.xquat[body]

        return objects

    return factory


def _unlock_reward(obs: jax.Array, c: Context) -> tuple[jax.Array, dict]:
    """sawyer_door_unlock_v3.py:122-165 (reward version v2) and its ``evaluate_state`` (:62-83)."""
    gripper, lock = obs[:3], obs[4:7]
    offset = jnp.array([0.0, 0.055, 0.07])  # the gripper's shoulder rather than its fingers
    scale = jnp.array([0.25, 1.0, 0.5])
    shoulder_to_lock = jnp.linalg.norm((gripper + offset - lock) * scale)
    shoulder_to_lock_init = jnp.linalg.norm((c.init_tcp + offset - c.extra[0:3]) * scale)
    ready_to_push = tolerance(shoulder_to_lock, 0.0, 0.02, shoulder_to_lock_init)
    obj_to_target = jnp.abs(c.target_pos[0] - lock[0])
    pushed = tolerance(obj_to_target, 0.0, 0.005, UNLOCK_LOCK_LENGTH)
    reward = 2.0 * ready_to_push + 8.0 * pushed
    info = _flags(
        success=obj_to_target <= 0.02,
        near_object=shoulder_to_lock <= 0.05,
        grasp_success=obs[3] > 0,
        grasp_reward=ready_to_push,
        in_place_reward=pushed,
        obj_to_target=obj_to_target,
    )
    return reward, info


# hammer: metaworld@3.1.1:metaworld/envs/sawyer_hammer_v3.py
HAMMER_HANDLE_LENGTH = 0.14  # sawyer_hammer_v3.py:16
HAMMER_HEAD_OFFSET = (0.16, 0.06, 0.0)  # :175: the head's point the reward drives to the goal, from the body hammer
HAMMER_NAIL_IN = 0.09  # :204: success, the nail's slide joint driven in beyond 9 cm


def _hammer_goal(model: mujoco.MjModel) -> Callable[[jax.Array, mjx.Data], tuple[jax.Array, jax.Array]]:
    goal_site = _site(model, "goal")

    def goal(rand_vec: jax.Array, d: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """sawyer_hammer_v3.py:108-120: the goal is the site ``goal`` on the nail's box (which the reset writes at its
        XML position, :112, so the goal is fixed); the episode's constant is the hammer's start (``obj_init_pos``:
        the draw, :117-119), which the gripper's caging reward reads."""
        return d.site_xpos[goal_site], rand_vec[:3]

    return goal


def _bodies(*names: str):
    """The objects of a task that observes bodies' positions and quaternions (hammer: the bodies ``hammer`` and
    ``nail_link``, sawyer_hammer_v3.py:91-99; ``get_body_com`` is ``data.body(name).xpos``)."""

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], tuple[jax.Array, jax.Array]]:
        bodies = np.array([_body(model, n) for n in names])

        def objects(d: mjx.Data) -> tuple[jax.Array, jax.Array]:
            return d.xpos[bodies].reshape(-1), d.xquat[bodies].reshape(-1)

        return objects

    return factory


def _pads_and_joint(name: str):
    """``extra`` of hammer: the pads' body positions (6; ``get_body_com("leftpad")``, ``("rightpad")``, which the
    gripper's caging reward reads, sawyer_xyz_env.py:761-762) and one joint's position (1; the nail's
    ``NailSlideJoint``, which success reads, sawyer_hammer_v3.py:204)."""

    def factory(model: mujoco.MjModel) -> Callable[[mjx.Data], jax.Array]:
        left, right = _body(model, "leftpad"), _body(model, "rightpad")
        adr = int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)])

        def extra(d: mjx.Data) -> jax.Array:
            return jnp.concatenate([d.xpos[left], d.xpos[right], d.qpos[adr : adr + 1].astype(d.xpos.dtype)])

        return extra

    return factory


def _gripper_caging(
    obj: jax.Array,
    c: Context,
    left_pad: jax.Array,
    right_pad: jax.Array,
    obj_radius: float,
    pad_success_thresh: float,
    xz_thresh: float,
) -> jax.Array:
    """Meta-World's ``SawyerXYZEnv._gripper_caging_reward`` with ``high_density=True`` and
    ``desired_gripper_effort=1`` (metaworld@3.1.1:metaworld/sawyer_xyz_env.py:721-858; sweep-into overrides it, see
    :func:`_sweep_reward`).

    Args:
      obj: the object's position as the task passes it.
      c: the context (``tcp``, ``init_tcp``, ``consts[:3]``: ``obj_init_pos``; ``action``).
      left_pad, right_pad: the pads' body positions now.
      obj_radius, pad_success_thresh, xz_thresh: the task's arguments.

    Returns:
      The caging reward in [0, 1].
    """
    obj_init = c.consts[:3]
    pad_y = jnp.stack([left_pad[1], right_pad[1]])  # :765-769
    pad_to_obj = jnp.abs(pad_y - obj[1])
    pad_to_obj_init = jnp.abs(pad_y - obj_init[1])
    caging_margin = jnp.abs(pad_to_obj_init - pad_success_thresh)  # :801-810
    left = tolerance(pad_to_obj[0], obj_radius, pad_success_thresh, caging_margin[0])
    right = tolerance(pad_to_obj[1], obj_radius, pad_success_thresh, caging_margin[1])
    caging_y = hamacher_product(left, right)
    xz = jnp.array([1.0, 0.0, 1.0])  # :814-828
    xz_margin = jnp.linalg.norm((obj_init - c.init_tcp) * xz) - xz_thresh
    caging_xz = tolerance(jnp.linalg.norm((c.tcp - obj) * xz), 0.0, xz_thresh, xz_margin)
    closed = jnp.clip(c.action[3], 0.0, 1.0)  # :831-833
    caging = hamacher_product(caging_y, caging_xz)  # :836-841
    gripping = jnp.where(caging > 0.97, closed, 0.0)
    return (hamacher_product(caging, gripping) + caging) / 2.0


def _hammer_reward(obs: jax.Array, c: Context) -> tuple[jax.Array, dict]:
    """sawyer_hammer_v3.py:169-214 (reward version v2), its ``_reward_quat`` (:145-151), ``_reward_pos``
    (:153-167) and ``evaluate_state`` (:64-86)."""
    hand, hammer = obs[:3], obs[4:7]
    head = hammer + jnp.array(HAMMER_HEAD_OFFSET)
    # :182-185: the handle is no sphere, so within half its length in x the caging reward sees it under the hand.
    near_in_x = jnp.abs(hammer[0] - hand[0]) < HAMMER_HANDLE_LENGTH / 2.0
    threshed = hammer.at[0].set(jnp.where(near_in_x, hand[0], hammer[0]))
    laid_down = jnp.maximum(1.0 - jnp.linalg.norm(obs[7:11] - jnp.array([1.0, 0.0, 0.0, 0.0])) / 0.4, 0.0)
    left_pad, right_pad, nail = c.extra[0:3], c.extra[3:6], c.extra[6]
    grab = _gripper_caging(threshed, c, left_pad, right_pad, obj_radius=0.015, pad_success_thresh=0.02, xz_thresh=0.01)
    lifted = head[2] > 0.02
    hit = long_tail_tolerance(jnp.linalg.norm(c.target_pos - head), 0.02, 0.2)
    in_place = 0.1 * lifted + 0.9 * hit
    reward = (2.0 * grab + 6.0 * in_place) * laid_down
    success = nail > HAMMER_NAIL_IN
    reward = jnp.where(success & (reward > 5.0), 10.0, reward)  # :205-206
    info = _flags(
        success=success,
        near_object=laid_down,  # Meta-World's info names reward_quat so (:78)
        grasp_success=grab >= 0.5,
        grasp_reward=grab,
        in_place_reward=in_place,
        obj_to_target=jnp.zeros(()),
    )
    return reward, info


TASKS: dict[str, TaskSpec] = {
    "drawer-open": TaskSpec(
        name="drawer-open",
        xml="sawyer_drawer.xml",
        hand_low=(-0.5, 0.40, 0.05),
        hand_high=(0.5, 1.0, 0.5),
        reset_low=(-0.1, 0.9, 0.0),
        reset_high=(0.1, 0.9, 0.0),
        hand_init_pos=(0.0, 0.6, 0.2),
        moved_body="drawer",
        reset_forward=False,
        goal=_drawer_goal,
        objects=_offset_body("drawer_link", (0.0, -0.16, 0.0)),
        reward=_drawer_reward,
        goal_site=True,  # sawyer_drawer_open_v3.py:112
    ),
    "button-press": TaskSpec(
        name="button-press",
        xml="sawyer_button_press.xml",
        hand_low=(-0.5, 0.40, 0.05),
        hand_high=(0.5, 1.0, 0.5),
        reset_low=(-0.1, 0.85, 0.115),
        reset_high=(0.1, 0.9, 0.115),
        hand_init_pos=(0.0, 0.4, 0.2),
        moved_body="box",
        reset_forward=True,
        goal=_button_goal,
        objects=_offset_body("button", (0.0, -0.193, 0.0)),
        reward=_button_reward,
    ),
    "door-open": TaskSpec(  # sawyer_door_v3.py:26-61
        name="door-open",
        xml="sawyer_door_pull.xml",
        hand_low=(-0.5, 0.40, 0.05),
        hand_high=(0.5, 1.0, 0.5),
        goal_low=(-0.3, 0.4, 0.1499),
        goal_high=(-0.2, 0.5, 0.1501),
        reset_low=(0.0, 0.85, 0.15),
        reset_high=(0.1, 0.95, 0.15),
        hand_init_pos=(0.0, 0.6, 0.2),
        moved_body="door",
        reset_forward=True,  # :121 (_set_obj_xyz ends with set_state)
        goal=_door_goal,
        objects=_geom_object("handle"),
        reward=_door_reward,
        extra=_joint_angle("doorjoint"),
        goal_site=True,  # sawyer_door_v3.py:120, :127
    ),
    "sweep-into": TaskSpec(  # sawyer_sweep_into_goal_v3.py:28-61
        name="sweep-into",
        xml="sawyer_table_with_hole.xml",
        hand_low=(-0.5, 0.40, 0.05),
        hand_high=(0.5, 1.0, 0.5),
        goal_low=(-0.001, 0.8399, 0.0199),
        goal_high=(0.001, 0.8401, 0.0201),
        reset_low=(-0.1, 0.6, 0.02, -0.001, 0.8399, 0.0199),
        reset_high=(0.1, 0.7, 0.02, 0.001, 0.8401, 0.0201),
        hand_init_pos=(0.0, 0.6, 0.2),
        moved_body=None,
        reset_forward=True,  # :114 (_set_obj_xyz ends with set_state)
        goal=_sweep_goal,
        objects=_sweep_objects,
        reward=_sweep_reward,
        object_qpos=2,  # :112-114: the draw's x and y, the height where the hand's reset left the puck
        accept=_sweep_accept,
        extra=_pads_and_touching,
        contacts=True,
        goal_site=True,  # :115
    ),
    "window-open": TaskSpec(  # sawyer_window_open_v3.py:38-70
        name="window-open",
        xml="sawyer_window_horizontal.xml",
        hand_low=(-0.5, 0.40, 0.05),
        hand_high=(0.5, 1.0, 0.5),
        reset_low=(-0.1, 0.7, 0.16),
        reset_high=(0.1, 0.9, 0.16),
        hand_init_pos=(0.0, 0.4, 0.2),
        moved_body="window",
        reset_forward=False,  # :112-127: no set_state, the observation shows the stale kinematics
        goal=_window_goal,
        objects=_site_object("handleOpenStart"),
        reward=_window_reward,
        shown_consts=_site_position("handleOpenStart"),
        goal_site=True,  # :122
    ),
    "door-unlock": TaskSpec(  # sawyer_door_unlock_v3.py:25-56
        name="door-unlock",
        xml="sawyer_door_lock.xml",
        hand_low=(-0.5, 0.40, -0.15),
        hand_high=(0.5, 1.0, 0.5),
        goal_low=(0.0, 0.64, 0.2100),
        goal_high=(0.2, 0.7, 0.2111),
        reset_low=(-0.1, 0.8, 0.15),
        reset_high=(0.1, 0.85, 0.15),
        hand_init_pos=(0.0, 0.6, 0.2),
        moved_body="door",
        reset_forward=True,  # :113 (_set_obj_xyz ends with set_state)
        goal=_unlock_goal,
        objects=_body_object("lockStartUnlock:door_link"),
        reward=_unlock_reward,
        extra=_body_position("lock_link"),
    ),
    "hammer": TaskSpec(  # sawyer_hammer_v3.py:18-58
        name="hammer",
        xml="sawyer_hammer.xml",
        hand_low=(-0.5, 0.40, 0.05),
        hand_high=(0.5, 1.0, 0.5),
        goal_low=(0.2399, 0.7399, 0.109),
        goal_high=(0.2401, 0.7401, 0.111),
        reset_low=(-0.1, 0.4, 0.0),
        reset_high=(0.1, 0.5, 0.0),
        hand_init_pos=(0.0, 0.4, 0.2),
        moved_body=None,  # :112 writes the box's body at its XML position: nothing moves
        reset_forward=True,  # :101-106, :120 (_set_hammer_xyz ends with set_state)
        goal=_hammer_goal,
        objects=_bodies("hammer", "nail_link"),
        reward=_hammer_reward,
        object_qpos=3,  # :104: the hammer's free joint at the draw's x, y and z
        extra=_pads_and_joint("NailSlideJoint"),
    ),
}
"""The tasks by Meta-World's name (without ``-v3``)."""

_NO_CYLINDER_BOX = "MJX's JAX step (mujoco 3.17) cannot collide cylinders with boxes; run it with impl='warp'"

IMPLS = ("jax", "warp")
"""The physics steps a task may run: MJX's JAX step or MuJoCo Warp's (MJX ``impl='warp'``). Observations,
rewards and resets are computed in JAX either way."""

STEP_REFUSED: dict[str, dict[str, str]] = {
    "jax": {
        "button-press": _NO_CYLINDER_BOX,
        "door-open": _NO_CYLINDER_BOX + " (the door's handle)",
        "window-open": _NO_CYLINDER_BOX,
        "door-unlock": "one step of MJX's JAX step from Meta-World's recorded states moves the lock's joint up to "
        "0.13 rad away from Meta-World's (44 of 125 states off by more than 1e-3; docs/tasks.md); run it with "
        "impl='warp'",
        "hammer": _NO_CYLINDER_BOX + " (the hammer's head, the nail)",
    },
    "warp": {},
}
"""Per physics step (:data:`IMPLS`), the tasks whose observation, reward and reset are implemented (and tested) but
whose step that engine does not run faithfully: why."""

STEP_STATE = ("qpos", "qvel", "act", "ctrl", "time", "qacc_warmstart", "mocap_pos", "mocap_quat")
"""The ``mjx.Data`` fields one physics step reads from the last: MuJoCo's state, the control, the solver's warm
start and the mocap body that drives the hand."""

STATIC_POSES = ("geom_xpos", "geom_xmat")
"""MuJoCo Warp computes the world poses of geoms fixed to the world once, in ``make_data``, and its steps keep them
(mujoco 3.17, mjx/third_party/mujoco_warp/_src/smooth.py:199-200). A reset that moves such a body (drawer-open's
casing) puts its geoms where the JAX kinematics of the moved model put them; without it Warp collides the drawer
with its casing at the XML's place and pushes it out (6 mm in 5 steps)."""

WARP_CONTACTS, WARP_CONSTRAINTS = 256, 1024
"""MuJoCo Warp's buffers per world (``naconmax`` per world, ``njmax``): its defaults (48 contacts, 64 constraint rows
for these models) overflow on contact-rich states and drop contacts."""


def refusal(task: str, impl: str) -> str | None:
    """Why ``task``'s physics step does not run with ``impl``: a one-line reason, or None."""
    why = STEP_REFUSED.get(impl, {}).get(task)
    return f"{PREFIX}{task} cannot step with impl={impl!r}: {why}" if why else None


def mj_model(task: str) -> mujoco.MjModel:
    """The compiled model of ``task`` with Meta-World's weld data (``reset_mocap_welds``, sawyer_xyz_env.py:133-141).

    Args:
      task: a key of :data:`TASKS`.

    Returns:
      The MuJoCo model; its solver options are the XML's (Newton, 50 iterations, elliptic cones).
    """
    model = mujoco.MjModel.from_xml_path(str(ASSETS / "sawyer_xyz" / TASKS[task].xml))
    for i in range(model.neq):
        if model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
            # Meta-World's 11 numbers (MuJoCo 3.3 has 11 weld fields); MuJoCo 3.17's twelfth keeps its compiled value.
            model.eq_data[i, : len(WELD_DATA)] = WELD_DATA
    return model


def mujoco_step(
    model: mujoco.MjModel, data: mujoco.MjData, task: str, mocap_pos: np.ndarray, action: np.ndarray
) -> None:
    """One control step of MuJoCo itself (float64, the CPU) in place, as Meta-World's ``step`` runs it
    (sawyer_xyz_env.py:580-640): the mocap moved by ``action[:3]`` cm from ``mocap_pos`` within the hand's bounds,
    the gripper set to ``action[3]``, :data:`FRAME_SKIP` physics steps. The reference the tests hold MJX's and
    Warp's steps to (``model``: :func:`mj_model` with the episode's ``body_pos``; ``data``: the state)."""
    spec = TASKS[task]
    move = np.clip(action[:3], -1.0, 1.0) * ACTION_SCALE
    data.mocap_pos[0] = np.clip(mocap_pos + move, spec.hand_low, spec.hand_high)
    data.mocap_quat[0] = MOCAP_QUAT
    data.ctrl[:] = (action[3], -action[3])
    mujoco.mj_step(model, data, nstep=FRAME_SKIP)


HAND_RESET = ASSETS / "hand_reset.npz"
"""The MuJoCo state that Meta-World 3.1.1's reset leaves the arm in, per task (``<task>/qpos``, ``qvel``,
``mocap_pos``, ``mocap_quat``, ``qacc_warmstart``), recorded by tests/data/metaworld/make_reference.py."""


@dataclasses.dataclass(frozen=True)
class HandReset:
    """The state Meta-World's reset leaves the arm in, and the one its reset observation shows.

    Meta-World's ``_reset_hand`` drives the mocap to ``hand_init_pos`` for 50 control steps (250 physics steps,
    sawyer_xyz_env.py:684-695), with the objects away from the hand's path, so every reset ends in the same state.
    It is Meta-World's own (:data:`HAND_RESET`): MuJoCo 3.17 runs those 250 steps of the redundant arm to joint
    angles up to 7e-3 rad away from MuJoCo 3.3's (docs/tasks.md).

    The reset's observation and ``init_tcp`` read MuJoCo's kinematics as the last ``mj_step`` left them, computed
    before that step's integration: at ``shown_qpos``, one physics step back along ``qvel``.

    Attributes:
      qpos, qvel, mocap_pos, mocap_quat, qacc_warmstart: the state (float64).
      shown_qpos: where the reset's kinematics are (``mj_integratePos`` by ``-timestep``).
    """

    qpos: np.ndarray
    qvel: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    qacc_warmstart: np.ndarray
    shown_qpos: np.ndarray


def hand_reset(task: str, model: mujoco.MjModel) -> HandReset:
    """Meta-World's reset state of ``task`` (:class:`HandReset`) for ``model`` (:func:`mj_model`'s)."""
    with np.load(HAND_RESET) as saved:
        fields = {
            k: np.asarray(saved[f"{task}/{k}"], np.float64)
            for k in ("qpos", "qvel", "mocap_pos", "mocap_quat", "qacc_warmstart")
        }
    shown = fields["qpos"].copy()
    mujoco.mj_integratePos(model, shown, fields["qvel"], -model.opt.timestep)
    return HandReset(**fields, shown_qpos=shown)


def scene_size(task: str) -> int:
    """How many numbers :func:`frame_scene` gives per state of ``task`` (a key of :data:`TASKS`)."""
    spec = TASKS[task]
    return 3 + 3 * (spec.moved_body is not None) + 3 * spec.goal_site


def frame_scene(spec: TaskSpec, state: State) -> jax.Array:
    """What a drawing of ``state`` needs beyond its ``qpos``.

    Meta-World's reset moves bodies and sites of the model itself (``model.body(...).pos``, ``model.site("goal").pos``),
    and its hand follows a mocap body, so MuJoCo draws a state from its ``qpos``, the mocap's pose and the model as
    the episode's reset left it. The mocap's orientation is Meta-World's fixed :data:`MOCAP_QUAT` (set at every step,
    and by the hand's reset), so only its position is kept.

    Args:
      spec: the task.
      state: the task's state (``pipeline_state`` and ``info``), with any leading batch axes.

    Returns:
      ``(..., scene_size)``: the mocap's position; then, where the reset moves a body (``TaskSpec.moved_body``), its
      position (``info["body_pos"]``); then, where the reset writes the site ``goal`` (``TaskSpec.goal_site``), its
      position (``info["target_pos"]``).
    """
    parts = [state.pipeline_state.mocap_pos[..., 0, :]]
    if spec.moved_body is not None:
        parts.append(state.info["body_pos"][..., :3])
    if spec.goal_site:
        parts.append(state.info["target_pos"])
    return jnp.concatenate([p.astype(jnp.float32) for p in parts], axis=-1)


def pose(task: str, model: mujoco.MjModel, data: mujoco.MjData, qpos: np.ndarray, scene: np.ndarray) -> None:
    """Puts MuJoCo's ``model`` and ``data`` of ``task`` (:func:`mj_model`'s) in the state one frame shows, as Meta-World
    has them there, and runs ``mj_forward`` (velocities zero: a drawing reads positions only).

    Args:
      task: a key of :data:`TASKS`.
      model, data: MuJoCo's model and data (the model's moved body and goal site are written).
      qpos: ``(nq,)`` the positions.
      scene: ``(scene_size,)`` the state's :func:`frame_scene`.
    """
    spec = TASKS[task]
    scene = np.asarray(scene, np.float64)
    if scene.shape != (scene_size(task),) or np.shape(qpos) != (model.nq,):
        raise ValueError(
            f"{task}: a frame needs qpos ({model.nq},) and scene ({scene_size(task)},); got {np.shape(qpos)} and "
            f"{scene.shape}"
        )
    data.qpos[:] = qpos
    data.qvel[:] = 0.0
    data.mocap_pos[0] = scene[:3]
    data.mocap_quat[0] = MOCAP_QUAT
    at = 3
    if spec.moved_body is not None:
        model.body_pos[_body(model, spec.moved_body)] = scene[at : at + 3]
        at += 3
    if spec.goal_site:
        model.site_pos[_site(model, "goal")] = scene[at : at + 3]
    mujoco.mj_forward(model, data)


def _cpu_cholesky() -> contextlib.AbstractContextManager:
    """``_mjx.plain_cholesky`` on the CPU (MJX's factorizations in plain JAX operations, as
    :class:`~rebel_jax.envs.dmc.DMCEnv` runs them), nothing elsewhere."""
    return plain_cholesky() if jax.default_backend() == "cpu" else contextlib.nullcontext()


class MetaWorldEnv(Env):
    """A Meta-World task on MJX, a ``brax.envs.Env``.

    Its ``State`` (brax's) holds:
      pipeline_state: the MJX physics data, kinematics current.
      obs: the 39-number observation.
      reward: Meta-World's dense reward (reward version v2) of the last transition.
      done: 1.0 once the episode has run ``episode_length`` steps (Meta-World's truncation; tasks never terminate).
      metrics: the reward's components (Meta-World's info) and ``success``.
      info: ``success`` (1.0 where Meta-World's ``info["success"]`` is true), ``target_pos``, ``init_tcp`` and
        ``body_pos`` (the reset's draw), and with a time limit ``steps`` and ``truncation``.

    Its compiled MuJoCo model is ``mujoco_model``. The labelling page's clips, the training command's evaluation clip
    and ``rebel_jax.run.video`` draw its states from their ``qpos`` and :meth:`scene`
    (``rebel_jax.run.human.clips.MetaWorldRenderer``).

    Args:
      task: a key of :data:`TASKS`.
      episode_length: control steps per episode (Meta-World: 500); None for no time limit (brax's convention).
      goal_observable: the observation's last three numbers are the goal; False: zeros, as in the preference-RL
        code bases (Meta-World's default ``_partially_observable``).
    """

    reports_success = True
    """Its steps report ``success`` in ``info``: the trainer logs the episodes' success rates."""

    def __init__(
        self,
        task: str,
        episode_length: int | None = EPISODE_LENGTH,
        goal_observable: bool = True,
        impl: str = "jax",
        worlds: int = 1,
    ):
        if task not in TASKS:
            raise ValueError(f"unknown Meta-World task {task!r}; valid: {', '.join(TASKS)}")
        if episode_length is not None and episode_length < 1:
            raise ValueError(f"episode_length must be >= 1 or None; got {episode_length}")
        if impl not in IMPLS:
            raise ValueError(f"unknown physics impl {impl!r}; one of {', '.join(IMPLS)}")
        if worlds < 1:
            raise ValueError(f"worlds must be >= 1; got {worlds}")
        self.spec = TASKS[task]
        self.episode_length = episode_length
        self.goal_observable = goal_observable
        self.impl = impl
        self.mujoco_model = mj_model(task)
        m = self.mujoco_model
        self.step_refused = STEP_REFUSED[impl].get(task)
        self._warp_sys = self._warp_data0 = None
        if impl == "warp":  # the physics steps' engine; observations, rewards and resets keep the JAX one
            self._warp_sys = jax.tree.map(uncommitted, mjx.put_model(m, impl="warp"))
            # One buffer holds the contacts of every world of a vmapped step (mujoco 3.17 mjx/_src/io.py:907).
            self._warp_data0 = jax.device_get(
                mjx.make_data(m, impl="warp", naconmax=worlds * WARP_CONTACTS, njmax=WARP_CONSTRAINTS)
            )
        self._jax_collides = True
        try:
            self.sys, kinematic = mjx.put_model(m), m
        except NotImplementedError:  # collisions MJX lacks: its kinematics only, no contacts
            self._jax_collides = False
            kinematic = mujoco.MjModel.from_xml_path(str(ASSETS / "sawyer_xyz" / self.spec.xml))
            kinematic.geom_contype[:] = kinematic.geom_conaffinity[:] = 0
            self.sys = mjx.put_model(kinematic)
        self.hand_reset = hand_reset(task, m)
        start = self.hand_reset
        d0 = mjx.make_data(kinematic)
        self._data0 = jax.device_get(
            d0.replace(
                qpos=jnp.asarray(start.qpos, jnp.float32),
                qvel=jnp.asarray(start.qvel, jnp.float32),
                mocap_pos=jnp.asarray(start.mocap_pos, jnp.float32),
                mocap_quat=jnp.asarray(start.mocap_quat, jnp.float32),
                qacc_warmstart=jnp.asarray(start.qacc_warmstart, jnp.float32),
                ctrl=jnp.asarray((-1.0, 1.0), jnp.float32),  # the hand reset's last gripper command
            )
        )
        self._objects = self.spec.objects(m)
        self._goal = self.spec.goal(m)
        self._extra = self.spec.extra(m) if self.spec.extra else (lambda d: jnp.zeros(0))
        self._warp_touching = _warp_touching(m) if impl == "warp" and self.spec.contacts else None
        name = lambda kind, n: mujoco.mj_name2id(m, kind, n)  # noqa: E731
        self._hand = name(mujoco.mjtObj.mjOBJ_BODY, "hand")
        self._claws = (name(mujoco.mjtObj.mjOBJ_BODY, "rightclaw"), name(mujoco.mjtObj.mjOBJ_BODY, "leftclaw"))
        self._pads = (
            name(mujoco.mjtObj.mjOBJ_SITE, "rightEndEffector"),
            name(mujoco.mjtObj.mjOBJ_SITE, "leftEndEffector"),
        )
        moved = self.spec.moved_body
        self._moved_body = None if moved is None else name(mujoco.mjtObj.mjOBJ_BODY, moved)
        # init_tcp: the fingertips' centre where the reset's kinematics are (HandReset.shown_qpos), the same at every
        # reset (the arm's chain moves with no draw); float64 MuJoCo, once.
        shown = mujoco.MjData(m)
        shown.qpos[:] = self.hand_reset.shown_qpos
        mujoco.mj_kinematics(m, shown)
        self._init_tcp = ((shown.site_xpos[self._pads[0]] + shown.site_xpos[self._pads[1]]) / 2.0).astype(np.float32)
        low = np.concatenate([HAND_SPACE[0], [-1.0], np.full(OBJ_PADDED, -np.inf)])
        high = np.concatenate([HAND_SPACE[1], [1.0], np.full(OBJ_PADDED, np.inf)])
        goal_low = self.spec.hand_low if self.spec.goal_low is None else self.spec.goal_low
        goal_high = self.spec.hand_high if self.spec.goal_high is None else self.spec.goal_high
        self._obs_low = np.concatenate([low, low, goal_low]).astype(np.float32)
        self._obs_high = np.concatenate([high, high, goal_high]).astype(np.float32)

    # brax's Env properties.
    @property
    def observation_size(self) -> int:
        return 39

    @property
    def action_size(self) -> int:
        return 4

    @property
    def dt(self) -> float:
        return float(self.mujoco_model.opt.timestep) * FRAME_SKIP

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def unwrapped(self) -> MetaWorldEnv:
        return self

    def model(self, body_pos: jax.Array) -> mjx.Model:
        """The MJX model with the reset's moved body at ``body_pos`` (Meta-World moves it in the model); the model
        itself for a task whose reset moves no body (``TaskSpec.moved_body`` None)."""
        return self._moved(self.sys, body_pos)

    def _moved(self, sys: mjx.Model, body_pos: jax.Array) -> mjx.Model:
        """``sys`` (the JAX or the Warp model) with the reset's moved body at ``body_pos``; ``sys`` itself where the
        reset moves no body."""
        if self._moved_body is None:
            return sys
        return sys.replace(body_pos=sys.body_pos.at[self._moved_body].set(body_pos))

    def current(self, d: mjx.Data) -> jax.Array:
        """The observation's first 18 numbers at ``d`` (kinematics current): Meta-World's
        ``_get_curr_obs_combined_no_goal`` (sawyer_xyz_env.py:475-511)."""
        right, left = self._claws
        opening = jnp.clip(jnp.linalg.norm(d.xpos[right] - d.xpos[left]) / 0.1, 0.0, 1.0)
        pos, quat = self._objects(d)
        k = pos.shape[0] // 3  # each object's position, then its quaternion (sawyer_xyz_env.py:500-510)
        poses = [x for i in range(k) for x in (pos[3 * i : 3 * i + 3], quat[4 * i : 4 * i + 4])]
        padding = jnp.zeros(OBJ_PADDED - 7 * k)
        return jnp.concatenate([d.xpos[self._hand], opening[None], *poses, padding])

    def tcp_center(self, d: mjx.Data) -> jax.Array:
        """The fingertips' centre (``tcp_center``, sawyer_xyz_env.py:71-81)."""
        return (d.site_xpos[self._pads[0]] + d.site_xpos[self._pads[1]]) / 2.0

    def observation(self, current: jax.Array, previous: jax.Array, target: jax.Array, clip: bool = True) -> jax.Array:
        """The 39 numbers: ``current``, ``previous``, the goal (zeros unless ``goal_observable``), clipped to
        Meta-World's observation space as its ``step`` clips them (sawyer_xyz_env.py:513-527, 620-628); the reset's
        observation is not clipped (``clip=False``)."""
        goal = target if self.goal_observable else jnp.zeros(3)
        obs = jnp.concatenate([current, previous, goal])
        if not clip:
            return obs
        low, high = self._obs_low, self._obs_high
        if not self.goal_observable:
            low, high = low.copy(), high.copy()
            low[-3:] = high[-3:] = 0.0
        return jnp.clip(obs, low, high)

    def _observe(
        self,
        d: mjx.Data,
        m: mjx.Model,
        previous: jax.Array | None,
        info: dict,
        done: jax.Array,
        action: jax.Array,
        shown=None,
        current: bool = False,
        touching: jax.Array | None = None,
    ) -> State:
        # After a step Meta-World runs mj_forward; the kinematics suffice unless the reward's info reads contacts
        # (``touching``: Warp's forward has read them).
        contacts = self.spec.contacts and previous is not None and self._jax_collides and touching is None
        if contacts:
            with _cpu_cholesky():
                d = mjx.forward(m, d)
        elif not current:  # ``current``: the caller has run the kinematics
            d = mjx.kinematics(m, d)
        current = self.current(d if shown is None else shown)
        clip = previous is not None
        obs = self.observation(current, current if previous is None else previous, info["target_pos"], clip)
        # The reward reads the goal itself, not the observation's (zeros when the goal is hidden).
        extra = self._extra(d) if touching is None else self._extra(d, touching)
        context = Context(self.tcp_center(d), info["target_pos"], info["init_tcp"], info["consts"], action, extra)
        reward, metrics = self.spec.reward(obs.at[36:].set(info["target_pos"]), context)
        if previous is None:  # Meta-World's reset returns no reward
            reward = jnp.zeros(())
        metrics = {k: v.astype(jnp.float32) for k, v in metrics.items()}
        info = dict(info, success=metrics["success"])
        return State(d, obs, reward.astype(jnp.float32), done, metrics, info)

    def state_at(
        self,
        qpos: jax.Array,
        qvel: jax.Array,
        mocap_pos: jax.Array,
        mocap_quat: jax.Array,
        qacc_warmstart: jax.Array,
        previous: jax.Array,
        episode: dict[str, jax.Array],
        action: jax.Array,
    ) -> State:
        """The ``State`` at a given MuJoCo state of an episode (as after a ``step``), for comparisons with Meta-World.

        Args:
          qpos, qvel, mocap_pos, mocap_quat, qacc_warmstart: the MuJoCo state.
          previous: the previous observation's first 18 numbers.
          episode: the episode's reset's ``info`` (``body_pos``, ``target_pos``, ``init_tcp``, ``consts``).
          action: the action of the step that led there (door-open's reward reads it).

        Returns:
          The state, with the observation, reward and success Meta-World's ``step`` returns there.
        """
        d = jax.tree.map(lambda x: jnp.asarray(x) if isinstance(x, np.ndarray) else x, self._data0)
        d = d.replace(qpos=qpos, qvel=qvel, mocap_pos=mocap_pos, mocap_quat=mocap_quat, qacc_warmstart=qacc_warmstart)
        info = {k: episode[k] for k in ("target_pos", "init_tcp", "body_pos", "consts")}
        zero = jnp.zeros(())
        if self.episode_length is not None:
            info.update(steps=jnp.ones((), jnp.int32), truncation=zero)
        touching = None
        if self._warp_touching is not None:  # as ``step`` reads the contacts under Warp
            touching = self._warp_touching(mjx.forward(*self._to_warp(d, info["body_pos"])))
        return self._observe(d, self.model(info["body_pos"]), previous, info, zero, action, touching=touching)

    def scene(self, state: State) -> jax.Array:
        """What a clip's frame of ``state`` needs beyond its ``qpos`` (:func:`frame_scene`; any leading batch axes)."""
        return frame_scene(self.spec, state)

    def draw(self, rng: jax.Array) -> jax.Array:
        """A uniform draw of the task's reset space (``_get_state_rand_vec``, sawyer_xyz_env.py:697-719), drawn
        again until ``TaskSpec.accept`` holds where the task has such a loop."""
        low, high = np.asarray(self.spec.reset_low), np.asarray(self.spec.reset_high)
        uniform = lambda key: low + jax.random.uniform(key, low.shape) * (high - low)  # noqa: E731
        if self.spec.accept is None:
            return uniform(rng)
        accept = self.spec.accept

        def again(carry: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
            key, sub = jax.random.split(carry[0])
            return key, uniform(sub)

        key, sub = jax.random.split(rng)
        return jax.lax.while_loop(lambda c: ~accept(c[1]), again, (key, uniform(sub)))[1]

    def start(self, rand_vec: jax.Array) -> mjx.Data:
        """The reset's MuJoCo state for the draw ``rand_vec``: the hand's reset state (:class:`HandReset`), with a
        free object's position at the draw where the task places it so (``TaskSpec.object_qpos``: sweep-into's x and
        y, hammer's x, y and z)."""
        d = jax.tree.map(lambda x: jnp.asarray(x) if isinstance(x, np.ndarray) else x, self._data0)
        n = self.spec.object_qpos
        if n:
            d = d.replace(qpos=d.qpos.at[9 : 9 + n].set(rand_vec[:n].astype(d.qpos.dtype)))
        return d

    def reset(self, rng: jax.Array) -> State:
        """Draws the object (and goal) uniformly in the task's reset space, the hand at its reset state.

        As Meta-World's ``reset`` (sawyer_xyz_env.py:664-682) runs ``reset_model`` twice and, unless the task's
        ``reset_model`` ends with ``set_state`` (``TaskSpec.reset_forward``), observes without a ``mj_forward``, its
        observation shows the hand one physics step back (:class:`HandReset`) and the object where the first of two
        independent draws put it; the episode runs with the second. ``init_tcp`` is one physics step back always.
        """
        shown_key, key = jax.random.split(rng)
        return self.reset_to(self.draw(key), self.draw(shown_key))

    def reset_to(self, rand_vec: jax.Array, shown_vec: jax.Array) -> State:
        """The reset state of the draw ``rand_vec``, its observation showing the object at ``shown_vec``."""
        m = self.model(rand_vec)
        d = mjx.kinematics(m, self.start(rand_vec))
        target, consts = self._goal(rand_vec, d)
        init_tcp = jnp.asarray(self._init_tcp)
        info = {"target_pos": target, "init_tcp": init_tcp, "body_pos": rand_vec, "consts": consts}
        zero = jnp.zeros(())
        if self.episode_length is not None:
            info.update(steps=jnp.zeros((), jnp.int32), truncation=zero)
        shown = None
        if not self.spec.reset_forward:
            stale = d.replace(qpos=jnp.asarray(self.hand_reset.shown_qpos, d.qpos.dtype))
            shown = mjx.kinematics(self.model(shown_vec), stale)
            if self.spec.shown_consts is not None:
                info["consts"] = jnp.concatenate([consts, self.spec.shown_consts(self.mujoco_model)(shown)])
        return self._observe(d, m, None, info, zero, jnp.zeros(4), shown=shown, current=True)

    def _physics_steps(self, m: mjx.Model, d: mjx.Data, body_pos: jax.Array) -> tuple[mjx.Data, jax.Array | None]:
        """The control step's :data:`FRAME_SKIP` physics steps from ``d`` under ``m`` (the JAX step), or under the
        Warp model with the reset's moved body at ``body_pos`` (``impl='warp'``): what a step carries over
        (:data:`STEP_STATE`) goes to a Warp data and comes back with the step's accelerations. Also, where the
        reward reads contact forces under Warp, ``touching`` from Warp's ``forward`` of the stepped state (else
        None)."""
        if self.impl == "jax":
            with _cpu_cholesky():
                return jax.lax.fori_loop(0, FRAME_SKIP, lambda _, x: mjx.step(m, x), d), None
        w_m, w = self._to_warp(d, body_pos)
        w = jax.lax.fori_loop(0, FRAME_SKIP, lambda _, x: mjx.step(w_m, x), w)
        touching = None if self._warp_touching is None else self._warp_touching(mjx.forward(w_m, w))
        return d.replace(**{f: getattr(w, f) for f in (*STEP_STATE, "qacc")}), touching

    def _to_warp(self, d: mjx.Data, body_pos: jax.Array) -> tuple[mjx.Model, mjx.Data]:
        """The Warp model with the reset's moved body at ``body_pos``, and a Warp data holding what a step carries
        over from ``d`` (:data:`STEP_STATE`, and the moved body's geoms' poses)."""
        carried = (*STEP_STATE, *STATIC_POSES) if self._moved_body is not None else STEP_STATE
        # MJX broadcasts a Warp data's unbatched fields to the vmapped batch but not its model's, and Warp reads world
        # w's batched model field at w % its batch (mujoco 3.17 mjx/warp/ffi.py:346-362, 415-440): a reset's body
        # position unbatched on an axis where the step's data is batched (one reset stepped under several actions)
        # would put another reset's body in most worlds. Both branches are the position: only the batch follows.
        fields = [getattr(d, f) for f in carried if getattr(d, f).size]
        tie = functools.reduce(jnp.logical_or, [jnp.ravel(x)[:1] > 0 for x in fields])
        w_m = self._moved(self._warp_sys, jnp.where(tie, body_pos, body_pos))
        return w_m, jax.tree.map(traced_constant, self._warp_data0).replace(**{f: getattr(d, f) for f in carried})

    def build_warp_kernels(self) -> None:
        """Builds and loads MuJoCo Warp's kernels for this model before a program steps it (``impl='warp'``;
        nothing for ``jax``), as :meth:`rebel_jax.envs.dmc.DMCEnv.build_warp_kernels` does."""
        if self.impl == "warp":
            build_warp_kernels(self.mujoco_model)

    def step(self, state: State, action: jax.Array) -> State:
        """Moves the mocap by ``action[:3]`` cm (clipped to [-1, 1] and to the hand's bounds), sets the gripper to
        ``action[3]`` and runs 5 physics steps (sawyer_xyz_env.py:580-640). On the CPU, MJX's Cholesky
        factorizations run in plain JAX operations (``_mjx.plain_cholesky``), as :class:`~rebel_jax.envs.dmc.DMCEnv`
        runs them."""
        if self.step_refused:
            raise ValueError(refusal(self.spec.name, self.impl))
        if action.shape != (4,):
            raise ValueError(f"{self.spec.name}: action must have shape (4,), got {action.shape}")
        d = state.pipeline_state
        m = self.model(state.info["body_pos"])
        delta = jnp.clip(action[:3], -1.0, 1.0) * ACTION_SCALE
        mocap = jnp.clip(d.mocap_pos[0] + delta, jnp.array(self.spec.hand_low), jnp.array(self.spec.hand_high))
        d = d.replace(
            mocap_pos=mocap[None].astype(d.mocap_pos.dtype),
            mocap_quat=jnp.array([MOCAP_QUAT], d.mocap_quat.dtype),
            ctrl=jnp.stack([action[3], -action[3]]).astype(d.ctrl.dtype),
        )
        d, touching = self._physics_steps(m, d, state.info["body_pos"])
        info = dict(state.info)
        done = jnp.zeros_like(state.done)
        if self.episode_length is not None:
            info["steps"] = state.info["steps"] + 1
            done = (info["steps"] >= self.episode_length).astype(jnp.float32)
            info["truncation"] = done
        return self._observe(d, m, state.obs[:18], info, done, action, touching=touching)


def make_env(
    name: str,
    episode_length: int | None = EPISODE_LENGTH,
    goal_observable: bool = True,
    impl: str = "jax",
    worlds: int = 1,
) -> MetaWorldEnv:
    """Builds ``metaworld_<task>`` (see :class:`MetaWorldEnv`)."""
    return MetaWorldEnv(name.removeprefix(PREFIX), episode_length, goal_observable, impl, worlds)
