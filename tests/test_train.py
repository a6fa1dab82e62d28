"""The scanned round: traced once, seeds by vmap, determinism, resume, sharding, the CLI."""

from __future__ import annotations

import dataclasses
import os
import pathlib
import subprocess
import sys
import textwrap

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.config import Config, EnvConfig, SACConfig, TrainConfig
from rebel_jax.run.checkpoint import Checkpointer
from rebel_jax.run.cli import parse
from rebel_jax.train import Trainer, compiled, seed_keys

# Episodes of 20 steps, rounds of 20 vector steps: resets, seeding and learning all happen. The
# probe task compiles in seconds; the MJX tasks have tests of their own (test_envs*.py).
MICRO = Config(
    env=EnvConfig(task="probe_point", num_envs=2, episode_length=20),
    sac=SACConfig(hidden=16, batch_size=16, utd=0.5),
    train=TrainConfig(total_steps=120, seed_steps=20, steps_per_round=40, eval_every=40, eval_episodes=1),
)
ROUNDS = 3


@pytest.fixture(scope="module")
def micro():
    trainer = Trainer(MICRO)
    # The module runs the round for 2 seeds and for 1 (test_vmap_over_seeds_equals_separate_runs):
    # one trace each; a round traced again (by any test of the module) raises chex's AssertionError.
    chex.clear_trace_counter()
    trainer.round = chex.assert_max_traces(trainer.round, n=2)
    init, round_fn, _ = compiled(trainer)
    return trainer, init, round_fn


def _run(init, round_fn, keys, rounds=ROUNDS, start=None):
    state = init(keys) if start is None else start[1]
    metrics = []
    for r in range(0 if start is None else start[0], rounds):
        state, m = round_fn(state, jnp.int32(r))
        metrics.append(jax.device_get(m))
    return state, metrics


def _assert_trees_equal(a, b, **tol):
    if tol:
        chex.assert_trees_all_close(a, b, **tol)
    else:
        chex.assert_trees_all_equal(a, b)


def test_round_is_traced_once_and_learns_after_seeding(micro):
    _, init, round_fn = micro
    state, metrics = _run(init, round_fn, seed_keys(0, 2))
    assert int(state.agent.steps[0]) > 0  # updates happened after the seed steps
    assert int(state.buffer.size[0]) == MICRO.train.total_steps // MICRO.env.num_envs
    # Episodes of 20 steps finished, so the training and evaluation returns are defined.
    assert np.all(np.isfinite(metrics[-1]["train_return"])) and np.all(np.isfinite(metrics[-1]["eval_return"]))
    assert np.all(np.isfinite(metrics[-1]["critic_loss"]))


def test_same_seed_same_result(micro):
    _, init, round_fn = micro
    a, _ = _run(init, round_fn, seed_keys(3, 2))
    b, _ = _run(init, round_fn, seed_keys(3, 2))
    _assert_trees_equal(a.agent, b.agent)


def test_vmap_over_seeds_equals_separate_runs(micro):
    """Batched and unbatched programs round differently, and chaos and Adam amplify it,
    so parameters are compared by relative norm; the random-action seed phase exactly."""
    _, init, round_fn = micro
    keys = seed_keys(5, 2)
    together, _ = _run(init, round_fn, keys)
    seed_rows = MICRO.train.seed_steps // MICRO.env.num_envs
    for i in range(2):
        alone, _ = _run(init, round_fn, keys[i : i + 1])
        np.testing.assert_allclose(together.buffer.obs[i, :seed_rows], alone.buffer.obs[0, :seed_rows], atol=1e-5)
        for x, y in zip(jax.tree.leaves(together.agent), jax.tree.leaves(alone.agent), strict=True):
            x, y = np.asarray(x[i], np.float64), np.asarray(y[0], np.float64)
            assert np.linalg.norm(x - y) <= 5e-2 * max(np.linalg.norm(y), 1e-6)  # other seeds differ by O(1)


def test_resume_from_checkpoint_equals_uninterrupted(micro, tmp_path):
    _, init, round_fn = micro
    keys = seed_keys(7, 2)
    uninterrupted, _ = _run(init, round_fn, keys)
    first, _ = _run(init, round_fn, keys, rounds=1)
    ckpt = Checkpointer(tmp_path)
    ckpt.save(1, first)
    del first
    start, state = ckpt.restore(init(seed_keys(99, 2)))  # a different state, overwritten by the checkpoint
    # As host arrays: restored device arrays are placed differently from init's outputs, and jit
    # would compile the round twice more for them (the values are what is compared).
    assert start == 1
    resumed, _ = _run(init, round_fn, keys, start=(start, jax.tree.map(np.asarray, state)))
    _assert_trees_equal(uninterrupted, resumed)


def test_interrupted_save_is_not_a_valid_checkpoint(micro, tmp_path):
    _, init, _ = micro
    ckpt = Checkpointer(tmp_path)
    # What an interrupted orbax save leaves: a temporary directory that was never committed.
    (tmp_path / "5.orbax-checkpoint-tmp-123").mkdir()
    assert ckpt.latest() is None
    ckpt.save(2, init(seed_keys(0, 2)))
    assert ckpt.latest() == 2


def test_cli_rejects_bad_values_naming_the_field(capsys):
    with pytest.raises(SystemExit) as err:
        parse(["--preset", "tiny", "--num-envs", "0"])
    assert err.value.code == 2
    assert "env.num_envs=0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse(["--preset", "tiny", "--sac.gamma", "1.5"])
    assert "sac.gamma=1.5" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse(["--preset", "tiny", "--steps-per-round", "1001"])
    assert "multiple of env.num_envs" in capsys.readouterr().err


def test_cli_overrides_preset_fields():
    args = parse(["--preset", "tiny", "--task", "cheetah_run", "--seeds", "3", "--sac.utd", "0.5"])
    assert args.config.env.task == "cheetah_run" and args.seeds == 3 and args.config.sac.utd == 0.5
    assert args.config.sac.hidden == 64  # the rest of the tiny preset is kept


def test_cli_teacher_grid_columns_are_lambda_then_teacher_then_seed():
    args = parse(["--preset", "tiny", "--algo", "pebble", "--seeds", "2", "--teacher-grid", "noisy", "skip"])
    lam = args.config.rebel.lam
    assert args.teacher_grid == ("noisy", "skip") and args.columns == 4
    assert args.grid() == [(lam, "noisy"), (lam, "noisy"), (lam, "skip"), (lam, "skip")]

    flags = ["--algo", "rebel", "--lam-grid", "0", "-0.1", "--teacher-grid", "noisy", "skip", "--seeds", "2"]
    args = parse(["--preset", "tiny", *flags])
    expected = []
    for lam in (0.0, -0.1):
        for teacher in ("noisy", "skip"):
            expected += [(lam, teacher)] * 2  # seeds innermost
    assert args.columns == 8 and len(args.grid()) == 8
    assert args.grid() == expected

    plain = parse(["--preset", "tiny", "--algo", "pebble", "--seeds", "3"])  # no grid: config.teacher, 3 columns
    assert plain.columns == 3 and plain.grid() == [(plain.config.rebel.lam, None)] * 3


@pytest.mark.parametrize(
    "flags,names",
    [
        (["--algo", "pebble", "--teacher-grid", "noisy", "bogus"], "bogus"),
        (["--algo", "sac", "--teacher-grid", "noisy"], "preference"),
    ],
    ids=["unknown-teacher", "sac"],
)
def test_cli_rejects_a_bad_teacher_grid(capsys, flags, names):
    with pytest.raises(SystemExit) as err:
        parse(["--preset", "tiny", *flags])
    assert err.value.code == 2
    message = capsys.readouterr().err
    assert ("teacher_grid=" in message or "--teacher-grid" in message) and "invalid" in message, message
    assert names in message, message


SHARDED = textwrap.dedent(
    """
    import sys
    import jax, jax.numpy as jnp, numpy as np
    from rebel_jax.train import placement
    from rebel_jax.train import Trainer, compiled, seed_keys
    from tests.test_train import MICRO, SHARDED_SEEDS, SHARDED_ROUNDS
    assert len(jax.devices()) == SHARDED_SEEDS
    sharding = placement.seed_sharding(SHARDED_SEEDS)
    init, round_fn, _ = compiled(Trainer(MICRO), sharding)  # as the CLI: each device runs its seeds
    state = init(placement.shard_seeds(seed_keys(11, SHARDED_SEEDS), sharding))
    for r in range(SHARDED_ROUNDS):
        state, _ = round_fn(state, jnp.int32(r))
    # Every leaf, the zeroed replay buffer included, holds one seed per device.
    for x in jax.tree.leaves(state):
        assert x.sharding.is_equivalent_to(sharding, x.ndim), x.sharding
    leaves = jax.device_get(jax.tree.leaves(state.agent))
    np.savez(sys.argv[1], *leaves)
    """
)
SHARDED_SEEDS, SHARDED_ROUNDS = 2, 2


@pytest.mark.heavy  # make test runs the seeds vmapped on one device (test_vmap_over_seeds_equals_separate_runs)
def test_seeds_sharded_over_devices_equal_unsharded(micro, tmp_path):
    """One seed per fake CPU device (a subprocess) against the module's vmapped program on one device."""
    _, init, round_fn = micro
    root = pathlib.Path(__file__).parents[1]
    # Keeps the XLA_FLAGS conftest sets (the jaxlib deadlock workaround) and the compilation cache.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={SHARDED_SEEDS}".strip()
    env = dict(
        os.environ,
        XLA_FLAGS=flags,
        PYTHONPATH=f"{root}/src:{root}",
        JAX_COMPILATION_CACHE_DIR=str(jax.config.jax_compilation_cache_dir),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=str(jax.config.jax_persistent_cache_min_compile_time_secs),
    )
    out_file = tmp_path / "sharded.npz"
    cmd = [sys.executable, "-c", SHARDED, str(out_file)]
    out = subprocess.run(cmd, env=env, cwd=root, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    unsharded, _ = _run(init, round_fn, seed_keys(11, SHARDED_SEEDS), rounds=SHARDED_ROUNDS)
    leaves = jax.tree.leaves(unsharded.agent)
    with np.load(out_file) as saved:
        sharded = [saved[f"arr_{k}"] for k in range(len(leaves))]
    # A device's batch of 1 and a vmapped batch of 2 round differently; chaos and Adam amplify it.
    for x, y in zip(sharded, leaves, strict=True):
        for i in range(SHARDED_SEEDS):
            a, b = np.asarray(x[i], np.float64), np.asarray(y[i], np.float64)
            assert np.linalg.norm(a - b) <= 5e-2 * max(np.linalg.norm(b), 1e-6), (a, b)


def test_micro_config_is_what_the_tests_think():
    assert dataclasses.replace(MICRO).validate() is not None
    assert MICRO.train.steps_per_round // MICRO.env.num_envs == MICRO.env.episode_length
