"""``benchmarks/scaling.py``: the efficiency read from two runs' logs, against the formula by hand."""

from __future__ import annotations

import importlib.util
import json
import pathlib

import pytest

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "scaling.py"


def _scaling():
    spec = importlib.util.spec_from_file_location("scaling", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(path: pathlib.Path, devices: int, columns: int, seconds: list[float]) -> pathlib.Path:
    path.mkdir()
    meta = {"devices": ["GPU"] * devices, "columns": columns, "jax": "0.11.2", "git_commit": "abc", "command": "x"}
    (path / "meta.json").write_text(json.dumps({**meta, "started": "2026-11-27T00:00:00"}))
    rows = [{"round": r, "seconds": s} for r, s in enumerate(seconds)]
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_efficiency_is_the_rate_ratio_over_the_device_count(tmp_path, capsys):
    multi = _run(tmp_path / "two", 2, 10, [90.0, 21.0, 20.0, 23.0])
    one = _run(tmp_path / "one", 1, 5, [80.0, 19.0, 20.5, 20.0])
    _scaling().main([str(multi), str(one)])
    out = capsys.readouterr().out
    expected = (10 / 21.0) / (2 * 5 / 20.0)  # medians of rounds 1-3: 21.0 and 20.0
    assert f"**{expected:.3f}**" in out, out
    assert "21.00, 20.00, 23.00" in out and "90.00" not in out  # round 0 (the compile) is left out


def test_a_run_without_timed_rounds_is_refused(tmp_path):
    only_compile = _run(tmp_path / "two", 2, 10, [90.0])
    with pytest.raises(SystemExit, match="no round from round 1"):
        _scaling().run_rate(only_compile)
