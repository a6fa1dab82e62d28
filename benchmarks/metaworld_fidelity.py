"""How close the Meta-World tasks come to Meta-World 3.1.1 itself.

Usage:
  python benchmarks/metaworld_fidelity.py [--tasks drawer-open] [--every 16] [--no-step] [--refused-step]
      [--impl warp] [--episodes]

Against the data recorded from Meta-World (tests/data/metaworld/<task>.npz, made by
tests/data/metaworld/make_reference.py), for each task of ``--tasks`` (built as ``metaworld_<task>``):

- ``states``: observation, reward and success at all recorded states after a reset (largest errors, mismatches);
- ``reset``: the reset at the draws Meta-World made (largest errors of observation, goal, fingertip centre, qpos);
- ``hand_reset_mujoco_3_17``: Meta-World's hand reset (50 control steps to ``hand_init_pos``) run by this MuJoCo
  (3.17) instead of Meta-World's (3.3): largest differences of qpos and qvel;
- ``step`` (``step_warp`` with ``--impl warp``): one control step of the task's physics step in float32 from every
  ``--every``-th recorded state, against the state Meta-World reached with the same action (median and largest
  errors per state: qpos, qvel, observation, reward, success) and the compile time, beside the same step of this
  MuJoCo in float64 on the CPU (``mujoco_3_17_float64``: what the engines' versions alone change). A task whose
  step the engine refuses (``metaworld.STEP_REFUSED``) only with ``--refused-step``, where MJX builds its model.

- ``episodes`` (``episodes_warp``), with ``--episodes``: every recorded episode (random actions, and Meta-World's
  scripted policy) replayed open-loop from its reset: returns, steps flagged successful and observation errors
  against Meta-World's own episode.

With ``--impl warp`` (warp-lang installed) only the step is measured and the other entries are kept. Writes
``benchmarks/results/metaworld_fidelity.json``; runs on whatever device JAX picks.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import sys
import time

import jax
import mujoco
import numpy as np

from rebel_jax.envs import metaworld

ROOT = pathlib.Path(__file__).parents[1]
DATA = ROOT / "tests" / "data" / "metaworld"
RESULTS = ROOT / "benchmarks" / "results" / "metaworld_fidelity.json"


def _f32(x) -> np.ndarray:
    return np.asarray(x, np.float32)


def _stats(err: np.ndarray) -> dict:
    per_state = err.reshape(len(err), -1).max(1)
    return {
        "median": float(np.median(per_state)),
        "max": float(per_state.max()),
        "states_over_1e-3": int((per_state > 1e-3).sum()),
    }


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


def replay(env: metaworld.MetaWorldEnv, ref: dict) -> dict[str, np.ndarray]:
    """Every recorded episode's actions played open-loop from its reset (at Meta-World's draws), all episodes in one
    vmapped scan: per episode and step, the reward, the success flag and the largest observation error."""
    resets = episodes(env, ref)
    n = len(ref["episode_draws"])
    steps = [ref["action"][(ref["episode"] == e) & (ref["t"] > 0)] for e in range(n)]
    actions = _f32(np.stack(steps, 1))  # (steps, episodes, 4)

    def body(state, action):
        state = jax.vmap(env.step)(state, action)
        return state, (state.obs, state.reward, state.info["success"], state.pipeline_state.qpos)

    obs, reward, success, qpos = jax.jit(lambda s, a: jax.lax.scan(body, s, a)[1])(resets, actions)
    theirs = np.stack([ref["obs"][(ref["episode"] == e) & (ref["t"] > 0)] for e in range(n)], 1)
    return {
        "reward": np.asarray(reward),
        "success": np.asarray(success),
        "obs_err": np.abs(np.asarray(obs) - theirs).max(-1),
        "qpos": np.asarray(qpos),
    }


def mujoco_replay(task: str, ref: dict) -> np.ndarray:
    """The recorded episodes' actions played open-loop by this MuJoCo (3.17, float64) from their recorded resets:
    qpos per step and episode, (steps, episodes, nq)."""
    model = metaworld.mj_model(task)
    data = mujoco.MjData(model)
    out = []
    for e in range(len(ref["episode_draws"])):
        rows = np.where(ref["episode"] == e)[0]
        model.body_pos[:] = ref["episode_body_pos"][e]
        mujoco.mj_resetData(model, data)
        for field in ("qpos", "qvel", "qacc_warmstart", "mocap_pos", "mocap_quat"):
            getattr(data, field)[:] = ref[field][rows[0]]
        qpos = []
        for i in rows[1:]:
            metaworld.mujoco_step(model, data, task, data.mocap_pos[0].copy(), ref["action"][i])
            qpos.append(data.qpos.copy())
        out.append(qpos)
    return np.asarray(out).transpose(1, 0, 2)


def _at_steps(err: np.ndarray) -> list[list[float]]:
    """Per episode, ``err`` (steps, episodes) after 10, 100 and 500 steps."""
    return [[float(e[t - 1]) for t in (10, 100, 500)] for e in err.T]


def _replayed(env: metaworld.MetaWorldEnv, ref: dict) -> dict:
    """:func:`replay` against Meta-World's own episodes: returns, successful steps and observation errors."""
    start = time.perf_counter()
    ours = replay(env, ref)
    rows = [(ref["episode"] == e) & (ref["t"] > 0) for e in range(len(ref["episode_draws"]))]
    theirs = mujoco_replay(env.spec.name, ref)
    recorded = np.stack([ref["qpos"][r] for r in rows], 1)
    return {
        "episodes": len(rows),
        "scripted": [bool(x) for x in ref["episode_scripted"]],
        "return": [round(float(x), 2) for x in ours["reward"].sum(0)],
        "metaworld_return": [round(float(ref["reward"][r].sum()), 2) for r in rows],
        "success_steps": [int(x) for x in ours["success"].sum(0)],
        "metaworld_success_steps": [int(np.nansum(ref["success"][r])) for r in rows],
        "obs_err_at_step_10_100_500": _at_steps(ours["obs_err"]),
        # Open-loop replays drift apart where the fingers push objects: MuJoCo 3.17's own replay against the
        # recording (MuJoCo 3.3) measures how much the engine's version alone moves them; ours against MuJoCo 3.17's.
        "mujoco_3_17_qpos_err_at_step_10_100_500": _at_steps(np.abs(theirs - recorded).max(-1)),
        "ours_vs_mujoco_3_17_qpos_at_step_10_100_500": _at_steps(np.abs(ours["qpos"] - theirs).max(-1)),
        "compile_and_run_s": round(time.perf_counter() - start, 1),
    }


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


def mujoco_step(task: str, ref: dict, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One control step of this MuJoCo (3.17, float64, the CPU; ``metaworld.mujoco_step``) from the recorded states
    ``rows``: qpos and qvel after it. Against the recording (Meta-World's MuJoCo 3.3) it separates the engines'
    versions from the ports' differences."""
    model = metaworld.mj_model(task)
    data = mujoco.MjData(model)
    qpos, qvel = [], []
    for i in rows:
        model.body_pos[:] = ref["episode_body_pos"][ref["episode"][i]]
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = ref["qpos"][i], ref["qvel"][i]
        data.qacc_warmstart[:] = ref["qacc_warmstart"][i]
        metaworld.mujoco_step(model, data, task, ref["mocap_pos"][i][0], ref["action"][i + 1])
        qpos.append(data.qpos.copy())
        qvel.append(data.qvel.copy())
    return np.asarray(qpos), np.asarray(qvel)


def measure(
    task: str, every: int, step: bool = True, refused_step: bool = False, impl: str = "jax", replay_episodes=False
) -> dict:
    ref = dict(np.load(DATA / f"{task}.npz"))
    rows = np.where(ref["t"] > 0)[0]
    stepped_rows = rows[ref["t"][rows] < metaworld.EPISODE_LENGTH][::every]
    env = metaworld.MetaWorldEnv(task, impl=impl, worlds=len(stepped_rows))
    if refused_step:  # the step is measured here, not offered: the tasks keep refusing it
        env.step_refused = None
    out: dict = {"versions": [str(v) for v in ref["versions"]]}
    r = episodes(env, ref)
    if impl == "jax":  # the states, reset and hand reset do not depend on the engine: measured with the JAX one
        out.update(_at_states(env, task, ref, rows, r))
    if not step or env.step_refused:
        return out
    suffix = "" if impl == "jax" else f"_{impl}"
    out[f"step{suffix}"] = _step(env, task, ref, stepped_rows, r, impl)
    if replay_episodes:  # Warp's contact buffer sized for the episodes, not the stepped states
        worlds = len(ref["episode_draws"])
        out[f"episodes{suffix}"] = _replayed(metaworld.MetaWorldEnv(task, impl=impl, worlds=worlds), ref)
    return out


def _at_states(env: metaworld.MetaWorldEnv, task: str, ref: dict, rows: np.ndarray, r, chunk: int = 256) -> dict:
    # about ``chunk`` states at a time: sweep-into's 2,000 at once (MJX's collision and solver each) ask for 25 GB
    parts = [states_at(env, ref, part, r) for part in np.array_split(rows, -(-len(rows) // chunk))]
    s = jax.tree.map(lambda *xs: np.concatenate(xs), *parts)
    out: dict = {}
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
    return out


def _step(env: metaworld.MetaWorldEnv, task: str, ref: dict, rows: np.ndarray, r, impl: str) -> dict:
    nxt = rows + 1
    start = time.perf_counter()
    stepped = jax.jit(jax.vmap(env.step))(states_at(env, ref, rows, r), _f32(ref["action"][nxt]))
    jax.block_until_ready(stepped)
    seconds = round(time.perf_counter() - start, 1)
    qpos, qvel = mujoco_step(task, ref, rows)
    ours = np.asarray(stepped.pipeline_state.qpos), np.asarray(stepped.pipeline_state.qvel)
    return {
        "impl": impl,
        "device": jax.devices()[0].device_kind,
        "n": len(rows),
        "compile_and_run_s": seconds,
        "qpos_err": _stats(np.abs(ours[0] - ref["qpos"][nxt])),
        "qvel_err": _stats(np.abs(ours[1] - ref["qvel"][nxt])),
        "obs_err": _stats(np.abs(np.asarray(stepped.obs) - ref["obs"][nxt])),
        "reward_err": _stats(np.abs(np.asarray(stepped.reward) - ref["reward"][nxt])),
        "success_mismatches": int((np.asarray(stepped.info["success"]) != ref["success"][nxt]).sum()),
        "mujoco_3_17_float64": {
            "qpos_err": _stats(np.abs(qpos - ref["qpos"][nxt])),
            "qvel_err": _stats(np.abs(qvel - ref["qvel"][nxt])),
            "ours_qpos_diff": _stats(np.abs(ours[0] - qpos)),
            "ours_qvel_diff": _stats(np.abs(ours[1] - qvel)),
        },
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="*", default=list(metaworld.TASKS))
    parser.add_argument("--every", type=int, default=16)
    parser.add_argument("--impl", choices=metaworld.IMPLS, default="jax", help="the physics step compared")
    parser.add_argument("--no-step", action="store_true", help="leave out the one-step comparison")
    parser.add_argument(
        "--episodes", action="store_true", help="replay every recorded episode's actions open-loop (with the step)"
    )
    parser.add_argument(
        "--refused-step", action="store_true", help="compare the step of a task that refuses it (MJX builds its model)"
    )
    args = parser.parse_args(argv)
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    for task in args.tasks:
        measured = measure(
            task, args.every, not args.no_step, args.refused_step, args.impl, replay_episodes=args.episodes
        )
        if args.impl != "jax":  # only the step depends on the engine: keep the JAX run's other entries
            measured = {k: v for k, v in measured.items() if k.startswith(("step", "episodes"))}
        results[task] = dict(
            results.get(task, {}),
            **measured,
            date=datetime.date.today().isoformat(),
            JAX_DISABLE_MOST_OPTIMIZATIONS=os.environ.get("JAX_DISABLE_MOST_OPTIMIZATIONS", ""),
            XLA_FLAGS=os.environ.get("XLA_FLAGS", ""),
        )
        print(task, json.dumps(measured), flush=True)
    RESULTS.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])
