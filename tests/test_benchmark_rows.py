"""``benchmarks/timing.merge_rows``: a new measurement replaces its own code's row, never another commit's, so
the numbers BENCHMARKS.md quotes from earlier commits stay in the results files."""

from __future__ import annotations

import json

import pytest

FIELDS = ("device", "commit", "batch")


def test_a_measurement_replaces_its_own_commits_row_and_keeps_other_commits_rows(tmp_path, benchmark_script):
    merge_rows = benchmark_script("timing").merge_rows
    out = tmp_path / "rows.json"
    first = {"device": "H100", "commit": "aaa", "batch": 1, "ms": 12.5}
    other_batch = {**first, "batch": 200, "ms": 13.4}
    merge_rows(out, [first, other_batch], FIELDS)
    newer = {**first, "commit": "bbb", "ms": 11.8}
    merge_rows(out, [newer], FIELDS)
    assert json.loads(out.read_text())["rows"] == [first, other_batch, newer]
    again = {**newer, "ms": 11.9}  # the same code measured again: its row is replaced
    merge_rows(out, [again], FIELDS)
    assert json.loads(out.read_text())["rows"] == [first, other_batch, again]


def test_the_checkpoint_checksum_benchmark_measures_a_small_state(tmp_path, benchmark_script):
    bench = benchmark_script("checkpoint_checksums")
    row = bench.row(1 / 1024, repeats=2, scratch=tmp_path / "scratch")  # a 1 MiB leaf
    assert row["step_bytes"] > 2**20 and row["gib"] == 1 / 1024 and row["commit"] and row["device"]
    timings = ("save_s", "checksums_s", "restore_checked_s", "restore_unchecked_s")
    assert row["save_s"] > 0 and all(isinstance(row[name], float) and row[name] >= 0 for name in timings), row
    assert not (tmp_path / "scratch").exists()  # its checkpoints are removed


def test_the_knn_reward_benchmark_times_each_way_after_checking_they_agree(tmp_path, benchmark_script):
    bench = benchmark_script("knn_reward")
    out = tmp_path / "knn.json"
    small = "--seeds 2 --batch-size 16 --rows 300 --fills 0.2 1 --chunk-sizes 128 --per-call 2 --repeats 1"
    bench.main([*small.split(), "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [(r["filled"], r["chunk_size"], r["select"]) for r in rows] == [
        (60, 128, "argmin"),
        (60, 128, "top_k"),
        (300, 128, "argmin"),
        (300, 128, "top_k"),
    ]
    assert all(r["ms"] > 0 and r["device"] and r["jax"] for r in rows)


def test_the_meta_world_speed_table_divides_each_gpu_rate_by_the_host_cpus_rates(benchmark_script):
    speed = benchmark_script("metaworld_speed_table")
    row = lambda commit, batch, rate: {  # noqa: E731
        "commit": commit,
        "task": "metaworld_drawer-open",
        "impl": "warp",
        "batch": batch,
        "env_steps_per_s": rate,
        "ms_per_vector_step": batch / rate * 1e3,
    }
    gpu = {"rows": [row("old", 1024, 1.0), row("new", 1024, 300_000.0), {"commit": "new", "refused": "why"}]}
    cpu = {"results": {"drawer-open": {"1": {"steps_per_s": 4000.0}, "60": {"steps_per_s": 120_000.0}}}}
    rows = speed.rows_at(gpu, None)
    assert [r["env_steps_per_s"] for r in rows] == [300_000.0]  # the last row's code, the refused row left out
    line = speed.table(rows, cpu).splitlines()[2]
    assert line.split("|")[6:8] == [" 75.0 ", " 2.5 "], line  # 300,000 / 4,000 and / 120,000
    assert speed.rows_at(gpu, "old")[0]["env_steps_per_s"] == 1.0
    with pytest.raises(SystemExit, match="no measured row"):
        speed.rows_at(gpu, "missing")
