"""``experiments/gpu_batch.py``: which jobs start, resume or are done, and the commands they get."""

from __future__ import annotations

import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "experiments"))
import gpu_batch  # noqa: E402


def test_a_job_is_new_then_resumed_from_a_checkpoint_then_done(tmp_path):
    run_dir = tmp_path / "job"
    assert gpu_batch._state(run_dir) == "new"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "12.orbax-checkpoint-tmp-1").mkdir()  # an interrupted save
    assert gpu_batch._state(run_dir) == "new"
    (run_dir / "checkpoints" / "12").mkdir()
    assert gpu_batch._state(run_dir) == "resume"
    (run_dir / "final.json").write_text("{}")
    assert gpu_batch._state(run_dir) == "done"


def test_the_command_carries_the_job_flags_the_time_limit_and_resume(tmp_path):
    job = {"name": "a", "gpu": 0, "args": ["--algo", "pebble", "--seeds", "5"]}
    fresh = gpu_batch._command(job, tmp_path / "a", 500.0, "new")
    assert fresh[1:3] == ["-m", "rebel_jax.train"]
    assert fresh[3:7] == job["args"]
    assert fresh[fresh.index("--run-dir") + 1] == str(tmp_path / "a")
    assert fresh[fresh.index("--time-limit") + 1] == "500"
    assert "--resume" not in fresh
    assert gpu_batch._command(job, tmp_path / "a", 500.0, "resume")[-1] == "--resume"
