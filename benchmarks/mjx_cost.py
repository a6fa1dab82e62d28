"""What MJX's JAX step costs on a Meta-World model, and where it goes (CPU or GPU, batch 1).

Usage:
  python benchmarks/mjx_cost.py census [--task drawer-open]
  python benchmarks/mjx_cost.py near [--task drawer-open]
  python benchmarks/mjx_cost.py time [--task drawer-open] [--parts step forward collision ...] [--repeats 20]
  python benchmarks/mjx_cost.py fidelity [--task drawer-open] [--every 16]
  python benchmarks/mjx_cost.py agree [--task drawer-open] [--every 64] [--option xla_cpu_use_fusion_emitters=false]
  python benchmarks/mjx_cost.py depth [--depths 4 5 6 7 8 9]
  add --xla-flags=FLAGS to any of them for this process's XLA_FLAGS (recorded in each row)

``census``: the model's sizes that set MJX's cost: geoms by type, meshes (vertices, faces, the convex hull MuJoCo
builds and the one MJX collides: vertices, faces, edges), the geom pairs MJX's collision driver builds after the
contype/conaffinity/exclude filters, grouped as it groups them (geom types, mesh, condim) with the contact slots each
group emits, the contacts and constraint rows of ``mjx.make_data``, and the solver options.

``near``: at every state recorded from Meta-World (tests/data/metaworld/<task>.npz, the episode's bodies where its
reset put them), MuJoCo C's contacts (``mj_forward``, ``d.ncon``), the pairs whose bounding spheres overlap, and each
MJX pair's smallest signed distance (``mj_geomDistance``), per pair of welded bodies. For the pairs of a body on one
slide joint (drawer-open's drawer) against the fixed geoms, the smallest distance over a grid of the reset's draw and
the joint position, a little past the joint's range (:func:`fixed_pairs_far`).

``time``: median seconds of one jitted call after a warm-up (compile seconds apart) from a recorded state with
contacts, for each part: ``step`` (one ``mjx.step``, a physics substep; a control step is 5), ``forward``
(``mjx.forward``), ``collision`` (``mjx.collision`` after ``mjx.kinematics``), ``kinematics``, ``step_nocontact``
(the contact disable flag set, and pyramidal cones: MJX cannot trace elliptic ones without contacts),
``step_nomesh`` (no pair with a mesh geom), ``step_far_dropped`` (without the pairs that can never come within their
margin: :func:`droppable_pairs`), ``forward_far_dropped``, ``collision_far_dropped``; a ``_hull64`` suffix caps the
meshes' convex hulls at 64 vertices (``maxhullvert``). On the CPU the factorizations run in plain JAX operations, as
the tasks run them. Each part is lowered and compiled once ahead of time and the compiled program is called
directly, so nothing is traced or compiled again while timing; the model is a constant of the program (closed over,
as the tasks' step has it), the data an argument already on the device. A row also gives the warm-up call's
milliseconds (``first_call_ms``), a jitted call returning its data argument unchanged (``identity_call_ms``: the
harness's own cost per call) and the optimized program's instruction count (``hlo_instructions``).

``depth``: the same timing of ``mjx.kinematics`` on a chain of ``n`` bodies, one hinge each (``--depths``), and
on dm_control's walker, cheetah and quadruped (:func:`rebel_jax.envs.dmc.mj_model`). On the CPU, XLA's fusion
emitters (``--xla_cpu_use_fusion_emitters``, on by default in jaxlib 0.10.2) make ``mjx.kinematics`` cost time that
grows exponentially with the depth of the kinematic tree (drawer-open's is 13 bodies deep): compare the rows with
``--xla-flags=--xla_cpu_use_fusion_emitters=false``.

``fidelity``: one control step (the task's ``step``) of the full model and of the one without the droppable pairs,
from every ``--every``-th recorded state, against Meta-World's next state, and against each other.

``agree``: one control step from every ``--every``-th recorded state, compiled with XLA's default options and with
``--option`` (XLA debug options, ``name=value``), against each other: whether a compiler option changes the step.

Rows go to ``benchmarks/results/mjx_cost.json``.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import pathlib
import statistics
import sys
import time
from collections.abc import Iterator

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import collision_driver
from timing import add_xla_flags_argument, merge_rows, provenance, use_xla_flags

from rebel_jax.envs import metaworld
from rebel_jax.envs._mjx import plain_cholesky

ROOT = pathlib.Path(__file__).parents[1]
DATA = ROOT / "tests" / "data" / "metaworld"
RESULTS = ROOT / "benchmarks" / "results" / "mjx_cost.json"
FIELDS = ("device", "commit", "xla_flags", "task", "part")
CLEARANCE = 0.0005
"""A pair is droppable when the lower bound of its distance exceeds its margin by this much (metres)."""
SLIDE_LOW_SLACK, SLIDE_HIGH_SLACK = 0.3, 0.05
"""How far past the slide joint's range the grid of :func:`fixed_pairs_far` runs (metres): the recorded episodes
pull drawer-open's drawer 4.3 cm past its range's low end (soft joint limits); 0.3 m is more than the hand's reach
allows there."""
GRID_X, GRID_Q = 41, 281
"""Grid points of the reset draw and of the joint position in :func:`fixed_pairs_far` (covering radii 0.9 mm along
the joint alone, 2.7 mm over both)."""


def _name(m: mujoco.MjModel, kind: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(m, kind, i) or f"{kind.name[6:].lower()}{i}"


def _type(t: int) -> str:
    return mujoco.mjtGeom(t).name[7:].lower()


def _weld(m: mujoco.MjModel, g: int) -> str:
    return _name(m, mujoco.mjtObj.mjOBJ_BODY, m.body_weldid[m.geom_bodyid[g]])


def model(task: str, maxhullvert: int | None = None) -> mujoco.MjModel:
    """:func:`metaworld.mj_model`, or with every mesh's convex hull capped at ``maxhullvert`` vertices (the MJCF
    attribute ``mesh/maxhullvert``, set through ``mujoco.MjSpec``)."""
    if maxhullvert is None:
        return metaworld.mj_model(task)
    spec = mujoco.MjSpec.from_file(str(metaworld.ASSETS / "sawyer_xyz" / metaworld.TASKS[task].xml))
    for mesh in spec.meshes:
        mesh.maxhullvert = maxhullvert
    m = spec.compile()
    for i in range(m.neq):
        if m.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
            m.eq_data[i, : len(metaworld.WELD_DATA)] = metaworld.WELD_DATA
    return m


def hull_vertices(m: mujoco.MjModel, i: int) -> np.ndarray:
    """The vertices of mesh ``i``'s convex hull as MuJoCo compiled it (its graph's vertex ids)."""
    adr = m.mesh_graphadr[i]
    return m.mesh_vert[m.mesh_vertadr[i] + m.mesh_graph[adr + 2 + m.mesh_graph[adr] : adr + 2 + 2 * m.mesh_graph[adr]]]


def hull_shrink(full: np.ndarray, capped: np.ndarray) -> float:
    """How far (metres) the full hull's vertices lie outside the capped hull: the largest, over the full hull's
    vertices, of the largest signed distance to the capped hull's face planes (a lower bound of the distance to the
    capped hull; the capped hull's vertices are a subset of the full one's, so it lies inside)."""
    from scipy.spatial import ConvexHull  # noqa: PLC0415

    eq = ConvexHull(capped).equations  # rows (normal, offset): normal . x + offset <= 0 inside
    return float((full @ eq[:, :3].T + eq[:, 3]).max(axis=1).max())


def pairs_of(m: mujoco.MjModel) -> list[tuple[int, int]]:
    """The geom pairs MJX's collision driver collides (``collision_driver.geom_pairs``), in its order."""
    return [(int(g1), int(g2)) for g1, g2, _ in collision_driver.geom_pairs(m)]


@contextlib.contextmanager
def without_pairs(dropped: set[tuple[int, int]]) -> Iterator[None]:
    """While MJX models and data are built and steps traced under it, its collision driver leaves out ``dropped``
    (geom pairs as ``pairs_of`` gives them). A measurement device, not a documented MJX option: the documented way
    to the same pairs is the model's contype/conaffinity bits or ``<contact><exclude>``."""
    original = collision_driver.geom_pairs

    def kept(m):
        for g1, g2, ip in original(m):
            if (int(g1), int(g2)) not in dropped:
                yield g1, g2, ip

    collision_driver.geom_pairs = kept
    try:
        yield
    finally:
        collision_driver.geom_pairs = original


def census(task: str) -> dict:
    m = metaworld.mj_model(task)
    collide = (m.geom_contype | m.geom_conaffinity) != 0
    out: dict = {
        "nq": m.nq,
        "nv": m.nv,
        "nbody": m.nbody,
        "ngeom": m.ngeom,
        "geoms_by_type": dict(collections.Counter(_type(t) for t in m.geom_type)),
        "colliding_geoms_by_type": dict(collections.Counter(_type(t) for t in m.geom_type[collide])),
        "npair": m.npair,
        "nexclude": m.nexclude,
        "solver": {
            "solver": mujoco.mjtSolver(m.opt.solver).name,
            "iterations": m.opt.iterations,
            "ls_iterations": m.opt.ls_iterations,
            "tolerance": m.opt.tolerance,
            "cone": mujoco.mjtCone(m.opt.cone).name,
            "timestep": m.opt.timestep,
            "integrator": mujoco.mjtIntegrator(m.opt.integrator).name,
        },
    }
    mx = mjx.put_model(m)
    meshes = []
    for i in range(m.nmesh):
        geoms = np.where((m.geom_type == mujoco.mjtGeom.mjGEOM_MESH) & (m.geom_dataid == i))[0]
        row = {
            "mesh": _name(m, mujoco.mjtObj.mjOBJ_MESH, i),
            "vertices": int(m.mesh_vertnum[i]),
            "faces": int(m.mesh_facenum[i]),
            "geoms": len(geoms),
            "colliding_geoms": int(collide[geoms].sum()),
        }
        if m.mesh_graphadr[i] >= 0:
            adr = m.mesh_graphadr[i]
            row["mujoco_hull"] = {"vertices": int(m.mesh_graph[adr]), "faces": int(m.mesh_graph[adr + 1])}
        if m.mesh_graphadr[i] >= 0:
            full = hull_vertices(m, i)
            for cap in (32, 64, 128):
                capped = model(task, cap)
                row[f"hull_{cap}_shrink_mm"] = round(1e3 * hull_shrink(full, hull_vertices(capped, i)), 3)
        convex = mx._impl.mesh_convex[i]
        if convex is not None:
            row["mjx_convex"] = {
                "vertices": convex.vert.shape[0],
                "faces": convex.face.shape[0],
                "face_vertices": convex.face.shape[1],
                "edges": convex.edge.shape[0],
            }
        meshes.append(row)
    out["meshes"] = meshes
    groups = []
    for key, pairs in collision_driver._geom_groups(m).items():
        ncon = collision_driver._COLLISION_FUNC[key.types].ncon
        mesh = [_name(m, mujoco.mjtObj.mjOBJ_MESH, int(i)) for i in key.data_ids if i >= 0]
        welds = collections.Counter(f"{_weld(m, g1)}-{_weld(m, g2)}" for g1, g2, _ in pairs)
        groups.append(
            {
                "types": [_type(t) for t in key.types],
                "mesh": mesh,
                "condim": int(key.condim),
                "pairs": len(pairs),
                "contacts_per_pair": ncon,
                "contacts": ncon * len(pairs),
                "pairs_by_welded_bodies": dict(welds),
            }
        )
    out["groups"] = sorted(groups, key=lambda g: -g["contacts"])
    out["pairs"] = sum(g["pairs"] for g in groups)
    d = mjx.make_data(m)
    out["mjx_contacts"] = int(d._impl.contact.dist.shape[0])
    out["mjx_contacts_by_condim"] = dict(collections.Counter(str(x) for x in np.asarray(d._impl.contact.dim)))
    out["mjx_nefc"] = int(d._impl.nefc)
    return out


def recorded(task: str) -> dict:
    return dict(np.load(DATA / f"{task}.npz"))


def set_state(m: mujoco.MjModel, d: mujoco.MjData, ref: dict, i: int) -> None:
    """MuJoCo at the recorded row ``i``: the episode's bodies, qpos, qvel, mocap and warm start."""
    m.body_pos[:] = ref["episode_body_pos"][ref["episode"][i]]
    d.qpos[:] = ref["qpos"][i]
    d.qvel[:] = ref["qvel"][i]
    d.mocap_pos[:] = ref["mocap_pos"][i]
    d.mocap_quat[:] = ref["mocap_quat"][i]
    d.qacc_warmstart[:] = ref["qacc_warmstart"][i]


def fixed_pairs_far(task: str, m: mujoco.MjModel, pairs: list[tuple[int, int]]) -> dict:
    """A lower bound of each pair's distance, for the pairs between a geom of the task's moved body's one slide joint
    and a geom welded to the world, over every reset draw (its first coordinate, the only one that varies for
    drawer-open) and every joint position from the range's low end minus :data:`SLIDE_LOW_SLACK` to its high end
    plus :data:`SLIDE_HIGH_SLACK`.

    Both bodies are rigid and the moving one only translates (the draw moves it in x, the joint along its axis), so a
    pair's distance is 1-Lipschitz in (draw, joint position): the smallest distance on a grid minus the grid's
    covering radius bounds it from below. A fixed geom that moves with the draw (the drawer's case) sees the joint
    position alone, so its grid is one-dimensional.

    Returns:
      ``{pair index: lower bound of its distance}``; empty where the task is not of that form.
    """
    spec = metaworld.TASKS[task]
    low, high = np.asarray(spec.reset_low), np.asarray(spec.reset_high)
    varying = np.where(high > low)[0]
    body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, spec.moved_body) if spec.moved_body else -1
    if body < 0 or len(varying) != 1:
        return {}
    below = [j for j in range(m.njnt) if _descends(m, m.jnt_bodyid[j], body)]
    if len(below) != 1 or m.jnt_type[below[0]] != mujoco.mjtJoint.mjJNT_SLIDE:
        return {}
    joint = below[0]
    weld = m.body_weldid[m.geom_bodyid]
    moving = weld == m.body_weldid[m.jnt_bodyid[joint]]
    fixed = weld == 0
    with_draw = np.array([_descends(m, b, body) for b in m.geom_bodyid])
    chosen = [j for j, (a, b) in enumerate(pairs) if (moving[a] and fixed[b]) or (fixed[a] and moving[b])]
    lo, hi = m.jnt_range[joint]
    qs = np.linspace(lo - SLIDE_LOW_SLACK, hi + SLIDE_HIGH_SLACK, GRID_Q)
    xs = np.linspace(low[varying[0]], high[varying[0]], GRID_X)
    radius_1d = (qs[1] - qs[0]) / 2
    radius_2d = np.hypot(radius_1d, (xs[1] - xs[0]) / 2)
    d = mujoco.MjData(m)
    best = {j: np.inf for j in chosen}
    for k, x in enumerate(xs):
        pos = low.copy()
        pos[varying[0]] = x
        m.body_pos[body] = pos
        for q in qs:
            d.qpos[:] = 0.0
            d.qpos[m.jnt_qposadr[joint]] = q
            mujoco.mj_kinematics(m, d)
            for j in chosen:
                a, b = pairs[j]
                if k and with_draw[a] and with_draw[b]:
                    continue  # the draw moves both: one x suffices
                best[j] = min(best[j], mujoco.mj_geomDistance(m, d, a, b, 1.0, None))
    return {
        j: v - (radius_1d if with_draw[pairs[j][0]] and with_draw[pairs[j][1]] else radius_2d) for j, v in best.items()
    }


def _descends(m: mujoco.MjModel, b: int, ancestor: int) -> bool:
    while b != ancestor and b != 0:
        b = m.body_parentid[b]
    return b == ancestor


def droppable_pairs(task: str) -> tuple[set[tuple[int, int]], dict]:
    """The pairs that can never come within their margin (plus :data:`CLEARANCE`):

    - a plane against any geom whose smallest distance to it at every recorded state exceeds 0.5 m (the floor,
      0.9 m under the table top that every moving geom stays above);
    - a geom of the moved body against a fixed geom, where :func:`fixed_pairs_far`'s lower bound keeps them apart.

    Returns:
      (the pairs, how many of each kind).
    """
    m = metaworld.mj_model(task)
    pairs = pairs_of(m)
    ref = recorded(task)
    d = mujoco.MjData(m)
    plane = [j for j, (a, b) in enumerate(pairs) if mujoco.mjtGeom.mjGEOM_PLANE in (m.geom_type[a], m.geom_type[b])]
    plane_min = {j: np.inf for j in plane}
    for i in range(len(ref["qpos"])):
        set_state(m, d, ref, i)
        mujoco.mj_kinematics(m, d)
        for j in plane:
            plane_min[j] = min(plane_min[j], mujoco.mj_geomDistance(m, d, pairs[j][0], pairs[j][1], 1.0, None))
    dropped = {pairs[j] for j, v in plane_min.items() if v > 0.5}
    margin = lambda j: max(m.geom_margin[pairs[j][0]], m.geom_margin[pairs[j][1]])  # noqa: E731
    grid = fixed_pairs_far(task, metaworld.mj_model(task), pairs)
    far = {pairs[j] for j, v in grid.items() if v > margin(j) + CLEARANCE}
    kinds = {"plane_far": len(dropped), "moved_body_vs_fixed_far": len(far - dropped)}
    return dropped | far, kinds


def near(task: str) -> dict:
    m = metaworld.mj_model(task)
    pairs = pairs_of(m)
    ref = recorded(task)
    d = mujoco.MjData(m)
    a, b = np.array(pairs).T
    bound = m.geom_rbound[a] + m.geom_rbound[b] + np.maximum(m.geom_margin[a], m.geom_margin[b])
    unbounded = (m.geom_rbound[a] == 0) | (m.geom_rbound[b] == 0)  # planes
    ncon, spheres = [], []
    smallest = np.full(len(pairs), np.inf)
    for i in range(len(ref["qpos"])):
        set_state(m, d, ref, i)
        mujoco.mj_forward(m, d)
        ncon.append(d.ncon)
        centre = np.linalg.norm(d.geom_xpos[a] - d.geom_xpos[b], axis=1)
        spheres.append(int(((centre <= bound) | unbounded).sum()))
        for j, (g1, g2) in enumerate(pairs):
            smallest[j] = min(smallest[j], mujoco.mj_geomDistance(m, d, g1, g2, 1.0, None))
    margin = np.maximum(m.geom_margin[a], m.geom_margin[b])
    by_welds: dict = {}
    for j, (g1, g2) in enumerate(pairs):
        key = f"{_weld(m, g1)}-{_weld(m, g2)} {_type(m.geom_type[g1])}-{_type(m.geom_type[g2])}"
        row = by_welds.setdefault(key, {"pairs": 0, "within_margin": 0, "within_1cm": 0, "smallest": np.inf})
        row["pairs"] += 1
        row["within_margin"] += int(smallest[j] <= margin[j])
        row["within_1cm"] += int(smallest[j] < 0.01)
        row["smallest"] = round(float(min(row["smallest"], smallest[j])), 4)
    dropped, kinds = droppable_pairs(task)
    ncon = np.asarray(ncon)
    return {
        "states": len(ncon),
        "mujoco_ncon": {"mean": float(ncon.mean()), "median": float(np.median(ncon)), "max": int(ncon.max())},
        "bounding_spheres_overlap": {"mean": float(np.mean(spheres)), "max": int(max(spheres))},
        "pairs": len(pairs),
        "pairs_ever_within_margin": int((smallest <= margin).sum()),
        "pairs_ever_within_1cm": int((smallest < 0.01).sum()),
        "by_welded_bodies": by_welds,
        "droppable": len(dropped),
        "droppable_kinds": kinds,
    }


def _busiest_row(task: str) -> int:
    """The recorded row with the most MuJoCo C contacts (a contact-rich state to time from)."""
    m = metaworld.mj_model(task)
    ref = recorded(task)
    d = mujoco.MjData(m)
    counts = []
    for i in range(len(ref["qpos"])):
        set_state(m, d, ref, i)
        mujoco.mj_forward(m, d)
        counts.append(d.ncon)
    return int(np.argmax(counts))


def _data(m: mujoco.MjModel, ref: dict, i: int) -> mjx.Data:
    d = mjx.make_data(m)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return d.replace(
        qpos=f32(ref["qpos"][i]),
        qvel=f32(ref["qvel"][i]),
        mocap_pos=f32(ref["mocap_pos"][i]),
        mocap_quat=f32(ref["mocap_quat"][i]),
        qacc_warmstart=f32(ref["qacc_warmstart"][i]),
        ctrl=f32([ref["action"][i, 3], -ref["action"][i, 3]]),
    )


def time_part(task: str, part: str, repeats: int) -> dict:
    """Compile and median run seconds of one jitted call of ``part`` (see the module's docstring)."""
    m = model(task, 64 if part.endswith("_hull64") else None)
    part_fn = part.removesuffix("_hull64")
    ref = recorded(task)
    row = _busiest_row(task)
    m.body_pos[:] = ref["episode_body_pos"][ref["episode"][row]]
    if part == "step_nocontact":
        m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
        # MJX 3.17's solver fails to trace elliptic cones without contacts (an empty float index); the cone type
        # changes nothing without contacts.
        m.opt.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    dropped: set = set()
    if part == "step_nomesh":
        mesh = mujoco.mjtGeom.mjGEOM_MESH
        dropped = {p for p in pairs_of(m) if mesh in (m.geom_type[p[0]], m.geom_type[p[1]])}
    elif part_fn.endswith("_far_dropped"):
        dropped, _ = droppable_pairs(task)
    fn = {
        "step": mjx.step,
        "forward": mjx.forward,
        "kinematics": mjx.kinematics,
        "collision": lambda mm, dd: mjx.collision(mm, mjx.kinematics(mm, dd)),
    }[part_fn.removesuffix("_nocontact").removesuffix("_nomesh").removesuffix("_far_dropped")]
    cholesky = plain_cholesky() if jax.default_backend() == "cpu" else contextlib.nullcontext()
    with without_pairs(dropped), cholesky:
        # The model is closed over, as the tasks' step closes over it: passed as an argument, every call checks its
        # static fields (NumPy arrays, meshes among them) against the compiled program's, which costs seconds.
        mx = mjx.put_model(m)
        d = jax.device_put(_data(m, ref, row))
        start = time.perf_counter()
        compiled = jax.jit(lambda dd: fn(mx, dd)).lower(d).compile()
        compile_s = time.perf_counter() - start
    first_ms = _call_ms(compiled, d)
    times = [_call_ms(compiled, d) for _ in range(repeats)]
    identity = jax.jit(lambda dd: dd).lower(d).compile()
    _call_ms(identity, d)
    return {
        "part": part,
        "row": row,
        "pairs_dropped": len(dropped),
        "contacts": int(d._impl.contact.dist.shape[0]),
        "nefc": int(d._impl.nefc),
        "compile_s": round(compile_s, 1),
        "hlo_instructions": _instructions(compiled.as_text()),
        "first_call_ms": round(first_ms, 3),
        "median_ms": round(statistics.median(times), 3),
        "identity_call_ms": round(statistics.median(_call_ms(identity, d) for _ in range(repeats)), 3),
        "repeats": repeats,
    }


def chain(n: int) -> mujoco.MjModel:
    """A chain of ``n`` bodies, each 10 cm above and turned from its parent, on one hinge, with one sphere that
    collides with nothing."""
    body = "".join(
        '<body pos="0 0 0.1" quat="0.98 0.1 0.1 0.1"><joint type="hinge" axis="0 1 0"/>'
        '<geom type="sphere" size="0.01" contype="0" conaffinity="0"/>'
        for _ in range(n)
    )
    return mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{body}{'</body>' * n}</worldbody></mujoco>")


def tree_depth(m: mujoco.MjModel) -> int:
    """The most bodies on a path from the world to a body."""
    depth = np.zeros(m.nbody, int)
    for b in range(1, m.nbody):  # parents come first
        depth[b] = depth[m.body_parentid[b]] + 1
    return int(depth.max())


def time_kinematics(m: mujoco.MjModel, repeats: int) -> dict:
    """:func:`time_part`'s timing of ``mjx.kinematics`` at ``m``'s default data."""
    mx = mjx.put_model(m)
    d = jax.device_put(mjx.make_data(m))
    start = time.perf_counter()
    compiled = jax.jit(lambda dd: mjx.kinematics(mx, dd)).lower(d).compile()
    compile_s = time.perf_counter() - start
    first_ms = _call_ms(compiled, d)
    times = [_call_ms(compiled, d) for _ in range(repeats)]
    return {
        "nbody": m.nbody,
        "njnt": m.njnt,
        "depth": tree_depth(m),
        "compile_s": round(compile_s, 1),
        "hlo_instructions": _instructions(compiled.as_text()),
        "first_call_ms": round(first_ms, 3),
        "median_ms": round(statistics.median(times), 3),
        "repeats": repeats,
    }


def _call_ms(compiled, *args) -> float:
    """Milliseconds of one call of ``compiled`` until its results are ready."""
    start = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    return 1e3 * (time.perf_counter() - start)


def _instructions(hlo: str) -> int:
    """Instructions of an optimized HLO module's text (its lines that assign one)."""
    return sum(1 for line in hlo.splitlines() if line.startswith("  ") and " = " in line)


def fidelity(task: str, every: int) -> dict:
    """One control step of the full and of the pruned model from recorded states (benchmarks/metaworld_fidelity.py's
    comparison), against Meta-World and against each other."""
    sys.path.insert(0, str(pathlib.Path(__file__).parent))
    import metaworld_fidelity as mf  # noqa: PLC0415

    ref = recorded(task)
    rows = np.where((ref["t"] > 0) & (ref["t"] < metaworld.EPISODE_LENGTH))[0][::every]
    dropped, _ = droppable_pairs(task)
    out: dict = {"n": len(rows)}
    stepped = {}
    for name, pairs in (("full", set()), ("far_dropped", dropped)):
        with without_pairs(pairs):
            env = metaworld.MetaWorldEnv(task)
            states = mf.states_at(env, ref, rows, mf.episodes(env, ref))
            start = time.perf_counter()
            s = jax.block_until_ready(jax.jit(jax.vmap(env.step))(states, mf._f32(ref["action"][rows + 1])))
            seconds = time.perf_counter() - start
        stepped[name] = s
        nxt = rows + 1
        out[name] = {
            "contacts": int(s.pipeline_state._impl.contact.dist.shape[-1]),
            "compile_and_run_s": round(seconds, 1),
            "qpos_err": mf._stats(np.abs(np.asarray(s.pipeline_state.qpos) - ref["qpos"][nxt])),
            "qvel_err": mf._stats(np.abs(np.asarray(s.pipeline_state.qvel) - ref["qvel"][nxt])),
            "obs_err": mf._stats(np.abs(np.asarray(s.obs) - ref["obs"][nxt])),
            "reward_err": mf._stats(np.abs(np.asarray(s.reward) - ref["reward"][nxt])),
            "success_mismatches": int((np.asarray(s.info["success"]) != ref["success"][nxt]).sum()),
        }
    full, pruned = stepped["full"], stepped["far_dropped"]
    out["far_dropped_vs_full"] = {
        "qpos_max_diff": float(np.abs(np.asarray(full.pipeline_state.qpos - pruned.pipeline_state.qpos)).max()),
        "qvel_max_diff": float(np.abs(np.asarray(full.pipeline_state.qvel - pruned.pipeline_state.qvel)).max()),
        "obs_max_diff": float(np.abs(np.asarray(full.obs - pruned.obs)).max()),
        "reward_max_diff": float(np.abs(np.asarray(full.reward - pruned.reward)).max()),
    }
    return out


def _option(text: str) -> tuple[str, bool | int | float | str]:
    """``name=value`` as an XLA debug option (booleans and numbers parsed)."""
    name, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected name=value; got {text!r}")
    low = value.lower()
    if low in ("true", "false"):
        return name, low == "true"
    for kind in (int, float):
        with contextlib.suppress(ValueError):
            return name, kind(value)
    return name, value


def agree(task: str, every: int, options: dict) -> dict:
    """One control step of the task from recorded states, compiled with XLA's defaults and with ``options``."""
    sys.path.insert(0, str(pathlib.Path(__file__).parent))
    import metaworld_fidelity as mf  # noqa: PLC0415

    ref = recorded(task)
    rows = np.where((ref["t"] > 0) & (ref["t"] < metaworld.EPISODE_LENGTH))[0][::every]
    env = metaworld.MetaWorldEnv(task)
    states = mf.states_at(env, ref, rows, mf.episodes(env, ref))
    actions = jax.device_put(mf._f32(ref["action"][rows + 1]))
    lowered = jax.jit(jax.vmap(env.step)).lower(states, actions)
    out: dict = {"n": len(rows), "options": {k: str(v) for k, v in options.items()}}
    stepped = {}
    for name, opts in (("default", {}), ("options", options)):
        start = time.perf_counter()
        compiled = lowered.compile(compiler_options=opts)
        compile_s = time.perf_counter() - start
        start = time.perf_counter()
        stepped[name] = jax.device_get(jax.block_until_ready(compiled(states, actions)))
        out[f"{name}_compile_s"] = round(compile_s, 1)
        out[f"{name}_run_s"] = round(time.perf_counter() - start, 2)
    a, b = stepped["default"], stepped["options"]
    for field, x, y in (
        ("qpos", a.pipeline_state.qpos, b.pipeline_state.qpos),
        ("qvel", a.pipeline_state.qvel, b.pipeline_state.qvel),
        ("obs", a.obs, b.obs),
        ("reward", a.reward, b.reward),
    ):
        x, y = np.asarray(x), np.asarray(y)
        out[field] = {
            "max_abs_diff": float(np.abs(x - y).max()),
            "max_rel_diff": float((np.abs(x - y) / np.maximum(np.abs(x), 1e-30)).max()),
            "identical_fraction": float((x == y).mean()),
        }
    out["success_mismatches"] = int((np.asarray(a.info["success"]) != np.asarray(b.info["success"])).sum())
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("what", choices=("census", "near", "time", "fidelity", "agree", "depth"))
    parser.add_argument("--task", default="drawer-open", choices=list(metaworld.TASKS))
    parser.add_argument("--parts", nargs="*", default=["step", "forward", "collision", "step_nocontact"])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--every", type=int, default=None, help="every n-th recorded state (fidelity 16, agree 64)")
    parser.add_argument(
        "--option",
        type=_option,
        action="append",
        default=None,
        help="agree: an XLA debug option name=value (default: xla_cpu_use_fusion_emitters=false)",
    )
    parser.add_argument("--depths", type=int, nargs="*", default=[4, 5, 6, 7, 8, 9])
    add_xla_flags_argument(parser)
    args = parser.parse_args(argv)
    use_xla_flags(args.xla_flags)
    base = dict(provenance(), task=args.task, mujoco=mujoco.__version__)
    if args.what == "time":
        for part in args.parts:
            row = dict(base, **time_part(args.task, part, args.repeats))
            print(json.dumps(row), flush=True)
            merge_rows(RESULTS, [row], FIELDS)
        return
    if args.what == "depth":
        from rebel_jax.envs import dmc  # noqa: PLC0415

        models = {f"chain{n}": chain(n) for n in args.depths}
        models.update(
            {task: dmc.mj_model(task, simulated=True) for task in ("walker_walk", "cheetah_run", "quadruped_walk")}
        )
        models[args.task] = metaworld.mj_model(args.task)
        for name, m in models.items():
            row = dict(base, task=name, part="kinematics", **time_kinematics(m, args.repeats))
            print(json.dumps(row), flush=True)
            merge_rows(RESULTS, [row], FIELDS)
        return
    if args.what == "agree":
        options = dict(args.option or [("xla_cpu_use_fusion_emitters", False)])
        out = agree(args.task, args.every or 64, options)
    elif args.what == "fidelity":
        out = fidelity(args.task, args.every or 16)
    else:
        out = {"census": census, "near": near}[args.what](args.task)
    row = dict(base, part=args.what, **out)
    print(json.dumps(row, indent=1), flush=True)
    merge_rows(RESULTS, [row], FIELDS)


if __name__ == "__main__":
    main(sys.argv[1:])
