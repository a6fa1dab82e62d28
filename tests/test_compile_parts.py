"""``benchmarks/compile_parts.py``: the round and its parts compile from the run's own shapes."""

from __future__ import annotations

import json

import jax
import pytest


@pytest.mark.heavy  # make test-heavy: five cold compiles of a PEBBLE run
def test_the_round_and_its_parts_compile_for_a_preference_run(tmp_path, benchmark_script, monkeypatch):
    bench = benchmark_script("compile_parts")
    flags = ["pebble", "--preset", "tiny", "--task", "probe_point", "--seeds", "2"]
    parts = bench.measure(flags)
    names = ("lower_round_s", "compile_round_s", "compile_env_step_s", "compile_env_reset_s", "compile_agent_update_s")
    assert set(parts) == set(names) and all(parts[name] > 0 for name in names)
    out = tmp_path / "rows.json"
    monkeypatch.setattr("sys.argv", ["compile_parts.py", *flags, "--out", str(out)])
    cache_on = jax.config.jax_enable_compilation_cache
    try:
        bench.main()  # it turns JAX's persistent cache off for its process
    finally:
        jax.config.update("jax_enable_compilation_cache", cache_on)
    (row,) = json.loads(out.read_text())["rows"]
    assert row["flags"] == " ".join(flags) and row["device"] and row["commit"]
