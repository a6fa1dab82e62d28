"""``benchmarks/overlap.py``: its modes compute what they claim, so that their times compare like with like."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from rebel_jax.agents.sac import SAC
from rebel_jax.config import PRESETS
from rebel_jax.envs import make_env


def _final_states(bench, modes):
    env = make_env("probe_point")
    cfg = dataclasses.replace(PRESETS["paper"].sac, precision="bf16", hidden=16, batch_size=8)
    sac = SAC(cfg, env.observation_size, env.action_size)
    out = {}
    for mode in modes:
        run, state = bench.vector_steps(env, sac, mode, columns=2, num_envs=3, updates=2, steps=3)
        out[mode] = run(state, jax.random.PRNGKey(7))
    return out


def _equal(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


# make test-heavy (14 s of compiles of a benchmark): the trainer's --overlap path is tested in test_overlap.py.
@pytest.mark.heavy
def test_modes_step_the_same_physics_and_only_serial_updates_read_it(benchmark_script):
    bench = benchmark_script("overlap")
    states = _final_states(bench, bench.MODES)
    env = {mode: s[0] for mode, s in states.items()}
    agent = {mode: s[1] for mode, s in states.items()}
    assert _equal(env["physics"], env["independent"]) and _equal(env["physics"], env["serial"])
    assert _equal(env["stream"], env["independent"])  # the stream annotation changes where, not what
    assert _equal(agent["updates"], agent["independent"]) and _equal(agent["stream"], agent["independent"])
    assert _equal(agent["stream_updates"], agent["independent"]) and _equal(env["stream_updates"], env["physics"])
    assert not _equal(agent["serial"], agent["independent"])  # serial's minibatches hold the new observations
    assert not _equal(agent["physics"], agent["updates"])  # physics alone leaves the agent as it started
