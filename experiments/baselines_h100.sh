#!/usr/bin/env bash
# The faithful-baseline runs of issue 9 on one lent H100 (2026-11-24): PEBBLE and PEBBLE+SURF on
# walker_walk (100 labels, 5 seeds, 500k steps, 10 envs, utd 0.3) and SAC on cheetah_run on the
# fixed reset, as three processes sharing the GPU. Each call runs for at most $1 seconds
# (--time-limit), checkpoints, and the next call resumes; the logs go to $OUT/runs.tar.gz.
# Usage (device tool, carrying .whl): bash experiments/baselines_h100.sh 520 [set]
#   set "shared" (default): the three runs side by side (the first GPU session: sharing slowed
#   each walker run about 2.5x, so they did not finish); set "utd1": PEBBLE at B-Pref's utd 1 alone.
set -u
limit=${1:-520}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl >/dev/null 2>&1
export PYTHONPATH=/tmp/site:src PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
common="--checkpoint-every 1000 --time-limit $limit --no-progress --no-tensorboard"
launch() {  # name, then the training flags
  local name=$1; shift
  local dir=runs/$name resume=""
  [ -d "$dir/checkpoints" ] && resume="--resume"
  [ -f "$dir/final.json" ] && { echo "$name: done"; return; }
  python3 -m rebel_jax.train "$@" --run-dir "$dir" $common $resume >>"runs/$name.log" 2>&1 &
}
mkdir -p runs
if [ "${2:-shared}" = utd1 ]; then
  launch pebble_walker_100_utd1 --preset paper --algo pebble --task walker_walk --labels 100 --seeds 5
  wait
  for f in runs/pebble_walker_100_utd1.log; do grep -v warp "$f" | tail -3; done
  tar czf "$OUT/runs.tar.gz" --exclude=checkpoints runs
  exit 0
fi
launch pebble_walker_100 --preset paper --algo pebble --task walker_walk --labels 100 --seeds 5 --utd 0.3
launch surf_walker_100 --preset paper --algo surf --task walker_walk --labels 100 --seeds 5 --utd 0.3
launch sac_cheetah_fixed --preset paper --algo sac --task cheetah_run --seeds 5 --num-envs 40 --utd 0.25
wait
for f in runs/*.log; do echo "== $f"; grep -v "warp" "$f" | tail -4; done
for d in runs/*/; do n=$(wc -l <"$d/metrics.jsonl" 2>/dev/null); echo "$d rounds=$n"; done
tar czf "$OUT/runs.tar.gz" --exclude=checkpoints runs
