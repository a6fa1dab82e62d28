"""DeepMind-Control-equivalent walker, cheetah and quadruped tasks on MJX.

Each task is a ``brax.envs.Env`` with brax's ``State``: a pure ``reset(key) -> State`` and
``step(state, action) -> State``, jittable and vmappable. Observations, rewards,
reset distributions, control and physics time steps and the 1000-step episode are
dm_control's (suite ``walker.py``, ``cheetah.py`` and ``quadruped.py``); the tests compare them with
dm_control on the same physics states.

References:
  Tassa et al., "DeepMind Control Suite", 2018 (arXiv:1801.00690).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.util
from collections.abc import Callable
from typing import Literal

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.base import Env, State
from mujoco import mjx

from rebel_jax.envs import models, quadruped
from rebel_jax.envs._mjx import (
    build_warp_kernels,
    mujoco_contact_frames,
    newton_trips,
    plain_cholesky,
    traced_constant,
    uncommitted,
)
from rebel_jax.envs.rewards import tolerance


@dataclasses.dataclass(frozen=True)
class Solver:
    """MJX constraint-solver settings.

    Attributes:
      iterations: maximum Newton iterations per physics step (MuJoCo default 100).
      ls_iterations: maximum line-search iterations per Newton iteration (default 50).
      tolerance: the solver stops early once the relative cost improvement is below
        it (MuJoCo default 1e-8; under ``vmap`` the loop runs until every member stops).
      eulerdamp: integrate joint damping implicitly in the Euler integrator, as
        MuJoCo does by default (MuJoCo Playground turns it off).
      newton_loop: how the Newton iterations run in the compiled program, with the same results:
        ``while``, MJX's ``while_loop`` (stops once every member has stopped; on a GPU it reads its
        predicate back to the host on every trip); ``trips``, a loop of ``iterations`` trips
        (``_mjx.newton_trips``); ``unrolled``, those trips unrolled.
    """

    iterations: int
    ls_iterations: int
    tolerance: float = 1e-8
    eulerdamp: bool = True
    newton_loop: Literal["while", "trips", "unrolled"] = "while"

    def __post_init__(self):
        if self.iterations < 1 or self.ls_iterations < 1:
            raise ValueError(f"solver iterations and ls_iterations must be >= 1; got {self}")
        if not self.tolerance >= 0:
            raise ValueError(f"solver tolerance must be >= 0; got {self.tolerance}")
        if self.newton_loop not in NEWTON_LOOPS:
            raise ValueError(f"solver newton_loop must be one of {', '.join(NEWTON_LOOPS)}; got {self.newton_loop!r}")


NEWTON_LOOPS = ("while", "trips", "unrolled")


SOLVERS: dict[str, Solver] = {
    # dm_control's own settings (MuJoCo's defaults).
    "dm_control": Solver(iterations=100, ls_iterations=50),
    # Our default, chosen by speed and fidelity: see BENCHMARKS.md ("Choice of solver").
    "default": Solver(iterations=4, ls_iterations=8),
}


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """What distinguishes one task: its model, time steps, reset, observation and reward.

    Attributes:
      randomize_rotational: the reset also draws unlimited hinges uniformly in [-pi, pi]
        (dm_control's ``randomize_limited_and_rotational_joints``, walker); otherwise only
        limited joints are drawn, in their range (dm_control's cheetah).
      pose_sampler: given the compiled model, a pure ``key -> qpos`` that replaces the joint-range draw
        above (the quadruped's random orientation at a contact-free height); None: the joint-range draw.
      sensors: the observation or reward reads MuJoCo sensors (``sensordata``). The reset then runs
        ``mjx.forward`` once, so that the acceleration and force sensors hold the reset state's values, as
        after dm_control's ``mj_forward``; each observation recomputes the position and velocity sensors at
        the new state, as dm_control's closing ``mj_step1`` does, and keeps the acceleration and force
        sensors of the last physics substep, as dm_control's ``mj_step2`` leaves them.
      has_pixels: the pure-JAX camera (:mod:`rebel_jax.envs.render`) draws every geom of the model, so the task has
        a pixel version (``<task>_pixels``).
      mujoco_frames: collide planes and capsules with MuJoCo's contact frames (``_mjx.mujoco_contact_frames``)
        instead of MJX's, which differ for capsules near the plane's normal: needed in 3-D (the quadruped);
        in a planar model (walker, cheetah) both frames span the same friction pyramid.
      never_near: body pairs whose geoms the simulation leaves out of its collision checks (unless
        ``all_contacts``), as excluded pairs of the model. MuJoCo's C engine tests a pair only once its bounding
        boxes overlap; MJX tests every pair at every physics step. The quadruped's lower legs against its torso
        and eyes are 36 geom pairs that MJX computes by 10 steps of gradient descent each (its SDF colliders),
        about two thirds of the quadruped's step on a CPU, and in dm_control their bounding boxes never overlapped
        under random actions (tests/test_envs_quadruped.py), so leaving them out changes no step seen there.
    """

    name: str
    xml: Callable[[], str]
    total_mass: float | None
    n_substeps: int
    settle_steps: int
    obs_size: int
    obs_fn: Callable[[mjx.Data], jax.Array]
    reward_fn: Callable[[mjx.Data], tuple[jax.Array, dict[str, jax.Array]]]
    randomize_rotational: bool
    pose_sampler: Callable[[mujoco.MjModel], Callable[[jax.Array], jax.Array]] | None = None
    sensors: bool = False
    has_pixels: bool = True
    mujoco_frames: bool = False
    never_near: tuple[tuple[str, str], ...] = ()


def _observed(d: mjx.Data, m: mjx.Model, sensors: bool = False) -> mjx.Data:
    """Position and velocity quantities of ``d``'s current qpos/qvel.

    ``mjx.step`` leaves kinematics at the pre-integration state; dm_control (legacy
    stepping) observes after ``mj_step1``, i.e. at the new state. This recomputes
    only what the observations and rewards read (no collision or constraint solve);
    with ``sensors``, also the position and velocity sensors (``mj_step1`` computes them; the
    acceleration and force sensors keep the values of the last ``mjx.step``, as ``mj_step2`` left them).
    """
    d = mjx.kinematics(m, d)
    d = mjx.com_pos(m, d)
    d = mjx.com_vel(m, d)
    d = mjx.subtree_vel(m, d)
    if sensors:
        d = mjx.sensor_vel(m, mjx.sensor_pos(m, d))
    return d


# Body index 1 is the torso in both models; index 0 is the world.
_TORSO = 1


def _torso_subtree_linvel_x(d: mjx.Data) -> jax.Array:
    return d._impl.subtree_linvel[_TORSO, 0]


def _walker_obs(d: mjx.Data) -> jax.Array:
    orientations = d.xmat[1:].reshape(-1, 9)[:, jnp.array([0, 2])].ravel()  # xx, xz
    return jnp.concatenate([orientations, d.xpos[_TORSO, 2:3], d.qvel])


def _walker_reward(move_speed: float):
    stand_height = 1.2

    def reward_fn(d: mjx.Data):
        height = d.xpos[_TORSO, 2]
        upright = (1.0 + d.xmat[_TORSO, 2, 2]) / 2.0
        standing = tolerance(height, bounds=(stand_height, jnp.inf), margin=stand_height / 2)
        stand = (3.0 * standing + upright) / 4.0
        velocity = _torso_subtree_linvel_x(d)
        metrics = {
            "standing": standing,
            "upright": upright,
            "stand_reward": stand,
            "torso_height": height,
            "horizontal_velocity": velocity,
        }
        if move_speed == 0:
            return stand, metrics
        move = tolerance(
            velocity,
            bounds=(move_speed, jnp.inf),
            margin=move_speed / 2,
            value_at_margin=0.5,
            sigmoid="linear",
        )
        metrics["move_reward"] = move
        return stand * (5.0 * move + 1.0) / 6.0, metrics

    return reward_fn


def _cheetah_obs(d: mjx.Data) -> jax.Array:
    return jnp.concatenate([d.qpos[1:], d.qvel])


def _cheetah_reward(d: mjx.Data):
    speed = _torso_subtree_linvel_x(d)
    reward = tolerance(speed, bounds=(10.0, jnp.inf), margin=10.0, value_at_margin=0.0, sigmoid="linear")
    return reward, {"speed": speed}


def _walker(name: str, move_speed: float) -> TaskSpec:
    return TaskSpec(
        name, models.walker_xml, None, 10, 0, 24, _walker_obs, _walker_reward(move_speed), randomize_rotational=True
    )


def _quadruped(name: str, speed: float) -> TaskSpec:
    """dm_control's quadruped ``walk`` or ``run`` (``Move`` at ``speed``) on ``make_model(floor_size=20 * speed)``."""
    return TaskSpec(
        name,
        functools.partial(models.quadruped_xml, quadruped.TIME_LIMIT * speed),
        None,
        quadruped.CONTROL_SUBSTEPS,
        0,
        quadruped.OBS_SIZE,
        quadruped.observation,
        quadruped.move_reward(speed),
        randomize_rotational=False,
        pose_sampler=quadruped.pose_sampler,
        sensors=True,
        has_pixels=False,  # ellipsoid and cylinder geoms, which the pure-JAX camera does not draw
        mujoco_frames=True,
        never_near=tuple(
            ("torso", f"{part}_{leg}") for leg, _, _ in models.QUADRUPED_LEGS for part in ("knee", "ankle", "toe")
        ),
    )


TASKS: dict[str, TaskSpec] = {
    "walker_stand": _walker("walker_stand", 0.0),
    "walker_walk": _walker("walker_walk", 1.0),
    "walker_run": _walker("walker_run", 8.0),
    "cheetah_run": TaskSpec(
        "cheetah_run",
        models.cheetah_xml,
        models.CHEETAH_TOTAL_MASS,
        1,
        200,
        17,
        _cheetah_obs,
        _cheetah_reward,
        randomize_rotational=False,
    ),
    "quadruped_walk": _quadruped("quadruped_walk", quadruped.WALK_SPEED),
    "quadruped_run": _quadruped("quadruped_run", quadruped.RUN_SPEED),
}


def mj_model(task: str, solver: Solver | None = None, simulated: bool = False) -> mujoco.MjModel:
    """The compiled MuJoCo model of ``task`` (dm_control's), with ``solver``'s options applied; ``simulated``: with
    the task's ``never_near`` body pairs excluded, the model :class:`DMCEnv` simulates by default."""
    spec = TASKS[task]
    model = models.compile_model(spec.xml(), spec.total_mass, spec.never_near if simulated else ())
    if solver is not None:
        model.opt.iterations = solver.iterations
        model.opt.ls_iterations = solver.ls_iterations
        model.opt.tolerance = solver.tolerance
        if not solver.eulerdamp:
            model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    return model


class DMCEnv(Env):
    """A dm_control-equivalent task on MJX, a ``brax.envs.Env``.

    Its ``State`` (brax's) holds:
      pipeline_state: the MJX physics data, kinematics current.
      obs: the observation.
      reward: the task's true reward for the last transition.
      done: 1.0 when the episode has ended (only by the time limit: these tasks never terminate).
      metrics: reward components and physical quantities behind the reward.
      info: ``steps`` (control steps in this episode, int32) and ``truncation`` (1.0 when the
        episode ended by the time limit rather than by termination, so always ``done`` here);
        other keys (a wrapper's) are carried through ``step`` unchanged.

    Use :func:`rebel_jax.envs.make_env` to build one. With ``episode_length=None`` the task has
    no time limit and keeps no ``steps``/``truncation`` in ``info`` (``done`` stays 0): brax's
    convention, where ``brax.envs.wrappers.training.EpisodeWrapper`` adds the time limit. The
    tasks registered with brax (``rebel_walker_walk``, ...; see :mod:`rebel_jax.envs.registry`)
    are built so.
    """

    def __init__(
        self,
        task: str,
        solver: Solver,
        episode_length: int | None = 1000,
        unroll_substeps: bool = False,
        all_contacts: bool = False,
        impl: str = "jax",
        worlds: int = 1,
    ):
        if episode_length is not None and episode_length < 1:
            raise ValueError(f"episode_length must be >= 1 or None; got {episode_length}")
        if worlds < 1:
            raise ValueError(f"worlds must be >= 1; got {worlds}")
        check_impl(impl)
        self.spec = TASKS[task]
        self.impl = impl
        self.solver = solver
        self.episode_length = episode_length
        self.unroll_substeps = unroll_substeps
        self.mj_model = mj_model(task, solver, simulated=not all_contacts)
        # ``mjx.put_model`` and ``mjx.make_data`` commit their arrays to the first device
        # (``jax.device_put(..., jax.devices()[0])``, mujoco 3.17 mjx/_src/io.py:463 and :771). Traced into
        # the programs that ``shard_map`` runs on every GPU, such arrays pin each device's part to the
        # first GPU, and XLA crashed (a segfault on 2 GPUs). The model's arrays are kept uncommitted (they
        # follow the program to every device), and ``reset`` builds on a host template of the data. Both are
        # built on this process's first device: with several processes (``--distributed``) the first device
        # of ``jax.devices()`` belongs to process 0, and another process cannot read it back.
        local = jax.local_devices()[0]
        self.sys = jax.tree.map(uncommitted, mjx.put_model(self.mj_model, device=local))
        self._data0 = jax.device_get(mjx.make_data(self.sys, device=local))
        if impl == "warp":  # the physics steps' engine; observations and rewards keep the JAX one (_warp_steps)
            model = mjx.put_model(self.mj_model, device=local, impl="warp")
            # The solver's iteration caps are this project's setting (Solver), not an overflow to print at every
            # step; buffer overflows (contacts, constraints) still print.
            flags = _warp_overflow()
            quiet = model.opt._impl.warn_overflow & ~(flags.ITERATIONS | flags.LS_ITERATIONS)
            model = model.replace(opt=model.opt.replace(_impl=model.opt._impl.replace(warn_overflow=quiet)))
            self._warp_sys = jax.tree.map(uncommitted, model)
            # MuJoCo Warp keeps the contacts of every world of a vmapped step in one buffer of ``naconmax`` rows
            # (mujoco 3.17 mjx/_src/io.py:907); MJX sizes it for one world. Contacts past it are dropped, and
            # the physics goes wrong, so it holds ``worlds`` times one world's default.
            one = mjx.make_data(self.mj_model, device=local, impl="warp")
            self._warp_data0 = jax.device_get(
                mjx.make_data(self.mj_model, device=local, impl="warp", naconmax=worlds * one._impl.naconmax)
            )
        m = self.mj_model
        # Reset: limited joints uniform in their range; unlimited hinges uniform in
        # [-pi, pi] where the task says so (walker; dm_control's cheetah leaves its root
        # hinge upright); everything else (unlimited slides) left at qpos0.
        low = np.array(m.qpos0, dtype=np.float32)
        high = low.copy()
        for j in range(m.njnt):
            adr = m.jnt_qposadr[j]
            if m.jnt_limited[j]:
                low[adr], high[adr] = m.jnt_range[j]
            elif self.spec.randomize_rotational and m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                low[adr], high[adr] = -np.pi, np.pi
        self._reset_low, self._reset_high = jnp.asarray(low), jnp.asarray(high)
        self._sample_pose = self.spec.pose_sampler(m) if self.spec.pose_sampler else None
        # Actions in [-1, 1] map linearly onto each actuator's control range, as dmc2gym (B-Pref, PEBBLE, SURF)
        # and DrQ-v2's action-scale wrapper map them; the identity where every range is [-1, 1] (walker, cheetah).
        ctrl_low, ctrl_high = (np.asarray(m.actuator_ctrlrange[:, i], np.float32) for i in (0, 1))
        self._ctrl_range = None if np.all(ctrl_low == -1) and np.all(ctrl_high == 1) else (ctrl_low, ctrl_high)

    # brax's Env properties.
    @property
    def observation_size(self) -> int:
        return self.spec.obs_size

    @property
    def action_size(self) -> int:
        return self.mj_model.nu

    @property
    def dt(self) -> float:
        return float(self.mj_model.opt.timestep) * self.spec.n_substeps

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def unwrapped(self) -> DMCEnv:
        return self

    def _solved(self, fn: Callable[[mjx.Data], mjx.Data], d: mjx.Data) -> mjx.Data:
        """``fn(d)``, traced with the solver's Newton loop (``Solver.newton_loop``), where the task says so
        MuJoCo's contact frames (``TaskSpec.mujoco_frames``), and on the CPU with Cholesky factorizations in plain
        JAX operations (``_mjx.plain_cholesky``: jaxlib's CPU LAPACK calls can hang on large batches)."""
        with contextlib.ExitStack() as stack:
            if self.spec.mujoco_frames:
                stack.enter_context(mujoco_contact_frames())
            if jax.default_backend() == "cpu":
                stack.enter_context(plain_cholesky())
            return self._solved_by_loop(fn, d)

    def _solved_by_loop(self, fn: Callable[[mjx.Data], mjx.Data], d: mjx.Data) -> mjx.Data:
        loop, iterations = self.solver.newton_loop, self.solver.iterations
        if loop == "while":
            return fn(d)
        with newton_trips(iterations, unroll=loop == "unrolled") as replaced:
            d = fn(d)
        if iterations > 1 and not replaced:  # MJX runs a single iteration without a loop
            raise RuntimeError(
                f"solver newton_loop={loop!r} found no Newton while_loop to replace in mujoco {mujoco.__version__}'s "
                "MJX solver; use newton_loop='while'"
            )
        return d

    def _physics_steps(self, d: mjx.Data, n: int, unroll: bool = False) -> mjx.Data:
        if self.impl == "warp":
            return self._warp_steps(d, n, unroll)
        return self._solved(lambda d: jax.lax.fori_loop(0, n, lambda _, x: mjx.step(self.sys, x), d, unroll=unroll), d)

    def _warp_steps(self, d: mjx.Data, n: int, unroll: bool) -> mjx.Data:
        """``n`` steps of MuJoCo Warp (MJX's ``impl="warp"``) from the state of ``d``, a JAX-implementation
        ``mjx.Data``: what a step carries over (:data:`STEP_STATE`) goes to a Warp data and comes back with the
        step's accelerations and sensor values; the position-dependent fields are recomputed by :meth:`_observe`,
        as after every step."""
        w = jax.tree.map(traced_constant, self._warp_data0).replace(**{f: getattr(d, f) for f in STEP_STATE})
        w = jax.lax.fori_loop(0, n, lambda _, x: mjx.step(self._warp_sys, x), w, unroll=unroll)
        return d.replace(**{f: getattr(w, f) for f in (*STEP_STATE, *STEP_RESULTS)})

    def build_warp_kernels(self) -> None:
        """Builds and loads MuJoCo Warp's kernels for this model (``impl='warp'``; nothing for ``jax``).

        One step of one world runs in Warp itself on this process's first device, outside any JAX program. A
        first vmapped step would otherwise build the same kernels one after the other inside the first round,
        after its compile; run from a thread (:func:`rebel_jax.run.cli.run` does) the build overlaps XLA's compile.
        Warp keeps them in its kernel cache (``~/.cache/warp``, or ``WARP_CACHE_PATH``). Finish it before a program
        that steps this environment runs: inside a program Warp's step is captured as a CUDA graph, and CUDA may
        refuse a capture while another thread loads kernels.
        """
        if self.impl == "warp":  # with the step's overflow warnings, as _warp_steps runs it
            build_warp_kernels(self.mj_model, self._warp_sys.opt._impl.warn_overflow)

    def _observe(self, d: mjx.Data, done: jax.Array, info: dict) -> State:
        d = _observed(d, self.sys, self.spec.sensors)
        reward, metrics = self.spec.reward_fn(d)
        return State(d, self.spec.obs_fn(d), reward, done, metrics, info)

    def observe(self, d: mjx.Data, steps: jax.Array, done: jax.Array) -> State:
        """The ``State`` of physics data ``d`` whose qpos/qvel are current (kinematics are recomputed)."""
        return self._observe(d, done, {"steps": steps, "truncation": done})

    def reset(self, rng: jax.Array) -> State:
        """Samples an initial state from dm_control's reset distribution."""
        if self._sample_pose is not None:
            qpos = self._sample_pose(rng)
        else:
            u = jax.random.uniform(rng, self._reset_low.shape)
            qpos = self._reset_low + u * (self._reset_high - self._reset_low)
        d = jax.tree.map(traced_constant, self._data0).replace(qpos=qpos)
        if self.spec.settle_steps:
            d = self._physics_steps(d, self.spec.settle_steps).replace(time=jnp.zeros(()))
        if self.spec.sensors:  # dm_control's closing mj_forward (actuation off; at rest it exerts nothing anyway)
            d = self._solved(lambda d: mjx.forward(self.sys, d), d)
        zero = jnp.zeros(())
        if self.episode_length is None:
            return self._observe(d, zero, {})
        return self.observe(d, jnp.zeros((), jnp.int32), zero)

    def control(self, action: jax.Array) -> jax.Array:
        """The actuator controls of ``action`` in [-1, 1]: mapped linearly onto the control ranges (the
        quadruped's lift and extend actuators have ranges [-1, 1.1] and [-0.8, 0.8]); the identity for the
        tasks whose ranges are all [-1, 1]. MuJoCo clips controls to their range."""
        if self._ctrl_range is None:
            return action
        low, high = self._ctrl_range
        return low + (action + 1.0) / 2.0 * (high - low)

    def step(self, state: State, action: jax.Array) -> State:
        """Applies ``action`` (in [-1, 1]; see :meth:`control`) for one control step."""
        if action.shape != (self.action_size,):
            raise ValueError(
                f"{self.spec.name}: action must have shape ({self.action_size},), got {action.shape}; "
                "vmap the environment for a batch of actions"
            )
        ctrl = self.control(action).astype(state.pipeline_state.ctrl.dtype)
        d = state.pipeline_state.replace(ctrl=ctrl)
        d = self._physics_steps(d, self.spec.n_substeps, self.unroll_substeps)
        if self.episode_length is None:
            return self._observe(d, jnp.zeros_like(state.done), dict(state.info))
        steps = state.info["steps"] + 1
        done = (steps >= self.episode_length).astype(jnp.float32)
        return self._observe(d, done, dict(state.info, steps=steps, truncation=done))


IMPLS = ("jax", "warp")
"""MJX's implementations of the physics step: ``jax`` (MJX in JAX operations) or ``warp`` (MuJoCo Warp's kernels,
called from JAX; needs the ``warp-lang`` package, ``pip install -e '.[warp]'``)."""

STEP_STATE = ("qpos", "qvel", "act", "ctrl", "time", "qacc_warmstart")
"""The ``mjx.Data`` fields one physics step reads from the last (MuJoCo's state, its control and the solver's
warm start; the tasks have no mocap bodies)."""

STEP_RESULTS = ("qacc", "sensordata")
"""Fields a physics step computes that the observations read without recomputing them (the acceleration and
force sensors); kept for inspection as well."""


def _warp_overflow():
    """MuJoCo Warp's overflow flags (``mujoco_warp.OverflowType``), imported only with ``impl='warp'``."""
    from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType

    return OverflowType


def check_impl(impl: str) -> None:
    """Raises a one-line ValueError for an unknown ``impl`` or for ``warp`` without the ``warp-lang`` package."""
    if impl not in IMPLS:
        raise ValueError(f"unknown physics impl {impl!r}; one of {', '.join(IMPLS)}")
    if impl == "warp" and importlib.util.find_spec("warp") is None:
        raise ValueError("env.impl='warp' needs the warp-lang package: pip install -e '.[warp]'")


def parse_solver(solver: str | Solver) -> Solver:
    """A :class:`Solver` from a preset name or ``"ITERATIONS/LS_ITERATIONS[/noeulerdamp]"``, then ``":NEWTON_LOOP"``."""
    if isinstance(solver, Solver):
        return solver
    if solver in SOLVERS:
        return SOLVERS[solver]
    name, colon, loop = solver.partition(":")
    if name in SOLVERS and loop in NEWTON_LOOPS:
        return dataclasses.replace(SOLVERS[name], newton_loop=loop)
    parts = name.split("/")
    if (
        len(parts) in (2, 3)
        and all(p.isdigit() for p in parts[:2])
        and parts[2:] in ([], ["noeulerdamp"])
        and (loop in NEWTON_LOOPS or not colon)
    ):
        return Solver(int(parts[0]), int(parts[1]), eulerdamp=len(parts) == 2, newton_loop=loop or "while")
    raise ValueError(
        f"unknown solver {solver!r}; valid: {', '.join(SOLVERS)}, 'ITERATIONS/LS_ITERATIONS[/noeulerdamp]' or a "
        f"Solver, each optionally followed by ':NEWTON_LOOP' ({', '.join(NEWTON_LOOPS)})"
    )


def make_env(
    name: str,
    solver: str | Solver = "default",
    episode_length: int | None = 1000,
    unroll_substeps: bool = False,
    all_contacts: bool = False,
    impl: str = "jax",
    worlds: int = 1,
) -> DMCEnv:
    """Builds a task by name.

    Args:
      name: one of ``walker_stand``, ``walker_walk``, ``walker_run``, ``cheetah_run``, ``quadruped_walk``,
        ``quadruped_run``.
      solver: a name from :data:`SOLVERS` (``default`` or ``dm_control``) or a :class:`Solver`.
      episode_length: control steps per episode (dm_control: 1000); None for no time limit (brax's
        convention: ``EpisodeWrapper`` adds it).
      unroll_substeps: unroll the physics substeps of a control step in the compiled
        program instead of looping over them (longer compile, fewer loop round trips).
      all_contacts: check every geom pair, also the task's ``never_near`` ones (:class:`TaskSpec`).
      impl: the physics step's implementation, one of :data:`IMPLS`.
      worlds: with ``impl='warp'``, the most environments that one vmapped step of a device runs at once (all
        vmapped axes together): MuJoCo Warp's contact buffer is sized for them. Unused by the JAX step.
    """
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; valid tasks: {', '.join(sorted(TASKS))}")
    return DMCEnv(name, parse_solver(solver), episode_length, unroll_substeps, all_contacts, impl, worlds)
