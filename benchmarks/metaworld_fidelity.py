"""How close the Meta-World tasks come to Meta-World 3.1.1 itself, on a CPU.

Usage:
  python benchmarks/metaworld_fidelity.py [--tasks drawer-open] [--every 16] [--no-step] [--refused-step]
      [--warp door-open ...]

Against the data recorded from Meta-World (tests/data/metaworld/<task>.npz, made by
tests/data/metaworld/make_reference.py), for each task of ``--tasks`` (built as ``metaworld_<task>``):

- ``states``: observation, reward and success at all recorded states after a reset (largest errors, mismatches);
- ``reset``: the reset at the draws Meta-World made (largest errors of observation, goal, fingertip centre, qpos);
- ``hand_reset_mujoco_3_17``: Meta-World's hand reset (50 control steps to ``hand_init_pos``) run by this MuJoCo
  (3.17) instead of Meta-World's (3.3): largest differences of qpos and qvel;
- ``step``: one control step of MJX's JAX step in float32 from every ``--every``-th recorded state, against the
  state Meta-World reached with the same action (median and largest errors per state) and the compile time; a task
  whose step the tasks refuse (``metaworld.STEP_REFUSED``) only with ``--refused-step``, where MJX builds its model.

``--warp`` runs the same one-step comparison with MuJoCo Warp's step (MJX ``impl='warp'``, warp-lang installed) on
the listed tasks' models, which MJX's JAX step cannot collide (cylinder-box); only the physics is compared there.
Writes ``benchmarks/results/metaworld_fidelity.json``.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import os
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from rebel_jax.envs import metaworld

ROOT = pathlib.Path(__file__).parents[1]
DATA = ROOT / "tests" / "data" / "metaworld"
RESULTS = ROOT / "benchmarks" / "results" / "metaworld_fidelity.json"
XML = {
    "drawer-open": "sawyer_drawer.xml",
    "door-open": "sawyer_door_pull.xml",
    "button-press": "sawyer_button_press.xml",
}
HAND = {"drawer-open": ((-0.5, 0.40, 0.05), (0.5, 1.0, 0.5))}  # the mocap bounds of each task's hand
for _t in ("door-open", "button-press"):  # metaworld@3.1.1: sawyer_door_v3.py:29-30, sawyer_button_press_v3.py:26-27
    HAND[_t] = ((-0.5, 0.40, 0.05), (0.5, 1.0, 0.5))


# MuJoCo Warp's buffers per world: its defaults (48 contacts, 64 constraint rows for these models) overflow on
# contact-rich states and drop contacts.
CONTACTS, CONSTRAINTS = 256, 1024


def _f32(x) -> np.ndarray:
    return np.asarray(x, np.float32)


def _stats(err: np.ndarray) -> dict:
    per_state = err.reshape(len(err), -1).max(1)
    return {"median": float(np.median(per_state)), "max": float(per_state.max())}


def episodes(env: metaworld.MetaWorldEnv, ref: dict):
    """The resets of the recorded episodes, at the draws Meta-World made."""
    draws = ref["episode_draws"]
    return jax.jit(jax.vmap(env.reset_to))(_f32(draws[:, -1]), _f32(draws[:, 0]))


def states_at(env: metaworld.MetaWorldEnv, ref: dict, rows: np.ndarray, resets):
    """Our states at recorded rows (steps after a reset) of the episodes ``resets`` began."""
    info = jax.tree.map(lambda x: x[ref["episode"][rows]], resets.info)
    return jax.jit(jax.vmap(env.state_at))(
        _f32(ref["qpos"][rows]),
        _f32(ref["qvel"][rows]),
        _f32(ref["mocap_pos"][rows]),
        _f32(ref["mocap_quat"][rows]),
        _f32(ref["qacc_warmstart"][rows]),
        _f32(ref["obs"][rows - 1, :18]),
        {k: info[k] for k in ("target_pos", "init_tcp", "body_pos", "consts")},
        _f32(ref["action"][rows]),
    )


def hand_reset_in_this_mujoco(task: str) -> tuple[np.ndarray, np.ndarray]:
    """Meta-World's ``_reset_hand`` (sawyer_xyz_env.py:684-695) run by this MuJoCo: qpos and qvel after it."""
    model = metaworld.mj_model(task)
    data = mujoco.MjData(model)
    mujoco.mj_resetData(model, data)
    for _ in range(metaworld.HAND_RESET_STEPS):
        data.mocap_pos[0] = metaworld.TASKS[task].hand_init_pos
        data.mocap_quat[0] = metaworld.MOCAP_QUAT
        data.ctrl[:] = (-1.0, 1.0)
        mujoco.mj_step(model, data, nstep=metaworld.FRAME_SKIP)
    return data.qpos.copy(), data.qvel.copy()


def measure(task: str, every: int, step: bool = True, refused_step: bool = False) -> dict:
    ref = dict(np.load(DATA / f"{task}.npz"))
    env = metaworld.MetaWorldEnv(task)
    if refused_step:  # the step is measured here, not offered: the tasks keep refusing it
        env.step_refused = None
    out: dict = {"versions": [str(v) for v in ref["versions"]]}
    rows = np.where(ref["t"] > 0)[0]
    r = episodes(env, ref)
    s = states_at(env, ref, rows, r)
    out["states"] = {
        "n": len(rows),
        "successes": int(ref["success"][rows].sum()),
        "obs_max_err": float(np.abs(np.asarray(s.obs) - ref["obs"][rows]).max()),
        "reward_max_err": float(np.abs(np.asarray(s.reward) - ref["reward"][rows]).max()),
        "success_mismatches": int((np.asarray(s.info["success"]) != ref["success"][rows]).sum()),
        "grasp_success_mismatches": int((np.asarray(s.metrics["grasp_success"]) != ref["grasp_success"][rows]).sum()),
        "info_terms_max_err": {
            k: float(np.abs(np.asarray(s.metrics[k]) - ref[k][rows]).max())
            for k in ("near_object", "grasp_reward", "in_place_reward", "obj_to_target")
        },
    }
    first = np.where(ref["t"] == 0)[0]
    out["reset"] = {
        "n": len(first),
        "obs_max_err": float(np.abs(np.asarray(r.obs) - ref["obs"][first]).max()),
        "target_max_err": float(np.abs(np.asarray(r.info["target_pos"]) - ref["episode_target_pos"]).max()),
        "init_tcp_max_err": float(np.abs(np.asarray(r.info["init_tcp"]) - ref["episode_init_tcp"]).max()),
        "qpos_max_err": float(np.abs(np.asarray(r.pipeline_state.qpos) - ref["qpos"][first]).max()),
    }
    qpos, qvel = hand_reset_in_this_mujoco(task)
    n = env.spec.object_qpos  # the object's position (sweep-into: x and y) is the reset's draw, not the hand reset's
    qpos[9 : 9 + n] = ref["qpos"][first[0], 9 : 9 + n]
    if n:  # and the reset zeroes its velocity (sawyer_xyz_env.py:351-361, sawyer_hammer_v3.py:101-106)
        qvel[9:15] = 0.0
    out["hand_reset_mujoco_3_17"] = {
        "mujoco": mujoco.__version__,
        "qpos_max_diff": float(np.abs(qpos - ref["qpos"][first[0]]).max()),
        "qvel_max_diff": float(np.abs(qvel - ref["qvel"][first[0]]).max()),
    }
    if env.step_refused or not step:
        return out
    rows = rows[ref["t"][rows] < metaworld.EPISODE_LENGTH][::every]
    start = time.perf_counter()
    stepped = jax.jit(jax.vmap(env.step))(states_at(env, ref, rows, r), _f32(ref["action"][rows + 1]))
    jax.block_until_ready(stepped)
    nxt = rows + 1
    out["step"] = {
        "impl": "jax",
        "n": len(rows),
        "compile_and_run_s": round(time.perf_counter() - start, 1),
        "qpos_err": _stats(np.abs(np.asarray(stepped.pipeline_state.qpos) - ref["qpos"][nxt])),
        "qvel_err": _stats(np.abs(np.asarray(stepped.pipeline_state.qvel) - ref["qvel"][nxt])),
        "obs_err": _stats(np.abs(np.asarray(stepped.obs) - ref["obs"][nxt])),
        "reward_err": _stats(np.abs(np.asarray(stepped.reward) - ref["reward"][nxt])),
        "success_mismatches": int((np.asarray(stepped.info["success"]) != ref["success"][nxt]).sum()),
    }
    return out


def measure_warp(task: str, every: int) -> dict:
    """One control step of MuJoCo Warp's step (float32) from recorded states: the mocap moved as Meta-World moves
    it, the gripper set, 5 physics steps; the model's bodies where the recorded reset put them."""
    from mujoco import mjx  # noqa: PLC0415

    ref = dict(np.load(DATA / f"{task}.npz"))
    model = mujoco.MjModel.from_xml_path(str(metaworld.ASSETS / "sawyer_xyz" / XML[task]))
    for i in range(model.neq):
        model.eq_data[i, : len(metaworld.WELD_DATA)] = metaworld.WELD_DATA
    low, high = (jnp.asarray(b) for b in HAND[task])

    def one(m, qpos, qvel, mocap_pos, qacc_warmstart, action):
        d = mjx.make_data(model, impl="warp", naconmax=CONTACTS, njmax=CONSTRAINTS)
        mocap = jnp.clip(mocap_pos[0] + jnp.clip(action[:3], -1, 1) * metaworld.ACTION_SCALE, low, high)
        d = d.replace(
            qpos=qpos,
            qvel=qvel,
            qacc_warmstart=qacc_warmstart,
            mocap_pos=mocap[None],
            mocap_quat=jnp.asarray([metaworld.MOCAP_QUAT]),
            ctrl=jnp.stack([action[3], -action[3]]),
        )
        for _ in range(metaworld.FRAME_SKIP):
            d = mjx.step(m, d)
        return d.qpos, d.qvel

    rows = np.where((ref["t"] > 0) & (ref["t"] < metaworld.EPISODE_LENGTH))[0][::every]
    qpos_err, qvel_err = [], []
    start = time.perf_counter()
    for e in np.unique(ref["episode"][rows]):
        model.body_pos[:] = ref["episode_body_pos"][e]
        step = jax.jit(functools.partial(one, mjx.put_model(model, impl="warp")))
        for i in rows[ref["episode"][rows] == e]:
            q, v = step(
                _f32(ref["qpos"][i]),
                _f32(ref["qvel"][i]),
                _f32(ref["mocap_pos"][i]),
                _f32(ref["qacc_warmstart"][i]),
                _f32(ref["action"][i + 1]),
            )
            qpos_err.append(np.abs(np.asarray(q) - ref["qpos"][i + 1]).max())
            qvel_err.append(np.abs(np.asarray(v) - ref["qvel"][i + 1]).max())
    return {
        "impl": "warp",
        "device": "cpu",
        "n": len(rows),
        "seconds": round(time.perf_counter() - start, 1),
        "qpos_err": _stats(np.asarray(qpos_err)),
        "qvel_err": _stats(np.asarray(qvel_err)),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="*", default=list(metaworld.TASKS))
    parser.add_argument("--every", type=int, default=16)
    parser.add_argument("--warp", nargs="*", default=[])
    parser.add_argument("--no-step", action="store_true", help="leave out the one-step comparison")
    parser.add_argument(
        "--refused-step", action="store_true", help="compare the step of a task that refuses it (MJX builds its model)"
    )
    args = parser.parse_args(argv)
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    for task in args.tasks:
        results[task] = dict(
            measure(task, args.every, step=not args.no_step, refused_step=args.refused_step),
            date=datetime.date.today().isoformat(),
            JAX_DISABLE_MOST_OPTIMIZATIONS=os.environ.get("JAX_DISABLE_MOST_OPTIMIZATIONS", ""),
            XLA_FLAGS=os.environ.get("XLA_FLAGS", ""),
        )
        print(task, json.dumps(results[task]), flush=True)
    for task in args.warp:
        results.setdefault(task, {})["step_warp"] = measure_warp(task, args.every)
        print(task, json.dumps(results[task]["step_warp"]), flush=True)
    RESULTS.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
