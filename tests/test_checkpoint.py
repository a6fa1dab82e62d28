"""``Checkpointer.restore_leaves``: a part of a saved state (a policy's parameters) read without the rest; the
checksums that catch a step's damaged files before orbax reads them."""

from __future__ import annotations

import json
import shutil
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_pixel_preference import MICRO as PIXEL_PEBBLE  # the same run, PEBBLE
from test_pixel_train import MICRO as PIXEL  # the tiny pixel run: 16x16 probe frames, 2 envs

from rebel_jax.config import ConfigError
from rebel_jax.run import checkpoint, cli
from rebel_jax.run.checkpoint import CHECKSUMS, CheckpointDamaged, Checkpointer, CheckpointMismatch
from rebel_jax.train import Trainer, seed_keys


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
    trainer = Trainer(PIXEL)
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
    # The full restore is the saved state, leaf by leaf: the frame replay, the reward ensemble, the optimisers.
    for restored, saved in zip(jax.tree.leaves(whole), jax.tree.leaves(state), strict=True):
        np.testing.assert_array_equal(restored, saved)


# Orbax's failed restore of the damaged checkpoint leaves its reader behind (harmless): reports of it during this
# test are ignored here; its coroutine's, which can surface during a later test, in pyproject.toml.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_the_other_leaves_are_not_read(tmp_path):
    ckpt = Checkpointer(tmp_path / "checkpoints", require_checksums=False)  # a run from before checksums
    state = _state()
    ckpt.save(1, state)
    (tmp_path / "checkpoints" / "1" / CHECKSUMS).unlink()  # unchecked (as older code wrote it): orbax reads alone
    _largest_data_file(tmp_path / "checkpoints" / "1").unlink()
    with pytest.raises(Exception):  # noqa: B017 - whichever tensorstore raises: the buffer is gone
        ckpt.restore(state, step=1)
    step, policy = ckpt.restore_leaves(state, _policy)  # the newest readable step: this one, kept in place
    assert step == 1 and ckpt.steps() == [1] and not (tmp_path / "checkpoints_damaged").exists()
    assert jax.tree.structure(policy) == jax.tree.structure(state["policy"])
    for got, saved in zip(jax.tree.leaves(policy), jax.tree.leaves(state["policy"]), strict=True):
        assert got.dtype == saved.dtype
        np.testing.assert_array_equal(got, saved)
    ckpt.close()


def _largest_data_file(step_dir):
    """OCDBT packs the leaves into data files; the replay leaf (1 MiB, incompressible) is in the largest one."""
    largest = max((p for p in step_dir.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    assert largest.stat().st_size > 2**19
    return largest


def _flip_a_bit(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))


def test_checksums_are_each_file_s_size_and_crc32_read_in_chunks(tmp_path, monkeypatch):
    monkeypatch.setattr(checkpoint, "_CHUNK", 4096)  # the 1 MiB data file in 256 chunks
    ckpt = Checkpointer(tmp_path / "checkpoints")
    ckpt.save(1, _state())
    ckpt.close()
    step_dir = tmp_path / "checkpoints" / "1"
    files = sorted(p for p in step_dir.rglob("*") if p.is_file() and p.name != CHECKSUMS)
    expected = {p.relative_to(step_dir).as_posix(): [p.stat().st_size, zlib.crc32(p.read_bytes())] for p in files}
    assert len(expected) > 3 and json.loads((step_dir / CHECKSUMS).read_text()) == expected
    assert checkpoint.file_checksums(step_dir) == expected and checkpoint.checksum_differences(step_dir) == []


def test_a_flipped_bit_that_orbax_would_read_silently_is_caught_and_the_step_before_restored(tmp_path, capsys):
    # Frames of random bytes (2 MiB, the largest leaf): zstd stores incompressible data raw, so a flipped bit in
    # them is one wrong byte to orbax, always (in compressed data it is garbage or a decompression error, by layout).
    frames = jnp.asarray(np.random.default_rng(1).integers(0, 256, size=2**21), jnp.uint8)
    state = {**_state(), "frames": frames}
    later = {**state, "policy": {**state["policy"], "b": state["policy"]["b"] + 1}}
    ckpt = Checkpointer(tmp_path / "checkpoints")
    ckpt.save(1, state)
    ckpt.save(2, later)
    step_dir = tmp_path / "checkpoints" / "2"
    damaged = _largest_data_file(step_dir)
    _flip_a_bit(damaged)
    name = damaged.relative_to(step_dir).as_posix()
    with pytest.raises(CheckpointDamaged, match=f"{name}: CRC-32 [0-9a-f]{{8}} saved, [0-9a-f]{{8}} now"):
        ckpt.restore(state, step=2)
    # Unchecked, orbax restores the step with one wrong byte in the frames, and no error.
    unchecked = tmp_path / "unchecked"
    shutil.copytree(tmp_path / "checkpoints", unchecked)
    (unchecked / "2" / CHECKSUMS).unlink()
    plain = Checkpointer(unchecked, require_checksums=False)  # a run written before checksums existed
    _, silent = plain.restore(state, step=2)
    plain.close()
    assert int(np.sum(np.asarray(silent["frames"]) != np.asarray(frames))) == 1
    np.testing.assert_array_equal(silent["buffer"], later["buffer"])
    # A run that has checksums: the step whose checksums.json was deleted is damaged, set aside like the others.
    strict = Checkpointer(unchecked)
    with pytest.raises(CheckpointDamaged, match=f"{CHECKSUMS} is missing"):
        strict.restore(state, step=2)
    step, _ = strict.restore(state)
    strict.close()
    assert step == 1 and [p.name.split("-")[0] for p in (tmp_path / "unchecked_damaged").iterdir()] == ["2"]
    assert f"CheckpointDamaged: {CHECKSUMS} is missing" in capsys.readouterr().err

    step, restored = ckpt.restore(state)
    assert step == 1 and ckpt.steps() == [1]
    for got, saved in zip(jax.tree.leaves(restored), jax.tree.leaves(state), strict=True):
        np.testing.assert_array_equal(got, saved)
    assert [p.name.split("-")[0] for p in (tmp_path / "checkpoints_damaged").iterdir()] == ["2"]
    err = capsys.readouterr().err
    assert "checkpoint 2 in" in err and "CheckpointDamaged: files differ from their checksums" in err, err
    ckpt.close()


def test_checksums_name_missing_cut_and_added_files_and_a_step_without_them_is_damaged_unless_older(tmp_path):
    ckpt = Checkpointer(tmp_path / "checkpoints")
    ckpt.save(1, _state())
    ckpt.close()
    step_dir = tmp_path / "checkpoints" / "1"
    largest = _largest_data_file(step_dir)
    size = largest.stat().st_size
    largest.write_bytes(largest.read_bytes()[: size // 2])
    metadata = step_dir / "_CHECKPOINT_METADATA"
    metadata.rename(step_dir / "moved")
    assert checkpoint.checksum_differences(step_dir) == [
        "_CHECKPOINT_METADATA: missing",
        f"{largest.relative_to(step_dir).as_posix()}: {size} bytes saved, {size // 2} now",
        "moved: not saved",
    ]
    ckpt = Checkpointer(tmp_path / "checkpoints")
    with pytest.raises(CheckpointDamaged, match=r"\(_CHECKPOINT_METADATA: missing; .*; moved: not saved\)"):
        ckpt.restore_leaves(_state(), _policy, step=1)  # all the files are checked, not only the policy's
    (step_dir / "moved").rename(metadata)
    sums = (step_dir / CHECKSUMS).read_bytes()
    (step_dir / CHECKSUMS).write_bytes(sums[:-10])
    [unreadable] = checkpoint.checksum_differences(step_dir)  # cut mid-write by hand: one difference, naming it
    assert unreadable.startswith(f"{CHECKSUMS}: unreadable (") and "char" in unreadable, unreadable
    largest.unlink()
    (step_dir / CHECKSUMS).unlink()
    with pytest.raises(CheckpointDamaged, match=f"{CHECKSUMS} is missing"):
        ckpt.restore_leaves(_state(), _policy, step=1)
    ckpt.close()
    older = Checkpointer(tmp_path / "checkpoints", require_checksums=False)  # a run from before checksums
    _, policy = older.restore_leaves(_state(), _policy, step=1)  # unchecked, as older code wrote it
    np.testing.assert_array_equal(policy["w"], _state()["policy"]["w"])
    older.close()


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


def _layout_before_the_replay_contract(state) -> tuple:
    """``state`` (a pixel run's) in the leaf order the code before the one trainer saved: the frame ring's
    ``reward`` (the learned reward of a preference run, the true one of DrQ-v2) where ``learned_reward`` now is and
    its ``true_reward`` last (None for DrQ-v2); the pixel state's ``eval_policy`` right after its key."""
    b = state.buffer
    pair = (b.learned_reward, b.true_reward) if b.learned_reward is not None else (b.true_reward, None)
    ring = (b.frames, b.frame_index, b.episode_step, b.action, pair[0], b.terminal, b.truncated, b.ptr, b.size)
    ring = (*ring, b.frame_ptr, pair[1])
    rest = (state.reward, state.teacher, state.lam, state.eval_trajectory)
    return (state.agent, ring, state.env, state.episodes, state.key, state.eval_policy, *rest)


@pytest.mark.parametrize("cfg", [PIXEL, PIXEL_PEBBLE], ids=["drqv2", "pebble"])
def test_a_pixel_checkpoint_of_the_code_before_the_one_trainer_is_refused_naming_its_commit(tmp_path, cfg):
    """Its leaves have other places now (the same number of them): the resume refuses it in one line that names
    the commit which wrote it, rather than restoring rewards and flags into each other's places."""
    trainer = Trainer(cfg)
    state = jax.jit(jax.vmap(trainer.init))(seed_keys(0, 2))
    old = _layout_before_the_replay_contract(state)
    assert len(jax.tree.leaves(old)) == len(jax.tree.leaves(state))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "meta.json").write_text(json.dumps({"git_commit": "4972dfe"}))
    ckpt = Checkpointer(run_dir / "checkpoints")
    ckpt.save(2, old)
    with pytest.raises(ConfigError) as refused:
        cli._restore(run_dir, ckpt, state, None)
    ckpt.close()
    message = str(refused.value)
    assert "\n" not in message and "holds another state" in message and "git_commit 4972dfe" in message, message


def test_a_save_without_waiting_survives_the_donation_of_its_arrays_and_completes_at_the_next_call(tmp_path):
    # The trainer's next round donates the state it saved (its buffers are reused in place) while orbax writes.
    state = _state(buffer_rows=2048)  # 8 MiB
    expected = jax.tree.map(np.asarray, state)
    ckpt = Checkpointer(tmp_path / "checkpoints")
    ckpt.save(1, state, wait=False)
    step = jax.jit(lambda s: jax.tree.map(lambda x: x + 1, s), donate_argnums=0)
    state = step(step(state))  # the saved arrays are donated, then overwritten
    assert ckpt.latest() == 1  # completes step 1
    assert (tmp_path / "checkpoints" / "1" / CHECKSUMS).exists() and not checkpoint.checksum_differences(
        tmp_path / "checkpoints" / "1"
    )
    _, restored = ckpt.restore(jax.eval_shape(lambda: state))
    ckpt.close()
    for got, want in zip(jax.tree.leaves(restored), jax.tree.leaves(expected), strict=True):
        np.testing.assert_array_equal(got, want)


def test_the_error_of_a_save_in_flight_is_raised_by_the_next_call_naming_its_step(tmp_path, monkeypatch):
    ckpt = Checkpointer(tmp_path / "checkpoints")
    ckpt.save(1, _state(), wait=False)
    ckpt.manager.wait_until_finished()  # orbax's own threads are done; the error below stands for theirs

    def failed():
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ckpt.manager, "wait_until_finished", failed)
    with pytest.raises(checkpoint.CheckpointSaveError, match="checkpoint 1 not saved: No space left on device"):
        ckpt.save(2, _state())
    monkeypatch.undo()
    assert ckpt.steps() == [1]  # step 2 was not started; step 1's files are there, without checksums
    assert not (tmp_path / "checkpoints" / "1" / CHECKSUMS).exists()
    ckpt.close()
