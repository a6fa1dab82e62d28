"""Records Meta-World reference data for tests/test_envs_metaworld.py (run in its own environment, not the project's).

Meta-World 3.1.1 pins mujoco==3.3.0 while rebel_jax pins mujoco 3.17.0, so the reference comes from a separate
virtual environment:

    python3.11 -m venv /tmp/mwenv && /tmp/mwenv/bin/pip install metaworld==3.1.1 packaging
    /tmp/mwenv/bin/python tests/data/metaworld/make_reference.py [TASK ...]

(gymnasium 1.4, which metaworld pulls in, imports ``packaging`` without requiring it). It writes
``tests/data/metaworld/<task>.npz`` for each task named (all of :data:`TASKS` without names), and the state that
Meta-World's reset leaves the arm in, ``src/rebel_jax/envs/metaworld_assets/hand_reset.npz`` (the same at every
reset: the objects are away from the hand's path; the tests check it; the other tasks' states are kept). Each test
file holds:

- ``reset_*``: :data:`RESETS` independent resets (Meta-World's ``_last_rand_vec``, ``_target_pos``,
  ``obj_init_pos``), for the KS tests of the reset distribution;
- per step of :data:`EPISODES` episodes (half under uniform random actions, half under Meta-World's scripted policy
  of the task), the MuJoCo state (``qpos``, ``qvel``, ``mocap_pos``, ``mocap_quat``, ``qacc_warmstart``), the action
  that led there, the observation, the reward and the info flags; step 0 of an episode is its reset state;
- per episode: every draw of the reset space during the reset (``episode_draws``: Meta-World's ``reset`` runs
  ``reset_model`` twice, and its observation shows the object where the first draw put it), the model's
  ``body_pos`` after the reset (the reset moves object bodies in the model), the target
  position and ``init_tcp`` (the fingertip centre after the reset, which the rewards read).

The environments are built as the PbRL code bases build them (rll-research/BPref@f3ece2e:utils.py,
``make_metaworld_env``, the same in huxiao09/QPA@502a966:utils.py): a fresh random object position at every reset
(``_freeze_rand_vec = False``), drawn here from the seeded generator (``seeded_rand_vec``) for reproducibility, and
with the goal observable (``_partially_observable = False``) so that the observation's last three numbers are tested
too.
"""

from __future__ import annotations

import pathlib
import sys

import metaworld
import mujoco
import numpy as np
from metaworld import policies
from metaworld.env_dict import ALL_V3_ENVIRONMENTS

TASKS = {
    "drawer-open": policies.SawyerDrawerOpenV3Policy,
    "door-open": policies.SawyerDoorOpenV3Policy,
    "button-press": policies.SawyerButtonPressV3Policy,
    "sweep-into": policies.SawyerSweepIntoV3Policy,
    "window-open": policies.SawyerWindowOpenV3Policy,
    "door-unlock": policies.SawyerDoorUnlockV3Policy,
    "hammer": policies.SawyerHammerV3Policy,
}
RESETS = 1000
EPISODES = 4  # 2 random, 2 scripted: 4 x 501 states
SEED = 0
INFO_KEYS = ("success", "near_object", "grasp_success", "grasp_reward", "in_place_reward", "obj_to_target")


def make(task: str, seed: int):
    env = ALL_V3_ENVIRONMENTS[f"{task}-v3"]()
    env._partially_observable = False
    env._freeze_rand_vec = False
    env.seeded_rand_vec = True
    env._set_task_called = True
    del env.sawyer_observation_space  # recomputed for the goal-observable observation
    env.seed(seed)
    return env


def state(env) -> dict[str, np.ndarray]:
    d = env.data
    return {
        "qpos": d.qpos.copy(),
        "qvel": d.qvel.copy(),
        "mocap_pos": d.mocap_pos.copy(),
        "mocap_quat": d.mocap_quat.copy(),
        "qacc_warmstart": d.qacc_warmstart.copy(),
    }


def record(task: str) -> dict[str, np.ndarray]:
    env = make(task, SEED)
    out: dict[str, list] = {k: [] for k in ("rand_vec", "target_pos", "obj_init_pos")}
    for _ in range(RESETS):
        env.reset()
        out["rand_vec"].append(env._last_rand_vec.copy())
        out["target_pos"].append(np.asarray(env._target_pos, np.float64).copy())
        out["obj_init_pos"].append(np.asarray(env.obj_init_pos, np.float64).copy())
    data = {f"reset_{k}": np.asarray(v) for k, v in out.items()}

    steps: dict[str, list] = {}
    episodes: dict[str, list] = {"body_pos": [], "target_pos": [], "init_tcp": [], "scripted": [], "draws": []}
    rng = np.random.default_rng(SEED)
    policy = TASKS[task]()
    draw = env._get_state_rand_vec
    draws: list[np.ndarray] = []
    env._get_state_rand_vec = lambda: draws.append(draw().copy()) or draws[-1]
    for e in range(EPISODES):
        scripted = e >= EPISODES // 2
        draws.clear()
        obs, _ = env.reset()
        episodes["draws"].append(np.asarray(draws))
        episodes["body_pos"].append(env.model.body_pos.copy())
        episodes["target_pos"].append(np.asarray(env._target_pos, np.float64).copy())
        episodes["init_tcp"].append(np.asarray(env.init_tcp, np.float64).copy())
        episodes["scripted"].append(scripted)
        rows = [
            dict(
                state(env),
                obs=obs.copy(),
                action=np.zeros(4),
                reward=np.nan,
                episode=e,
                t=0,
                **dict.fromkeys(INFO_KEYS, np.nan),
            )
        ]
        for t in range(1, env.max_path_length + 1):
            a = policy.get_action(obs) if scripted else rng.uniform(-1, 1, 4)
            a = np.asarray(a, np.float32)
            obs, reward, _, _, info = env.step(a)
            # A copy: some scripted policies shift the observation they are given in place (door-open's moves the
            # handle's x by -0.05, metaworld@3.1.1:metaworld/policies/sawyer_door_open_v3_policy.py:37-39).
            rows.append(
                dict(
                    state(env),
                    obs=obs.copy(),
                    action=a,
                    reward=reward,
                    episode=e,
                    t=t,
                    **{k: info[k] for k in INFO_KEYS},
                )
            )
        for row in rows:
            for k, v in row.items():
                steps.setdefault(k, []).append(np.asarray(v))
    data.update({k: np.asarray(v) for k, v in steps.items()})
    data.update({f"episode_{k}": np.asarray(v) for k, v in episodes.items()})
    # The state after the first recorded episode's reset (after RESETS resets), not after a fresh environment's first
    # reset: door-unlock's first reset leaves the arm 1e-4 rad from where every later reset leaves it.
    data["hand_reset"] = {k: data[k][0] for k in ("qpos", "qvel", "mocap_pos", "mocap_quat", "qacc_warmstart")}
    data["versions"] = np.asarray([metaworld.__name__ + "==3.1.1", f"mujoco=={mujoco.__version__}"])
    return data


def main(tasks: list[str]) -> None:
    here = pathlib.Path(__file__).parent
    package = here.parents[2] / "src" / "rebel_jax" / "envs" / "metaworld_assets"
    with np.load(package / "hand_reset.npz") as kept:  # the other tasks' reset states stay as they are
        resets = {k: kept[k] for k in kept.files if k.split("/")[0] not in tasks}
    for task in tasks:
        data = record(task)
        resets.update({f"{task}/{k}": v for k, v in data.pop("hand_reset").items()})
        np.savez_compressed(here / f"{task}.npz", **data)
        print(
            task,
            {k: v.shape for k, v in data.items()},
            "success rate of scripted steps:",
            float(np.nanmean(data["success"][len(data["success"]) // 2 :])),
        )
    np.savez(package / "hand_reset.npz", **resets)


if __name__ == "__main__":
    main(sys.argv[1:] or list(TASKS))
