"""``experiments/check_commands.py``: every command of experiments/README.md reproduces the runs it names."""

from __future__ import annotations

import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "experiments"))
import check_commands  # noqa: E402

COMMAND = """
    # logs: results/runs/quadruped/sac_quadruped_walk_1m_bf16
    python -m rebel_jax.train sac --preset paper_quadruped --task quadruped_walk --seeds {seeds} \\
        --sac.precision {precision} --run-dir runs/sac_quadruped_walk_1m_bf16
"""


def test_every_documented_run_matches_its_command(capsys):
    assert check_commands.main([]) == 0, capsys.readouterr().out


def test_a_command_that_differs_from_its_run_is_reported(tmp_path, capsys):
    readme = tmp_path / "README.md"
    readme.write_text(COMMAND.format(seeds=3, precision="bf16"))
    assert check_commands.main([str(readme)]) == 0
    readme.write_text(COMMAND.format(seeds=5, precision="tf32"))
    assert check_commands.main([str(readme)]) == 1
    out = capsys.readouterr().out
    assert "seeds (run 3, command 5)" in out and "sac.precision (run 'bf16', command 'tf32')" in out
