"""Nothing traced into the run's programs is tied to one device.

``train.compiled`` runs the seed-vmapped programs on every device (several GPUs, one block of seeds
each, ``sweep.per_device``). A program that places data on one device (``jax.device_put(x, device)``
traced inside it), or that closes over an array committed to one device, asks every device's block
to live on that device: on two GPUs XLA crashed with a segmentation fault in the first ``init``.
MJX does both by default: ``mjx.put_model`` and ``mjx.make_data`` commit their arrays to the first
device (mujoco 3.17, ``mjx/_src/io.py:463`` and ``:771``). On CPU the crash does not show, but both
are visible in the traced programs: these tests read them there.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import pytest
from jax.extend import core
from mujoco import mjx

from rebel_jax import config, train
from rebel_jax.envs import make_env


def _device_ties(closed: core.ClosedJaxpr) -> list[str]:
    """What in ``closed`` (sub-programs included) is tied to one device: pinned placements and committed constants."""
    found = [f"constant committed to {c.sharding}" for c in closed.consts if isinstance(c, jax.Array) and c.committed]
    for eqn in closed.jaxpr.eqns:
        if eqn.primitive.name == "device_put" and any(d is not None for d in eqn.params["devices"]):
            found.append(f"device_put to {eqn.params['devices'][0]}")
        for value in eqn.params.values():
            for sub in value if isinstance(value, tuple | list) else (value,):
                if isinstance(sub, core.ClosedJaxpr):
                    found += _device_ties(sub)
                elif isinstance(sub, core.Jaxpr):
                    found += _device_ties(core.ClosedJaxpr(sub, []))
    return found


def test_the_check_sees_what_mjx_ties_to_a_device():
    env = make_env("walker_walk", episode_length=10)
    committed = mjx.put_model(env.mj_model)
    placed = jax.make_jaxpr(lambda key: mjx.make_data(env.sys))(jax.random.PRNGKey(0))
    closed_over = jax.make_jaxpr(lambda key: mjx.forward(committed, env.reset(key).pipeline_state))(
        jax.random.PRNGKey(0)
    )
    assert any(tie.startswith("device_put") for tie in _device_ties(placed))
    assert any(tie.startswith("constant") for tie in _device_ties(closed_over))


@pytest.mark.parametrize(
    "task",
    # quadruped_walk in make test-heavy (its compile); its reset and step are DMCEnv's, as walker's and cheetah's
    [
        "walker_walk",
        "cheetah_run",
        pytest.param("quadruped_walk", marks=pytest.mark.heavy),
        "probe_point",
        "walker_walk_pixels",
    ],
)
def test_reset_and_step_are_tied_to_no_device(task):
    env = make_env(task, episode_length=10)
    key = jax.random.PRNGKey(0)
    assert _device_ties(jax.make_jaxpr(env.reset)(key)) == []
    state = jax.eval_shape(env.reset, key)
    assert _device_ties(jax.make_jaxpr(env.step)(state, jnp.zeros(env.action_size))) == []


def test_tasks_build_on_this_process_s_devices(monkeypatch):
    """With several processes ``jax.devices()[0]`` is process 0's device, which another process cannot read."""
    first = jax.devices()[0]
    remote = [type("Remote", (), {"platform": first.platform, "id": 99, "process_index": 1})()]
    monkeypatch.setattr(jax, "devices", lambda *a, **k: remote)  # what MJX places on by default
    env = make_env("walker_walk", episode_length=10)  # MJX's default placement would fail here
    assert not any(x.committed for x in jax.tree.leaves(env.sys) if isinstance(x, jax.Array))


@pytest.mark.parametrize(
    ("algo", "task"),
    [
        # make test-heavy: SAC's programs alone; PEBBLE's below hold SAC's update and the same env programs
        pytest.param("sac", "walker_walk", marks=pytest.mark.heavy),
        ("pebble", "walker_walk"),
        # make test-heavy: the pixel programs' trace; the pixel task's reset and step are checked above
        pytest.param("drqv2", "walker_walk_pixels", marks=pytest.mark.heavy),
    ],
)
def test_the_run_programs_are_tied_to_no_device(algo, task):
    tiny = config.PRESETS["tiny"]
    cfg = dataclasses.replace(tiny, algo=algo, env=dataclasses.replace(tiny.env, task=task))
    trainer = train.Trainer(cfg)
    keys = train.seed_keys(0, 2)
    init, round_fn, _ = train.compiled(trainer)
    assert _device_ties(jax.make_jaxpr(init)(keys)) == []
    states = jax.eval_shape(init, keys)
    assert _device_ties(jax.make_jaxpr(round_fn)(states, jnp.int32(1))) == []


# make test-heavy (16 s, the benchmark's three sharded compiles): make test checks the run programs' placement above.
@pytest.mark.heavy
def test_sharded_compile_reports_each_part_over_two_devices():
    script = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "sharded_compile.py"
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    command = [
        sys.executable,
        str(script),
        "--task",
        "probe_point",
        "--parts",
        "evaluate",
        "--seeds-per-device",
        "1",
        "--jobs",
        "2",
    ]
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)
    rows = [json.loads(line) for line in done.stdout.splitlines()]
    assert [(r["part"], r["mode"], r["status"]) for r in rows] == [
        ("evaluate", "per_device", "ok"),
        ("evaluate", "shard_map", "ok"),
        ("evaluate", "partitioner", "ok"),
    ]
    assert all(len(r["devices"]) == 2 and r["compile_seconds"] > 0 for r in rows)


@pytest.mark.heavy  # make test-heavy: a tiny PEBBLE run, about 2 minutes on 2 cores
def test_pebble_in_one_process_over_two_cpu_devices_finishes(tmp_path):
    """The run that used to hang in the CPU runtime (one process, 2 forced CPU devices, PEBBLE), with a deadline."""
    run_dir = tmp_path / "run"
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    command = [sys.executable, "-m", "rebel_jax.train", "--preset", "tiny", "--algo", "pebble", "--task", "probe_point"]
    command += ["--seeds", "2", "--total-steps", "4000", "--no-progress", "--no-tensorboard", "--run-dir", str(run_dir)]
    done = subprocess.run(command, capture_output=True, text=True, env=dict(os.environ, XLA_FLAGS=flags), timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    meta = json.loads((run_dir / "meta.json").read_text())
    assert len(meta["devices"]) == 2, meta["devices"]
    rounds = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert rounds[-1]["labels_used"] == [20, 20]
