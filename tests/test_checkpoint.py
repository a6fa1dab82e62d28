"""``Checkpointer.restore_leaves``: a part of a saved state (a policy's parameters) read without the rest."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_pixel_train import MICRO as PIXEL  # the tiny pixel run: 16x16 probe frames, 2 envs

from rebel_jax.checkpoint import Checkpointer, CheckpointMismatch
from rebel_jax.pixel_train import PixelTrainer
from rebel_jax.train import seed_keys


def _state(buffer_rows: int = 256, policy_width: int = 3) -> dict:
    """A state of a large replay leaf (random, so that it stays large on disk), a policy and a zero-size leaf."""
    rng = np.random.default_rng(0)
    return {
        "buffer": jnp.asarray(rng.normal(size=(buffer_rows, 1024)), jnp.float32),  # 1 MiB at 256 rows
        "empty": jnp.zeros((0, 4)),
        "policy": {"w": jnp.asarray(rng.normal(size=(2, policy_width)), jnp.float32), "b": jnp.arange(3)},
    }


def _policy(state: dict) -> dict:
    return state["policy"]


def test_a_pixel_run_s_policy_restores_as_in_a_full_restore_and_alone(tmp_path):
    trainer = PixelTrainer(PIXEL)
    state = jax.jit(jax.vmap(trainer.init))(seed_keys(0, 2))
    ckpt = Checkpointer(tmp_path / "checkpoints")
    ckpt.save(3, state)
    like = jax.eval_shape(jax.vmap(trainer.init), seed_keys(0, 2))
    step, params = ckpt.restore_leaves(like, trainer.policy_params)
    _, whole = ckpt.restore(like)
    ckpt.close()
    assert step == 3
    # Only the policy's leaves (encoder and actor), not the replay buffer, the critic or the optimisers.
    assert jax.tree.structure(params) == jax.tree.structure(trainer.policy_params(like))
    assert len(jax.tree.leaves(params)) < len(jax.tree.leaves(like)) // 4
    for got, full, saved in zip(
        *map(jax.tree.leaves, (params, trainer.policy_params(whole), trainer.policy_params(state))), strict=True
    ):
        assert isinstance(got, jax.Array) and got.dtype == full.dtype and got.shape == full.shape
        np.testing.assert_array_equal(got, full)
        np.testing.assert_array_equal(got, saved)


# Orbax's failed restore of the damaged checkpoint leaves its reader behind (harmless): reports of it during this
# test are ignored here; its coroutine's, which can surface during a later test, in pyproject.toml.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_the_other_leaves_are_not_read(tmp_path):
    ckpt = Checkpointer(tmp_path / "checkpoints")
    state = _state()
    ckpt.save(1, state)
    # OCDBT packs the leaves into data files; the replay leaf (1 MiB, incompressible) is the largest one. Delete it.
    files = [p for p in (tmp_path / "checkpoints" / "1").rglob("*") if p.is_file()]
    largest = max(files, key=lambda p: p.stat().st_size)
    assert largest.stat().st_size > 2**19
    largest.unlink()
    with pytest.raises(Exception):  # noqa: B017 - whichever tensorstore raises: the buffer is gone
        ckpt.restore(state, step=1)
    step, policy = ckpt.restore_leaves(state, _policy)  # the newest readable step: this one, kept in place
    assert step == 1 and ckpt.steps() == [1] and not (tmp_path / "checkpoints_damaged").exists()
    assert jax.tree.structure(policy) == jax.tree.structure(state["policy"])
    for got, saved in zip(jax.tree.leaves(policy), jax.tree.leaves(state["policy"]), strict=True):
        assert got.dtype == saved.dtype
        np.testing.assert_array_equal(got, saved)
    ckpt.close()


def test_restore_leaves_refuses_other_states_and_computed_leaves(tmp_path):
    ckpt = Checkpointer(tmp_path / "checkpoints")
    with pytest.raises(FileNotFoundError, match="no readable checkpoint"):
        ckpt.restore_leaves(_state(), _policy)
    ckpt.save(1, _state())
    # Another replay size (a run extended since) is no matter; another policy is.
    _, policy = ckpt.restore_leaves(_state(buffer_rows=512), _policy)
    np.testing.assert_array_equal(policy["w"], _state()["policy"]["w"])
    with pytest.raises(CheckpointMismatch, match=r"checkpoint 1 in .*\(leaf 3: saved \(2, 3\), now \(2, 4\)"):
        ckpt.restore_leaves(_state(policy_width=4), _policy)
    with pytest.raises(CheckpointMismatch, match="3 leaves saved, 4 now"):
        ckpt.restore_leaves({**_state(), "more": jnp.ones(2)}, _policy)
    with pytest.raises(ValueError, match="not compute new ones"):
        ckpt.restore_leaves(_state(), lambda s: {"w": s["policy"]["w"] * 2})
    assert ckpt.steps() == [1] and not (tmp_path / "checkpoints_damaged").exists()
    ckpt.close()
