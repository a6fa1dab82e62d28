#!/usr/bin/env bash
# Every preference figure and JSON summary in results/ (RESULTS.md) from the logged runs.
#
# The runs: on a GPU machine, repeat until every job reads "done" (each call continues the last):
#   python experiments/gpu_batch.py experiments/plans/paper.json --seconds 500   # 4 GPUs
#   python experiments/gpu_batch.py experiments/plans/study.json --seconds 440   # 2 GPUs
# then copy runs/batch/<job>/{config,meta,metrics,final}.json* to results/runs/{paper,study}/<job>/.
# SAC baselines: results/runs/sac_* (RESULTS.md gives their commands).
#
# Usage: bash experiments/figures.sh   (from the repository root; CPU is enough)
set -e
export PYTHONPATH=src:experiments; P=results/runs/paper; S=results/runs/study; PY=.venv/bin/python
$PY experiments/compare.py results/runs/sac_walker_walk $P/pebble_walker_1000 $P/rebel_walker_100_neg $P/rebel_walker_100_pos $P/surf_walker_100 --name paper_comparison_walker_walk --methods sac "pebble 1000 labels" "pebble (rebel lam=0)" surf "rebel lam=0.01 (replay V)" "rebel lam=-0.01 (replay V)" --reference "pebble (rebel lam=0)"
$PY experiments/compare.py results/runs/sac_cheetah_run_utd025 $P/rebel_cheetah_100 $P/surf_cheetah_100 --name paper_comparison_cheetah_run --reference "pebble (rebel lam=0)"
$PY experiments/compare.py $P/rebel_walker_100_neg $P/rebel_walker_100_pos --name rebel_lambda_ablation_walker_walk --threshold 100
$PY experiments/compare.py $P/rebel_walker_100_neg $S/teachers_pebble_walker_100_200k --name teachers_walker_walk_180k --max-steps 180000 --methods "pebble (rebel lam=0)" "pebble (rebel lam=0), noisy" "pebble (rebel lam=0), mistake" "pebble (rebel lam=0), skip" "pebble (rebel lam=0), equal" "pebble (rebel lam=0), myopic" --threshold 60
$PY experiments/compare.py $P/rebel_walker_100_neg $P/rebel_walker_100_pos $S/rebel_mean_walker_100_200k --name rebel_estimator_walker_walk_200k --max-steps 200000 --methods "pebble (rebel lam=0)" "rebel lam=0.01 (replay V)" "rebel lam=-0.01 (replay V)" "rebel lam=0.01 (replay V, mean estimator)" "rebel lam=-0.01 (replay V, mean estimator)" "rebel lam=0.001 (replay V, mean estimator)" "rebel lam=-0.001 (replay V, mean estimator)" --threshold 60
# The faithful-protocol tables (issues 9 and 10): results/baselines.json (+ figures) and results/rebel.json.
$PY experiments/baselines.py
$PY experiments/rebel.py
# REBEL's first faithful-protocol runs, stopped at 140k, against the baselines cut there (RESULTS.md).
B=results/runs/baselines; R=results/runs/rebel
$PY experiments/compare.py $B/pebble_walker_100_utd1 $B/pebble_walker_100_utd1_bf16_seed1 $B/surf_walker_100_utd1_bf16 $R/rebel_walker_100_lams_0.1_-0.1_bf16_stopped140k $R/rebel_walker_100_lams_0.01_-0.01_bf16_stopped140k --name rebel_walker_walk_140k --max-steps 140000 --reference pebble
$PY experiments/pixels.py  # issue 12's results/pixels.json and figures (its RUNS and STOPPED runs)
