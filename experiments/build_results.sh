#!/usr/bin/env bash
# Every table (results/*.json) and figure (results/*.png) of RESULTS.md, rebuilt from the run directories'
# logs (config.json, meta.json, metrics.jsonl, final.json) under results/runs/. A CPU is enough (a few minutes).
#
# Usage, from the repository root:
#   bash experiments/build_results.sh            # PYTHON defaults to .venv/bin/python, else python3
#
# To build the tables from your own runs, copy each run directory (its config.json, meta.json, metrics.jsonl and
# final.json are enough) to the path under results/runs/ that experiments/README.md names for it, then run this.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python3)}
export PYTHONPATH=$PWD/src:$PWD/experiments${PYTHONPATH:+:$PYTHONPATH}
run() { echo "+ $*" >&2; "$PYTHON" "$@"; }
WRONG_RESET="Run with a wrong cheetah reset (root pitch drawn over a full turn: 48.6% of episodes started on the \
cheetah's back); fixed 2026-11-23, not re-run. See RESULTS.md."
R=results/runs P=results/runs/paper S=results/runs/study B=results/runs/baselines E=results/runs/rebel

# SAC on the true reward (RESULTS.md, "Are our baselines faithful?").
run experiments/curves.py $R/sac_walker_walk --name sac_walker_walk
run experiments/curves.py $R/sac_cheetah_run_utd025 $R/sac_cheetah_run_utd05 --labels "SAC utd 0.25 (cut at 490k)" "SAC utd 0.5" \
  --name sac_cheetah_run --caveat "$WRONG_RESET"

# B-Pref's protocol: results/baselines.json and results/baselines_<task>.png.
run experiments/baselines.py

# REBEL against the baselines: results/rebel.json and results/rebel_<task>.png, rebel_lambda_walker_walk.png,
# rebel_teachers_walker_walk.png.
run experiments/rebel.py

# SAC and PEBBLE on quadruped_walk against their published figures: results/quadruped.json and
# results/quadruped_walk.png.
run experiments/quadruped.py

# Meta-World: SAC on the true reward, PEBBLE and QPA on the oracle's labels, success rates: results/metaworld.json,
# results/metaworld_sac.png and results/metaworld_pbrl.png.
run experiments/metaworld.py

# QPA and RUNE beside the five above: results/qpa_rune.json and results/qpa_rune_<task>.png.
run experiments/qpa_rune.py

# PEBBLE's walker_walk row at today's code and the running std's effect: results/headline.json and
# results/headline_walker_walk.png.
run experiments/headline.py

# MRN and RIME against PEBBLE on the same keys: results/rime_mrn.json, results/rime_mrn_walker_walk.png and
# results/rime_walker_walk_mistake.png.
run experiments/rime_mrn.py

# REBEL's first runs on B-Pref's protocol, stopped at 140k, against the baselines cut there.
run experiments/compare.py $B/pebble_walker_100_utd1 $B/pebble_walker_100_utd1_bf16_seed1 $B/surf_walker_100_utd1_bf16 \
  $E/rebel_walker_100_lams_0.1_-0.1_bf16_stopped140k $E/rebel_walker_100_lams_0.01_-0.01_bf16_stopped140k \
  --name rebel_walker_walk_140k --max-steps 140000 --reference pebble

# Pixels: results/pixels.json and its figures, and the DrQ-v2 walker take-off test.
run experiments/pixels.py
run experiments/takeoff.py

# The earlier protocol (40 envs, utd 0.25, uniform queries): RESULTS.md, "The earlier protocol".
run experiments/compare.py $R/sac_walker_walk $P/pebble_walker_1000 $P/rebel_walker_100_neg $P/rebel_walker_100_pos \
  $P/surf_walker_100 --name paper_comparison_walker_walk \
  --methods sac "pebble 1000 labels" "pebble (rebel lam=0)" surf "rebel lam=0.01 (replay V)" "rebel lam=-0.01 (replay V)" \
  --reference "pebble (rebel lam=0)"
run experiments/compare.py $R/sac_cheetah_run_utd025 $P/rebel_cheetah_100 $P/surf_cheetah_100 \
  --name paper_comparison_cheetah_run --reference "pebble (rebel lam=0)" --caveat "$WRONG_RESET"
run experiments/compare.py $P/rebel_walker_100_neg $P/rebel_walker_100_pos --name rebel_lambda_ablation_walker_walk \
  --threshold 100
run experiments/compare.py $P/rebel_walker_100_neg $S/teachers_pebble_walker_100_200k --name teachers_walker_walk_180k \
  --max-steps 180000 --methods "pebble (rebel lam=0)" "pebble (rebel lam=0), noisy" "pebble (rebel lam=0), mistake" \
  "pebble (rebel lam=0), skip" "pebble (rebel lam=0), equal" "pebble (rebel lam=0), myopic" --threshold 60
run experiments/compare.py $P/rebel_walker_100_neg $P/rebel_walker_100_pos $S/rebel_mean_walker_100_200k \
  --name rebel_estimator_walker_walk_200k --max-steps 200000 \
  --methods "pebble (rebel lam=0)" "rebel lam=0.01 (replay V)" "rebel lam=-0.01 (replay V)" \
  "rebel lam=0.01 (replay V, mean estimator)" "rebel lam=-0.01 (replay V, mean estimator)" \
  "rebel lam=0.001 (replay V, mean estimator)" "rebel lam=-0.001 (replay V, mean estimator)" --threshold 60
