"""dm_control's quadruped ``Move`` task (walk and run) in JAX: its observation, reward and reset pose.

The task is dm_control 1.0.50's ``suite/quadruped.py``: ``walk`` and ``run`` are ``Move`` with desired
speeds 0.5 and 5 m/s, on ``make_model(floor_size=20 * speed)`` (:func:`rebel_jax.envs.models.quadruped_xml`).

- Observation (78 numbers, dm_control's order): ``egocentric_state`` (the 16 hinge angles, their 16
  velocities and the 12 actuator activations), ``torso_velocity`` (velocimeter at the torso site, in its
  frame), ``torso_upright`` (the torso's zz orientation entry), ``imu`` (accelerometer then gyro at the
  torso site) and ``force_torque`` (``arcsinh`` of the 4 toe force sensors, then the 4 toe torque sensors).
- Reward: ``upright * move``: ``upright = tolerance(zz, (1, inf), margin=2, linear, value_at_margin=0)``,
  i.e. ``(1 + zz) / 2``, and ``move = tolerance(vx, (speed, inf), margin=speed, linear, value_at_margin=0.5)``
  of the velocimeter's forward (torso x) component.
- Reset: a uniformly random orientation (a normalised 4-d Gaussian quaternion), the joints at their zero
  angles, at rest, at the lowest height of the 1 cm grid 0, 0.01, 0.02, ... at which nothing touches
  (``_find_non_contacting_height``); see :func:`pose_sampler`.

MJX 3.17 computes all five sensor types of the model (accelerometer, gyro, velocimeter, force, torque), every
geom pair it collides (plane, sphere, capsule, ellipsoid, cylinder) and the fixed tendons, their equality
constraints and the tendon actuators. Sensor timing follows dm_control's stepping (``mj_step2``, then
``mj_step1`` at the new state): the velocity sensors are read at the new state, the acceleration and force
sensors as the last physics substep computed them (``DMCEnv``, ``TaskSpec.sensors``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from rebel_jax.envs.rewards import tolerance

WALK_SPEED = 0.5
RUN_SPEED = 5.0
TIME_LIMIT = 20.0
"""Seconds per episode: 1000 control steps of 0.02 s."""
CONTROL_SUBSTEPS = 4
"""Physics steps (0.005 s) per control step (dm_control's control timestep, 0.02 s)."""
HEIGHT_STEP = 0.01
"""The reset's height grid (dm_control raises the body in 1 cm increments)."""
OBS_SIZE = 78

_TORSO = 1  # body index
# qpos: the free joint (7), then the 16 hinges; qvel: 6, then 16.
_HINGE_QPOS = slice(7, 23)
_HINGE_QVEL = slice(6, 22)
# sensordata addresses (tests/test_envs_quadruped.py checks them against the model's sensors by name).
_ACCELEROMETER = slice(0, 3)
_GYRO = slice(3, 6)
_VELOCIMETER = slice(6, 9)
_TOE_FORCE_TORQUE = slice(9, 33)  # 4 force sensors, then 4 torque sensors


def observation(d: mjx.Data) -> jax.Array:
    """The 78-number observation of ``d``, whose sensors are current (see the module docstring)."""
    return jnp.concatenate(
        [
            d.qpos[_HINGE_QPOS],
            d.qvel[_HINGE_QVEL],
            d.act,
            d.sensordata[_VELOCIMETER],
            d.xmat[_TORSO, 2, 2:3],
            d.sensordata[_ACCELEROMETER],
            d.sensordata[_GYRO],
            jnp.arcsinh(d.sensordata[_TOE_FORCE_TORQUE]),
        ]
    )


def move_reward(speed: float) -> Callable[[mjx.Data], tuple[jax.Array, dict[str, jax.Array]]]:
    """dm_control's ``Move.get_reward`` at desired speed ``speed``: ``(reward, metrics)`` of data ``d``."""

    def reward_fn(d: mjx.Data):
        zz = d.xmat[_TORSO, 2, 2]
        forward = d.sensordata[_VELOCIMETER][0]
        upright = tolerance(zz, bounds=(1.0, jnp.inf), margin=2.0, value_at_margin=0.0, sigmoid="linear")
        move = tolerance(forward, bounds=(speed, jnp.inf), margin=speed, value_at_margin=0.5, sigmoid="linear")
        metrics = {"upright": upright, "move_reward": move, "torso_upright": zz, "forward_velocity": forward}
        return upright * move, metrics

    return reward_fn


def _quat_to_mat(q: jax.Array) -> jax.Array:
    """The rotation matrix of unit quaternion ``q`` (w, x, y, z)."""
    w, x, y, z = q
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _body_geoms(m: mujoco.MjModel) -> dict[str, np.ndarray]:
    """The body's geoms (all but the world's) at the zero pose with the root at the origin, unrotated:
    type, size, centre and rotation in the root frame."""
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0
    d.qpos[:7] = [0, 0, 0, 1, 0, 0, 0]
    mujoco.mj_kinematics(m, d)
    body = np.nonzero(m.geom_bodyid != 0)[0]
    supported = {int(t) for t in (mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_CAPSULE)} | {
        int(mujoco.mjtGeom.mjGEOM_CYLINDER),
        int(mujoco.mjtGeom.mjGEOM_ELLIPSOID),
    }
    unknown = {int(t) for t in m.geom_type[body]} - supported
    if unknown:
        raise ValueError(f"the reset's height search has no support function for geom types {sorted(unknown)}")
    return {
        "type": m.geom_type[body].copy(),
        "size": m.geom_size[body].copy(),
        "pos": d.geom_xpos[body].copy(),
        "mat": d.geom_xmat[body].reshape(-1, 3, 3).copy(),
    }


def _depth_below_centre(kind: int, size: jax.Array, up: jax.Array) -> jax.Array:
    """How far a geom reaches below its centre along the world's z axis, ``up`` in the geom's frame (the
    support function of each shape in direction -z)."""
    radial = jnp.sqrt(up[0] ** 2 + up[1] ** 2)
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return size[0] + 0 * up[2]
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return size[0] + size[1] * jnp.abs(up[2])
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return size[0] * radial + size[1] * jnp.abs(up[2])
    return jnp.sqrt(jnp.sum((size * up) ** 2))  # ellipsoid


def lowest_point(geoms: dict[str, np.ndarray], rotation: jax.Array) -> jax.Array:
    """The lowest z of any of ``geoms`` (:func:`_body_geoms`) when the root, at the origin, has ``rotation``."""
    up = rotation[2]  # the world's z axis in the root frame
    lows = []
    for kind in np.unique(geoms["type"]):
        sel = geoms["type"] == kind
        centre_z = jnp.asarray(geoms["pos"][sel]) @ up
        up_local = jnp.einsum("gij,i->gj", jnp.asarray(geoms["mat"][sel]), up)
        depth = jax.vmap(functools.partial(_depth_below_centre, int(kind)))(jnp.asarray(geoms["size"][sel]), up_local)
        lows.append(centre_z - depth)
    return jnp.min(jnp.concatenate(lows))


def non_contacting_height(geoms: dict[str, np.ndarray], rotation: jax.Array) -> jax.Array:
    """dm_control's ``_find_non_contacting_height`` for the joints' zero pose: the first of the heights 0, 0.01,
    0.02, ... at which no geom reaches the floor (the zero pose has no self-contacts; tests check both).

    dm_control raises the body 1 cm at a time and runs MuJoCo's collision detection at each height. The floor
    is a plane at z = 0 and the body moves rigidly, so the first free height follows from the body's lowest
    point at height 0: a closed form, the same grid point, with no loop.
    """
    reach = -lowest_point(geoms, rotation)  # > 0: the body starts embedded in the floor
    steps = jnp.maximum(jnp.floor(reach / HEIGHT_STEP) + 1, 0)
    return steps * HEIGHT_STEP


def pose_sampler(m: mujoco.MjModel) -> Callable[[jax.Array], jax.Array]:
    """``key -> qpos`` of dm_control's ``Move.initialize_episode``: a random orientation (a normalised 4-d
    standard normal, as ``random.randn(4)``), the joints at ``qpos0`` (zero), raised to the first height with
    no contact."""
    geoms = _body_geoms(m)
    qpos0 = jnp.asarray(m.qpos0, jnp.float32)

    def sample(key: jax.Array) -> jax.Array:
        q = jax.random.normal(key, (4,))
        q = q / jnp.linalg.norm(q)
        z = non_contacting_height(geoms, _quat_to_mat(q))
        return qpos0.at[2].set(z).at[3:7].set(q)

    return sample
