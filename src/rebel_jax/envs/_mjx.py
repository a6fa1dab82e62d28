"""``mujoco.mjx``, imported with its optional-backend messages sent to logging (and Warp quiet where installed);
its Newton loop with known trips; MuJoCo's contact frames for capsules on a plane; Cholesky factorizations in
plain JAX operations (CPU).

Without the optional Warp backend (``pip install -e '.[warp]'`` adds it, for ``--impl warp``),
importing ``mujoco.mjx`` prints "Failed to import warp: No module named 'warp'" and the same
for ``mujoco_warp``. Those lines go to this module's logger at DEBUG level, which Python's
default logging does not show; anything else the import prints is passed through.
"""

from __future__ import annotations

import contextlib
import io
import logging
import sys
import types
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

logger = logging.getLogger(__name__)


def import_quietly() -> None:
    """Imports ``mujoco.mjx`` (a no-op if it already is), logging its "Failed to import" lines at DEBUG."""
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        import mujoco.mjx  # noqa: F401

    for line in printed.getvalue().splitlines():
        if line.startswith("Failed to import"):
            logger.debug("mujoco.mjx: %s", line)
        else:
            print(line)
    warp = sys.modules.get("warp")  # imported by mujoco.mjx where installed (env.impl='warp')
    if warp is not None:
        warp.config.log_level = warp.LOG_WARNING  # no banner and no line per kernel module loaded


import_quietly()


class _Namespace(types.ModuleType):
    """``module`` with some attributes replaced (``overrides``); every other attribute read from ``module``."""

    def __init__(self, module: types.ModuleType, **overrides: Any):
        super().__init__(module.__name__)
        self._module = module
        self.__dict__.update(overrides)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._module, name)


@contextlib.contextmanager
def newton_trips(iterations: int, unroll: bool = False) -> Iterator[list[int]]:
    """While code is traced under it, MJX's Newton loop runs a known number of trips.

    MJX's constraint solver (``mujoco/mjx/_src/solver.py``, ``solve``, mujoco 3.17) iterates with
    ``jax.lax.while_loop(cond, body, ctx)``: its only data-dependent loop (the line search already
    scans ``ls_iterations`` trips). On a GPU such a loop reads its predicate back to the host on every
    trip, so the device drains between trips; here that happens 1 + ``iterations`` times per physics
    substep. Under this context the loop is instead ``iterations`` trips of a ``fori_loop``, each
    applying ``body`` where MJX's own stopping test ``cond`` still holds and keeping ``ctx`` where it
    does not. The results are the same: ``cond`` stops MJX's loop after ``iterations`` trips at most
    (``solver_niter >= iterations``), and a stopped state stays stopped since it no longer changes;
    under ``vmap`` the ``while_loop`` already computes ``body`` for every member until all have stopped.
    ``tests/test_envs.py`` checks the equality.

    Args:
      iterations: the model's ``opt.iterations``.
      unroll: unroll the trips in the compiled program (no loop at all).

    Yields:
      A list that gets one entry per replaced loop traced, so that callers can check it applied.
    """
    from mujoco.mjx._src import solver

    replaced: list[int] = []

    def while_loop(cond: Callable, body: Callable, ctx: Any) -> Any:
        replaced.append(iterations)

        def trip(_: jax.Array, ctx: Any) -> Any:
            going = cond(ctx)
            return jax.tree.map(lambda new, old: jnp.where(going, new, old), body(ctx), ctx)

        return jax.lax.fori_loop(0, iterations, trip, ctx, unroll=unroll)

    original = solver.jax  # jax itself, or another context's namespace (``plain_cholesky``): kept underneath
    solver.jax = _Namespace(original, lax=_Namespace(original.lax, while_loop=while_loop))
    try:
        yield replaced
    finally:
        solver.jax = original


def cholesky_upper(a: jax.Array) -> jax.Array:
    """The upper Cholesky factor ``u`` of symmetric positive definite matrices (``a = u^T u``; leading axes batch),
    column by column in plain JAX operations (no LAPACK call): column ``j`` of the lower factor is
    ``(a[:, j] - l[:, :j] l[j, :j]) / sqrt(.)``, zero above the diagonal."""
    n = a.shape[-1]
    rows = jnp.arange(n)

    def column(j, lower):
        v = a[..., :, j] - jnp.einsum("...ik,...k->...i", lower, lower[..., j, :])  # columns >= j of lower are 0
        v = v / jnp.sqrt(v[..., j])[..., None]
        return lower.at[..., :, j].set(jnp.where(rows >= j, v, 0.0))

    return jnp.swapaxes(jax.lax.fori_loop(0, n, column, jnp.zeros_like(a)), -1, -2)


def _substitute(u: jax.Array, b: jax.Array, transpose: bool) -> jax.Array:
    """Solves ``u^T x = b`` (``transpose``, forward) or ``u x = b`` (backward) for upper-triangular ``u``; ``b``
    is a vector per matrix."""
    n = u.shape[-1]
    order = jnp.arange(n) if transpose else jnp.arange(n)[::-1]
    t = jnp.swapaxes(u, -1, -2) if transpose else u

    def row(k, x):
        i = order[k]
        rest = jnp.einsum("...j,...j->...", t[..., i, :], x)  # x is 0 where not yet solved
        return x.at[..., i].set((b[..., i] - rest) / t[..., i, i])

    return jax.lax.fori_loop(0, n, row, jnp.zeros_like(b))


def _cho_factor(a: jax.Array, lower: bool = False, **_) -> tuple[jax.Array, bool]:
    if lower:
        raise NotImplementedError("plain_cholesky: MJX factors with lower=False")
    return cholesky_upper(a), False


def _cho_solve(c_and_lower: tuple[jax.Array, bool], b: jax.Array, **_) -> jax.Array:
    u, lower = c_and_lower
    if lower or b.ndim != u.ndim - 1:
        raise NotImplementedError("plain_cholesky: MJX solves one vector per upper factor")
    return _substitute(u, _substitute(u, b, transpose=True), transpose=False)


@contextlib.contextmanager
def plain_cholesky() -> Iterator[None]:
    """While code is traced under it, MJX factors and solves with its mass matrix and its Newton solver's Hessian
    (``jax.scipy.linalg.cho_factor`` and ``cho_solve`` in ``smooth.py``, ``solver.py`` and ``forward.py``, mujoco
    3.17) by :func:`cholesky_upper` and substitution, in plain JAX operations, instead of LAPACK.

    Why: jaxlib 0.10.2's CPU LAPACK kernels split a large batch over XLA's CPU thread pool and wait for the parts
    from inside that pool (``jax::ParallelBatchMap``, jaxlib/cpu/lapack_kernels.cc). When as many factorizations
    run at once as the pool has threads, every thread waits and none computes: the program hangs. On 2 cores a
    quadruped step of 60 or 64 environments hung in each of 4 tries (of 4, 32 and 48 it did not).
    :class:`rebel_jax.envs.dmc.DMCEnv` traces its physics under this context on the CPU only; GPU programs keep
    MJX's calls.
    """
    from mujoco.mjx._src import forward, smooth, solver

    modules = (forward, smooth, solver)
    originals = [m.jax for m in modules]
    for m, original in zip(modules, originals, strict=True):
        linalg = _Namespace(original.scipy.linalg, cho_factor=_cho_factor, cho_solve=_cho_solve)
        m.jax = _Namespace(original, scipy=_Namespace(original.scipy, linalg=linalg))
    try:
        yield
    finally:
        for m, original in zip(modules, originals, strict=True):
            m.jax = original


def _plane_capsule(plane, capsule):
    """MuJoCo's plane-capsule contacts (``mjc_PlaneCapsule``, mujoco 3.17): a sphere-plane test at each end of the
    capsule's segment, each contact's first tangent the capsule's axis made orthogonal to the normal.

    MJX's ``plane_capsule`` (``collision_primitive.py``) computes the same points but falls back to a fixed
    tangent, ``(0, 1, 0)``, whenever the axis' projection onto the plane is shorter than 0.5, i.e. for a capsule
    within 30 degrees of the normal. MuJoCo completes the frame from the axis in every case (``mju_makeFrame``
    tests the hint's length before projecting it), and with pyramidal friction cones (MuJoCo's default) the
    tangents orient the friction pyramid: the two frames give different contact forces, one step apart by up to a
    third of the joint velocities on dm_control's quadruped (its thighs and shins). In a planar model (walker,
    cheetah) both frames span the same pyramid.
    """
    n, axis = plane.mat[:, 2], capsule.mat[:, 2]
    tangent = axis - n * jnp.dot(n, axis)
    length = jnp.linalg.norm(tangent)
    # mju_normalize3: a vector shorter than mjMINVAL becomes (1, 0, 0).
    tangent = jnp.where(length < 1e-15, jnp.array([1.0, 0.0, 0.0]), tangent / jnp.maximum(length, 1e-15))
    frame = jnp.stack([n, tangent, jnp.cross(n, tangent)])
    segment = axis * capsule.size[1]
    ends = jnp.stack([capsule.pos + segment, capsule.pos - segment])
    dist = (ends - plane.pos) @ n - capsule.size[0]
    pos = ends - n * (capsule.size[0] + 0.5 * dist)[:, None]
    return dist, pos, jnp.stack([frame, frame])


@contextlib.contextmanager
def mujoco_contact_frames() -> Iterator[None]:
    """While code is traced under it, MJX collides planes with capsules as MuJoCo does, contact frames included
    (:func:`_plane_capsule`); MJX's other collision functions are unchanged. ``tests/test_envs_quadruped.py``
    compares the contacts with MuJoCo's."""
    from mujoco.mjx._src import collision_driver, collision_primitive
    from mujoco.mjx._src.types import GeomType

    key = (GeomType.PLANE, GeomType.CAPSULE)
    original = collision_driver._COLLISION_FUNC[key]
    collision_driver._COLLISION_FUNC[key] = collision_primitive.collider(ncon=2)(_plane_capsule)
    try:
        yield
    finally:
        collision_driver._COLLISION_FUNC[key] = original


def uncommitted(leaf):
    """A JAX array as an uncommitted copy (placed wherever the program using it runs); other leaves unchanged."""
    return jnp.asarray(jax.device_get(leaf)) if isinstance(leaf, jax.Array) else leaf


def traced_constant(leaf):
    """A host array as a JAX array (a constant of the program being traced); other leaves unchanged."""
    return jnp.asarray(leaf) if isinstance(leaf, np.ndarray) else leaf


def build_warp_kernels(mj_model, warn_overflow=None) -> None:
    """Builds and loads MuJoCo Warp's kernels for ``mj_model``: one step of one world in Warp itself on this
    process's first device, outside any JAX program (``warn_overflow``: the step's overflow warnings, Warp's
    default if None). Warp keeps them in its kernel cache (``~/.cache/warp``, or ``WARP_CACHE_PATH``)."""
    import warp  # noqa: PLC0415 - only with impl='warp' (warp-lang is optional)
    from mujoco.mjx.third_party import mujoco_warp  # noqa: PLC0415

    local = jax.local_devices()[0]
    device = warp.get_device(f"cuda:{local.local_hardware_id}" if local.platform == "gpu" else "cpu")
    with warp.ScopedDevice(device):
        model = mujoco_warp.put_model(mj_model)
        if warn_overflow is not None:
            model.opt.warn_overflow = warn_overflow
        data = mujoco_warp.make_data(mj_model, nworld=1)
        mujoco_warp.step(model, data)
        warp.synchronize_device(device)
