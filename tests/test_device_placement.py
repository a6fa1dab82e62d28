"""Nothing traced into the run's programs pins data to one device.

``jax.device_put(x, device)`` inside a traced function places its result on that one device. In the
programs that ``train.compiled`` runs per device under ``shard_map`` (several GPUs, one seed block
each), such a placement asks every device's block to live on the first device: on two GPUs XLA
crashed with a segmentation fault in the first ``init``. ``mjx.make_data`` ends in such a call
(mujoco 3.17, ``mjx/_src/io.py:771``), so the tasks' ``reset`` must not trace it. On CPU the crash
does not show, but the placement is visible in the traced program: these tests read it there.
"""

from __future__ import annotations

import dataclasses

import jax
import pytest
from jax.extend import core
from mujoco import mjx

from rebel_jax import config, train
from rebel_jax.envs import make_env


def _pinned_placements(jaxpr: core.Jaxpr) -> list[str]:
    """Every ``device_put`` of ``jaxpr`` (sub-programs included) whose target is a concrete device."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "device_put" and any(d is not None for d in eqn.params["devices"]):
            found.append(str(eqn.params["devices"][0]))
        for sub in core.jaxprs_in_params(eqn.params):
            found += _pinned_placements(sub)
    return found


def test_the_check_sees_the_placement_of_mjx_make_data():
    env = make_env("walker_walk", episode_length=10)
    jaxpr = jax.make_jaxpr(lambda key: mjx.make_data(env.sys))(jax.random.PRNGKey(0)).jaxpr
    assert _pinned_placements(jaxpr)


@pytest.mark.parametrize(
    "task", ["walker_walk", "cheetah_run", "quadruped_walk", "quadruped_run", "probe_point", "walker_walk_pixels"]
)
def test_reset_and_step_place_nothing(task):
    env = make_env(task, episode_length=10)
    reset = jax.make_jaxpr(env.reset)(jax.random.PRNGKey(0))
    assert _pinned_placements(reset.jaxpr) == []
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    step = jax.make_jaxpr(env.step)(state, jax.numpy.zeros(env.action_size))
    assert _pinned_placements(step.jaxpr) == []


@pytest.mark.parametrize("algo", ["sac", "pebble"])
def test_the_run_programs_place_nothing(algo):
    cfg = dataclasses.replace(config.PRESETS["tiny"], algo=algo)
    trainer = train.Trainer(cfg)
    keys = train.seed_keys(0, 2)
    init, round_fn, _ = train.compiled(trainer)
    assert _pinned_placements(jax.make_jaxpr(init)(keys).jaxpr) == []
    states = jax.eval_shape(init, keys)
    assert _pinned_placements(jax.make_jaxpr(round_fn)(states, jax.numpy.int32(1)).jaxpr) == []
