"""``experiments/compare.py``: grid runs split into methods, labels, subsets and cut curves."""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np
import pytest

from rebel_jax.config import PRESETS, to_dict

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "experiments"))
import compare  # noqa: E402

SEEDS = 2
GRID = [(lam, teacher) for lam in (0.0, -0.1) for teacher in ("noisy", "skip") for _ in range(SEEDS)]


def write_grid_run(run_dir: pathlib.Path, algo: str = "rebel", labels: int = 100, rounds: int = 4) -> np.ndarray:
    """A run directory as ``python -m rebel_jax.train --lam-grid 0 -0.1 --teacher-grid noisy skip`` writes it.

    Column j's evaluation return at round i is ``100 * j + i``, so every column is recognisable.
    Returns the (rounds, columns) returns.
    """
    run_dir.mkdir(parents=True)
    cfg = to_dict(PRESETS["tiny"])
    cfg["algo"], cfg["feedback"]["labels"] = algo, labels
    meta = {
        "devices": ["cpu"],
        "command": "train.py --preset tiny",
        "seeds": SEEDS,
        "columns": len(GRID),
        "lams": [lam for lam, _ in GRID] if algo == "rebel" else None,
        "teachers": [t for _, t in GRID],
        "started": "2026-11-22T10:00:00",
    }
    (run_dir / "config.json").write_text(json.dumps(cfg))
    (run_dir / "meta.json").write_text(json.dumps(meta))
    returns = np.array([[100.0 * j + i for j in range(len(GRID))] for i in range(rounds)])
    rows = [{"env_steps": 10 * (i + 1), "round": i, "eval_return": r.tolist()} for i, r in enumerate(returns)]
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    return returns


def test_a_lambda_and_teacher_grid_splits_into_one_method_per_grid_point(tmp_path):
    returns = write_grid_run(tmp_path / "run")
    methods = compare.methods(tmp_path / "run")
    expected = {}
    for j, (lam, teacher) in enumerate(GRID):
        label = ("pebble (rebel lam=0)" if lam == 0 else f"rebel lam={lam:g}") + f", {teacher}"
        expected.setdefault(label, []).append(j)
    assert list(methods) == list(expected)
    for label, columns in expected.items():
        (steps, got), info = methods[label]
        assert steps.tolist() == [10, 20, 30, 40]
        np.testing.assert_array_equal(got, returns[:, columns])
        lam, teacher = GRID[columns[0]]
        assert (info["lam"], info["teacher"], info["labels"], info["algo"]) == (lam, teacher, 100, "rebel")


def test_labels_name_other_budgets_and_curves_can_be_cut(tmp_path):
    write_grid_run(tmp_path / "run", algo="pebble", labels=1000)
    curves, infos = compare.gather([tmp_path / "run"], max_steps=25)
    assert list(curves) == ["pebble 1000 labels, noisy", "pebble 1000 labels, skip"]
    steps, got = curves["pebble 1000 labels, skip"]
    assert steps.tolist() == [10, 20]
    # Without lambdas (pebble) both halves of the grid are the same method: columns 2, 3, 6, 7.
    np.testing.assert_array_equal(got, [[200.0, 300.0, 600.0, 700.0], [201.0, 301.0, 601.0, 701.0]])
    assert infos["pebble 1000 labels, skip"]["lam"] is None


def test_surf_labels_name_a_reward_update_other_than_its_walker_value(tmp_path):
    for name, steps in (("walker_value", 1000), ("other", 100)):
        write_grid_run(tmp_path / name, algo="surf")
        cfg = json.loads((tmp_path / name / "config.json").read_text())
        cfg["surf"]["reward_update"] = steps
        (tmp_path / name / "config.json").write_text(json.dumps(cfg))
    curves, _ = compare.gather([tmp_path / "walker_value", tmp_path / "other"])
    assert list(curves) == [
        "surf, noisy",
        "surf, skip",
        "surf (reward_update 100), noisy",
        "surf (reward_update 100), skip",
    ]


def test_a_pixel_reward_stepped_as_surfs_or_in_bf16_is_named_and_never_merges(tmp_path):
    runs = {
        "summed": {"per_member_adam": False, "precision": "tf32"},
        "surf_adam": {"per_member_adam": True, "precision": "tf32"},
        "bf16": {"per_member_adam": False, "precision": "bf16"},
        "before_the_settings": None,  # runs before the settings existed have no such key: the summed step, tf32
    }
    for name, pixel_reward in runs.items():
        write_grid_run(tmp_path / name, algo="surf")
        cfg = json.loads((tmp_path / name / "config.json").read_text())
        if pixel_reward is not None:
            cfg["pixel_reward"] = pixel_reward
        (tmp_path / name / "config.json").write_text(json.dumps(cfg))
    curves, _ = compare.gather([tmp_path / n for n in runs])
    assert list(curves) == [
        "surf, noisy",
        "surf, skip",
        "surf (SURF's reward Adam), noisy",
        "surf (SURF's reward Adam), skip",
        "surf (bf16 reward), noisy",
        "surf (bf16 reward), skip",
    ]
    assert curves["surf, noisy"][1].shape[1] == 2 * curves["surf (SURF's reward Adam), noisy"][1].shape[1]


def test_a_float32_critic_output_is_named_and_never_merges(tmp_path):
    for name, out_f32 in (("bf16", False), ("qf32", True), ("before_the_setting", None)):
        write_grid_run(tmp_path / name, algo="drqv2")
        cfg = json.loads((tmp_path / name / "config.json").read_text())
        if out_f32 is None:
            del cfg["drqv2"]["critic_out_f32"]
        else:
            cfg["drqv2"]["critic_out_f32"] = out_f32
        (tmp_path / name / "config.json").write_text(json.dumps(cfg))
    curves, infos = compare.gather([tmp_path / n for n in ("bf16", "qf32", "before_the_setting")])
    assert list(curves) == [
        "drqv2, noisy",
        "drqv2, skip",
        "drqv2 (float32 critic output), noisy",
        "drqv2 (float32 critic output), skip",
    ]
    assert [p.name for p in infos["drqv2, noisy"]["run_dirs"]] == ["bf16", "before_the_setting"]
    assert [p.name for p in infos["drqv2 (float32 critic output), noisy"]["run_dirs"]] == ["qf32"]


def test_a_single_teacher_other_than_the_oracle_names_the_method_and_never_merges_with_the_oracle(tmp_path):
    for name, teacher in (("oracle", {}), ("mistake", {"eps_mistake": 0.1})):
        write_grid_run(tmp_path / name, algo="pebble")
        cfg, meta = (json.loads((tmp_path / name / f).read_text()) for f in ("config.json", "meta.json"))
        cfg["teacher"] |= teacher
        meta["teachers"] = None  # --teacher, not --teacher-grid
        (tmp_path / name / "config.json").write_text(json.dumps(cfg))
        (tmp_path / name / "meta.json").write_text(json.dumps(meta))
    curves, infos = compare.gather([tmp_path / "oracle", tmp_path / "mistake"])
    assert list(curves) == ["pebble", "pebble, mistake"]
    assert [infos[label]["teacher"] for label in curves] == ["oracle", "mistake"]
    assert curves["pebble, mistake"][1].shape == (4, len(GRID))


def test_variants_of_the_rebel_term_are_named_and_never_merge_with_the_papers(tmp_path):
    variants = {
        "paper": {},
        "replay": {"rebel": {"source": "replay"}},
        "old_replay": {"rebel": {"source": None}},  # written before rebel.source existed: the replay window
        "mean": {"rebel": {"source": "replay", "estimator": "mean"}},
        "penalty_normalized": {"rebel": {"form": "penalty", "normalize": True}},
        "sigmoid": {"reward": {"output": "sigmoid"}},
    }
    for name, changes in variants.items():
        write_grid_run(tmp_path / name)
        cfg = json.loads((tmp_path / name / "config.json").read_text())
        for section, knobs in changes.items():
            cfg[section] |= knobs
            cfg[section] = {k: v for k, v in cfg[section].items() if v is not None}
        (tmp_path / name / "config.json").write_text(json.dumps(cfg))
    curves, _ = compare.gather([tmp_path / name for name in variants])
    without_teacher = {label.rsplit(", ", 1)[0] for label in curves}  # the grid's teacher comes last
    assert sorted(without_teacher) == sorted(
        [
            "pebble (rebel lam=0)",
            "pebble (rebel lam=0) (sigmoid output)",
            "rebel lam=-0.1",
            "rebel lam=-0.1 (replay V)",
            "rebel lam=-0.1 (replay V, mean estimator)",
            "rebel lam=-0.1 (penalty, normalized)",
            "rebel lam=-0.1 (sigmoid output)",
        ]
    )
    # lambda 0 is PEBBLE whatever the term, so those columns merge; the old and new replay runs merge too.
    assert curves["pebble (rebel lam=0), skip"][1].shape == (4, 5 * SEEDS)
    assert curves["rebel lam=-0.1 (replay V), skip"][1].shape == (4, 2 * SEEDS)
    assert curves["rebel lam=-0.1, skip"][1].shape == (4, SEEDS)


def test_runs_of_the_same_method_merge_their_seeds(tmp_path):
    write_grid_run(tmp_path / "a")
    write_grid_run(tmp_path / "b")
    curves, _ = compare.gather([tmp_path / "a", tmp_path / "b"])
    assert curves["rebel lam=-0.1, skip"][1].shape == (4, 2 * SEEDS)


def test_compare_reports_a_faster_method_with_a_ratio_below_one():
    steps = np.array([10, 20, 30, 40])
    slow = (steps, np.array([[0.0], [1.0], [2.0], [4.0]]))
    fast = (steps, np.array([[0.0], [2.0], [4.0], [4.0]]))
    out = compare.compare({"slow": slow, "fast": fast}, reference="slow", threshold=2.0)
    assert out["methods"]["slow"]["steps_ratio_vs_reference"] == pytest.approx(1.0)
    assert out["methods"]["fast"]["steps_ratio_vs_reference"] == pytest.approx(20 / 30)


def _edit(run_dir: pathlib.Path, name: str, **changes) -> None:
    """Updates the run's ``config.json`` or ``meta.json`` (``name``) at dotted keys ("env.num_envs")."""
    path = run_dir / name
    data = json.loads(path.read_text())
    for dotted, value in changes.items():
        *parents, key = dotted.split(".")
        node = data
        for parent in parents:
            node = node[parent]
        node[key] = value
    path.write_text(json.dumps(data))


def test_a_pooled_method_lists_every_runs_provenance_and_refuses_runs_of_other_settings(tmp_path):
    """Seeds of one method from runs on two devices and days, each with its command and --seed, pool into one
    method whose info names them all; a run of the same label at another num_envs is not pooled."""
    runs = [tmp_path / name for name in ("first", "second", "third")]
    for run in runs:
        write_grid_run(run, algo="pebble")
    second = {"devices": ["gpu"], "started": "2026-11-21T09:00:00", "command": "train.py --preset tiny --seed 5"}
    _edit(runs[1], "meta.json", **second)
    _edit(runs[1], "config.json", **{"train.seed": 5})
    curves, infos = compare.gather(runs[:2])
    info = infos["pebble, noisy"]
    assert curves["pebble, noisy"][1].shape[1] == 2 * 4  # 4 noisy columns per run
    assert info["device"] == ["cpu", "gpu"] and info["date"] == ["2026-11-21", "2026-11-22"]
    assert info["command"] == ["train.py --preset tiny", "train.py --preset tiny --seed 5"]
    assert info["train_seed"] == [PRESETS["tiny"].train.seed, 5] and info["run_dirs"] == runs[:2]
    assert "columns" not in info  # one run's own columns
    _edit(runs[2], "config.json", **{"env.num_envs": 7})
    with pytest.raises(ValueError, match="num_envs values differ"):
        compare.gather(runs)


def _write_run(run_dir: pathlib.Path, algo: str, returns: np.ndarray, train_seed: int = 0) -> None:
    """A one-method run (no grid) of ``algo`` whose seed j's evaluation return at round i is ``returns[i, j]``."""
    run_dir.mkdir(parents=True)
    cfg = to_dict(PRESETS["tiny"])
    cfg["algo"], cfg["train"]["seed"], cfg["feedback"]["labels"] = algo, train_seed, 100
    seeds = returns.shape[1]
    meta = {"devices": ["cpu"], "command": "train.py --preset tiny", "seeds": seeds, "columns": seeds}
    (run_dir / "config.json").write_text(json.dumps(cfg))
    (run_dir / "meta.json").write_text(json.dumps(meta | {"started": "2026-11-27T10:00:00"}))
    rows = [{"env_steps": 10 * (i + 1), "round": i, "eval_return": r.tolist()} for i, r in enumerate(returns)]
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    (run_dir / "final.json").write_text(json.dumps({"final_eval_return": returns[-1].tolist()}))


def test_qpa_rows_leave_the_threshold_to_the_baselines_and_pair_with_pebble_by_key(tmp_path):
    import qpa_rune
    import rebel

    rng = np.random.default_rng(0)
    pebble0, pebble1 = rng.uniform(100, 200, (4, 2)), rng.uniform(100, 200, (4, 2))
    sac, qpa = rng.uniform(300, 400, (4, 2)), rng.uniform(0, 50, (4, 3))
    _write_run(tmp_path / "p0", "pebble", pebble0)
    _write_run(tmp_path / "p1", "pebble", pebble1, train_seed=1)
    _write_run(tmp_path / "sac", "sac", sac)
    _write_run(tmp_path / "qpa", "qpa", qpa)
    dirs = [tmp_path / name for name in ("p0", "p1", "sac", "qpa")]
    rows = {r["method"]: r for r in rebel.rows("probe_point", dirs)}
    lowest_baseline = min(np.mean(pebble0.mean(0).tolist() + pebble1.mean(0).tolist()), sac.mean(0).mean())
    assert rows["qpa"]["threshold"] == pytest.approx(0.8 * lowest_baseline, abs=0.01)

    mine = qpa_rune.keyed_returns([tmp_path / "qpa"], "qpa")
    pebble = qpa_rune.keyed_returns([tmp_path / "p0", tmp_path / "p1"], "pebble")
    out = qpa_rune.paired(mine, pebble)
    expected = [qpa[:, i].mean() - pebble0[:, i].mean() for i in range(2)]  # keys (0, 0) and (0, 1) only
    assert out["keys"] == [[0, 0], [0, 1]]
    np.testing.assert_allclose(out["differences"], expected, atol=0.01)
    assert out["positive"] == 0 and out["pairs"] == 2
    end = qpa_rune.end_of_run([tmp_path / "qpa"], [[0, 1, 2]])
    assert end["mean"] == pytest.approx(qpa[-1].mean(), abs=0.01) and end["seeds"] == 3
    assert end["std"] == pytest.approx(qpa[-1].std(ddof=1), abs=0.01)  # the sample std, as every table gives it


def test_a_method_composed_with_rebels_term_names_its_lambdas_by_its_own_name(tmp_path):
    # examples/rebel_on_qpa.py registers rebel_qpa in its own process only: its lambda 0 is QPA, not PEBBLE.
    write_grid_run(tmp_path / "run", algo="rebel_qpa")
    _edit(tmp_path / "run", "meta.json", lams=[lam for lam, _ in GRID])
    labels = sorted(compare.methods(tmp_path / "run"))
    assert labels == sorted(f"rebel_qpa lam={lam:g}, {t}" for lam in (0.0, -0.1) for t in ("noisy", "skip"))


def test_rebel_rows_count_only_the_named_surf_run_in_the_threshold(tmp_path, monkeypatch):
    import rebel

    rng = np.random.default_rng(1)
    pebble, sac = rng.uniform(100, 200, (4, 2)), rng.uniform(300, 400, (4, 2))
    low, high = rng.uniform(10, 20, (4, 2)), rng.uniform(120, 180, (4, 2))
    _write_run(tmp_path / "pebble", "pebble", pebble)
    _write_run(tmp_path / "sac", "sac", sac)
    _write_run(tmp_path / "surf_low", "surf", low)
    _write_run(tmp_path / "surf_high", "surf", high)
    _edit(tmp_path / "surf_high", "config.json", **{"surf.reward_update": 7})
    dirs = [tmp_path / name for name in ("pebble", "sac", "surf_low", "surf_high")]
    labels = sorted(compare.methods(tmp_path / "surf_high"))
    assert len(labels) == 1 and labels[0] != "surf", labels  # the second SURF run has a label of its own
    task = json.loads((tmp_path / "pebble" / "config.json").read_text())["env"]["task"]
    monkeypatch.setattr(rebel, "SURF", {task: labels[0]})
    rows = {r["method"]: r for r in rebel.rows(task, dirs)}
    named = [x.mean() for x in (pebble, sac, high)]  # 4 evaluations per seed: the final return is their mean
    assert rows["surf"]["threshold"] == pytest.approx(0.8 * min(named), abs=0.01)  # the low SURF run is a row only
