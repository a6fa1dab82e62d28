#!/usr/bin/env bash
# The faithful-baseline runs of issue 9 on one lent H100. Each call runs for at most $1 seconds
# (--time-limit), checkpoints, and the next call (on the same warm machine) resumes; the logs (no
# checkpoints) go to $OUT/runs.tar.gz (`python experiments/collect.py <files_at>/runs.tar.gz pixels` copies the
# finished runs into results/runs/pixels/). A persistent compilation cache under runs/ spares the resumed
# calls the ~90 s compile.
# Usage (device tool, carrying .whl): REBEL_JAX_GIT_COMMIT=<sha> bash experiments/baselines_h100.sh LIMIT SET
# The device image has no mujoco, mujoco-mjx or brax; fetch the wheels once here (.whl/ is git-ignored), from the
# repo root with the .venv active (the versions the device ran since the first pixel sessions):
#   pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 -d .whl mujoco==3.17.0 mujoco-mjx==3.17.0 brax==0.14.2 tyro==1.0.17 \
#     tensorboardX==2.6.5 jaxopt==0.8.5 ml-collections flask flask-cors trimesh glfw pyopengl websockets \
#     docstring-parser typeguard blinker itsdangerous
#   SET "shared" (2026-11-24, first session): PEBBLE and SURF at utd 0.3 and SAC cheetah side by side
#       (sharing the GPU slowed each walker run about 2.5x, so they did not finish);
#   SET "utd1" (2026-11-24, first session): PEBBLE at B-Pref's utd 1 alone (stopped at 270k);
#   SET "pebble500" (second session): the same PEBBLE job, run to 500k over several calls;
#   SET "surf500": PEBBLE+SURF at utd 1, likewise.
#   SET "surf500bf16" (third session): the "surf500" job in bf16 (same seeds), to 500k;
#   SET "pebble500bf16": the "pebble500" job in bf16 on five new seeds (--seed 1).
# Planned for the next session (bf16, each fits one 30-minute machine by the bf16 round times of
# BENCHMARKS.md; cheetah's settings are walker's carried over: neither B-Pref nor SURF publishes a
# cheetah command, and the published cheetah figures are PPE's re-run):
#   SET "pebble_cheetah1m" / "surf_cheetah1m": cheetah_run, 100 labels, 1M steps (~100k vector
#       steps x (1.3 ms env + 10 bf16 updates) = about 21 min);
#   SET "pebble1000": walker_walk PEBBLE with 1,000 labels (100 per session, B-Pref's
#       scripts/walker_walk/1000/oracle/run_PEBBLE.sh); ran in the sixth session (948.1, 1,325 s);
#   SET "pebble_env40" (fifth session): the "pebble500bf16" job (same seeds) at 40 envs instead of 10, for
#       the 12-minute target and the smallest num_envs that keeps B-Pref's curve;
#       It was refused: num_envs <= 10 under query.pool episodes (RESULTS.md);
#   SET "surf_cheetah_ru" with RU=<steps factor> (after the fifth session): the SURF cheetah 1M job
#       with --surf.reward-update RU. RU=100 ran in the sixth session to 790k (620.8, RESULTS.md;
#       12.4 s rounds, about 1,520 s to 1M); its 1M figure is owed. Its first call on a fresh machine with
#       LIMIT 560 passed the call's 600 s and lost its work; 480 was safe;
#   SET "drqv2_seed" with TASK=walker|cheetah and SEED=k: DrQ-v2 on pixels, SEEDS seeds (default 1), 500k frames
#       (250k agent steps at action repeat 2). Sixteenth session: TASK=cheetah SEEDS=5 PRECISION=bf16 in one
#       program, 6.90 s rounds, 1,798 s of rounds, four chained calls (LIMIT 300, 560, 575, 580), 1,930 s held: a
#       machine goes back after 30 minutes held only at the end of the call then in flight. Walker at 5 seeds is
#       projected at about 13 s per round in bf16 (BENCHMARKS.md): about 55 min per 5-seed job, longer than one
#       machine is held, and its replay checkpoint (2.1 GB per seed) cannot travel. One walker seed per job is
#       about 21 min held (4.67 s rounds at 10 envs). Eighteenth session: TASK=walker SEED=1 SEEDS=2, 6.70 s
#       rounds, four chained calls (LIMIT 480, 585, 604, 112), 1,775 s held, counted in full: the device time ran
#       out at round 245 of 250. Two walker seeds fit a session only where held time counts at less than full.
#       Nineteenth session (two H200s, GPU=0 beside a pixel_seed job on GPU=1): SEED=0 to 500k, 3.79 s rounds,
#       1,006 s of rounds (it failed: RESULTS.md). On two H200s, SEED=3 SEEDS=2 on GPU 0 and SEED=5 SEEDS=2 on GPU
#       1 would take about 24 min of rounds each (estimated). Twentieth session, the take-off test (two H200s):
#       SEED=10 SEEDS=8 STEPS=60000 PRECISION=bf16 on GPU 0 and the same with CRITIC_F32=1 on GPU 1, 17.0 s rounds,
#       about 1,040 s of rounds each, three chained calls (LIMIT 470, 585, 150), 1,566 s held.
#       Twenty-fourth session, for the walker target (code 2c946c3, one machine of four H100s, 1,320 s held, counted
#       in full; three chained calls, LIMIT 470, 585, 380): CRITIC_F32=1 PRECISION=bf16, one detached job per GPU,
#       GPU=0 SEED=20 (SEEDS=2 only where the GPUs are H200s: the 2-seed job is about 28 min on an H100) and
#       GPU=1..3 SEED=22, 23, 24, WATCH=0 on all but the last: 4.52-4.61 s rounds, 1,173-1,205 s each, all four
#       walk. The fifth seed, SEED=21 alone on a one-GPU machine with 475 s left, was lost: that machine counted
#       its held time in full and the call's limit_s (445 s, what the budget left) ended it before finish shipped
#       the log. A call's LIMIT must stay below the limit_s the budget leaves.
#       SET "four_gpu_plan" (REBEL_JAX_GIT_COMMIT=<sha> bash experiments/baselines_h100.sh LIMIT four_gpu_plan, chained
#       with the same command: a job that runs or has finished is not started again) ran in the twenty-fifth session
#       (code 9988a96, one machine of four H100s, three chained calls, LIMIT 470, 585, 540, 1,566 s held, counted in
#       full; every job finished): GPU=0 TASK=walker SEED=21 CRITIC_F32=1 drqv2_seed (3.85 s median rounds, 1,014 s
#       in all; it failed, 28.2); GPU=1 ALGO=surf TASK=cheetah SEED=6 SEEDS=2 STEPS=150000 pixel_seed (1,383 s);
#       GPU=2 ALGO=rebel LAMS="0 0.001" TASK=cheetah SEED=8 SEEDS=2 STEPS=150000 (1,201 s); GPU=3 the first pixel
#       walker preference job, ALGO=rebel LAMS="0 0.001" TASK=walker SEED=0 ENVS=20 SEED_STEPS=10000 STEPS=250000
#       (5.51 s median rounds, 1,440 s in all with a 71 s first round). Its CPU memory estimate was 2.85 GiB of state
#       and 3.6 GiB of round temp per column.
#       SET "walker_pixel_plan" (the same usage) ran in the twenty-sixth session (code d8aeeb7, one machine of four
#       H100s, three chained calls, LIMIT 470, 585, 585, 1,619 s held, counted in full; every job finished): GPU=0..2
#       that walker job on SEED=1, 2, 3 (5.50-5.55 s median rounds, 1,469-1,474 s in all with 86-97 s first rounds),
#       GPU=3 ALGO=surf TASK=walker SEED=0 with the same ENVS, SEED_STEPS and STEPS (3.22 s median rounds, 1,042 s in
#       all with a 99 s first round; the CPU estimate had been 19 min, from benchmarks/pixel_memory.py --configs
#       surf_walker --seeds 1 --total-steps 250000 --flags="--num-envs 20 --seed-steps 10000 --drqv2.precision bf16":
#       5.1 GiB of state and 6.2 GiB of round temp).
#       SET "walker_pixel_last" (the same usage) ran in the twenty-eighth session (code df8af23, one machine of four
#       H100s, three chained calls, LIMIT 470, 585, 560, 1,567 s held, counted in full; every job finished): GPU=0 the
#       PEBBLE and REBEL walker job on SEED=4 (5.45 s median rounds, 1,441 s), GPU=1..3 ALGO=surf on SEED=1, 2, 3
#       (3.13-3.16 s, 992-1,009 s). PEBBLE and REBEL had 5 walker keys and SURF 4. Twenty-ninth session (code d6a47af,
#       two one-GPU machines, each counting half its held time): DETACH=1 PRECISION=bf16 ALGO=surf TASK=walker SEED=4
#       ENVS=20 SEED_STEPS=10000 STEPS=250000 bash experiments/baselines_h100.sh L pixel_seed (three chained calls,
#       LIMIT 470, 585, 150; 3.16 s median rounds, 1,013 s, 1,146 s held), then the same with ALGO=rebel LAMS="0 0.001"
#       SEED=5 (four chained calls, LIMIT 470, 585, 570, 150; 5.57 s median rounds, 1,483 s, about 1,646 s held):
#       6, 6 and 5 walker keys;
#   SET "ladder" with RUNG=0|1|2|3 (planned): the issue's ladder re-run on today's code in bf16 with the
#       seeds of the rung-4 bf16 run (--seed 1), so that every rung has a log, its 200k and 500k returns and
#       the frozen evaluation: 0 = the earlier protocol (uniform, lecun init, rows pool, 40 envs, utd 0.25,
#       no reset update), 1 = + disagreement, 2 = + torch init, 3 = + complete-episode pool at 10 envs and
#       the reset update (utd 0.3); rung 4 is "pebble500bf16". All at pretrain.running_std exact, as the
#       rung-4 runs. Rungs 0-2 (40 envs, 125k updates) are estimated at about 9 min each, rung 3 about
#       15 min (not measured);
#   SET "rebel_ablation" with LAMS="<lambda> <lambda>" (issue 10's ablation): REBEL as the paper
#       defines it (on-policy V from the reset, whole episode, gamma 0.99, lower bound, not normalised) at
#       two lambdas in one program of 10 columns (5 seeds each). Seventh session: LAMS "0.1 -0.1" and
#       "0.01 -0.01" ran one call each and stopped at 140k (RESULTS.md); a round takes 30.3 s, so 500k is
#       about 25 min of rounds plus ~2 min of compile: one program per machine, its calls chained at once.
#       The grid +-0.001, +-0.01, +-0.1 (|lambda| >= 0.1 saturates the reward) is three such programs;
#       FORM=penalty (the un-relaxed penalty, in which a constant shift of the reward cancels) and
#       NORMALIZE=1 (the scale-free form) are the variants, named in the run directory;
#       On a machine of several GPUs, GPU=k puts a detached job on GPU k alone (CUDA_VISIBLE_DEVICES) and WATCH=0
#       returns at once after starting it, so that one call starts a job per GPU: every script but the last takes
#       WATCH=0, and the last one's watch waits for all of them and ships every log.
#       Eighth session: DETACH=1 runs it as one process for the whole machine (setsid, so it outlives
#       each call): no resumed compiles and no checkpoints (they cannot leave the machine, and the CLI's
#       default of one per round cost 1-3 s per REBEL round and about 8 s per DrQ-v2 round of 4.7 s).
#       The first call starts it; every call (the same command, chained) watches it until it ends or the
#       call's LIMIT, then ships the logs. A .gpu_cache folder in the repo root (carried; not .jax_cache,
#       the tests' CPU cache) seeds the compilation cache; finish ships the cache back when it is small.
#       LAMS "0.01 -0.01" ran so (eighth session: 4 calls, 1,919 s held, 1,661 s of rounds), and
#       LAMS "0.001 -0.001" (ninth session: 3 calls, 1,669 s held, 1,579 s of rounds; the carried cache
#       cut the first round to 89 s), and LAMS "0.001 0.01" SOURCE=replay (tenth session: 3 calls, about
#       1,715 s held, 1,608 s of rounds); eleventh session: LAMS "0.001 0.01" OUTPUT=sigmoid (1,728 s held,
#       1,632 s of rounds) and LAMS "0.1 -0.1" to 500k (1,677 s held, 1,579 s of rounds), two machines counted at
#       half. A one-GPU machine may count its held time in full (it did in the
#       ninth session): then one such program is a whole session's device time;
#   SET "rebel_cheetah" with LAM=<lambda>: the lambda the rule of RESULTS.md chose on walker_walk (0.001
#       since the ninth session) on cheetah_run, 1M steps, PEBBLE's cheetah seeds; LAM=0.001 ran in the tenth
#       session (3 calls, 1,433 s held, 1,308 s of rounds: 114.6 s with the compile, then 12.05 s);
#   SET "rebel_teacher" with LAM and TEACHER: PEBBLE and REBEL under one imperfect teacher; LAM=0.001 TEACHER=noisy
#       ran in the twelfth session (3 calls, 1,733 s held, counted in full; 1,632 s of rounds: 123.4 s for the
#       first, its round program from the carried cache, then 30.8 s); mistake and skip in the thirteenth (two machines
#       counted at half, about 1,650 and 1,700 s held; 84.3 s first rounds, then 30.0 and 30.9 s); equal and myopic
#       remain, one machine each. Since 79e1013 the round also logs session_oracle_agreement, so .gpu_cache no longer
#       held its program: equal's first round (fourteenth session, code 83927f7; 3 calls, about 1,673 s held, counted
#       at 67%) compiled it in 113.2 s, then 29.9 s rounds; myopic in the fifteenth (code 8cc84bc, 3 calls, 1,670 s
#       held; the carried cache held the round program: 84.6 s first round, then 30.2 s): all five teachers have run;
#   SET "pixel_seed" with ALGO, TASK, SEED and STEPS: SEEDS seeds (default 1) of a pixel preference run; ENVS and
#       SEED_STEPS change the preset's 4 envs and 2,000 seed steps (below). Nineteenth session: ALGO=rebel
#       TASK=cheetah LAMS="0 0.001" SEED=0 SEEDS=2 STEPS=150000 PRECISION=bf16 on one H200 (GPU=1), 5.87 s plain
#       rounds and 55-150 s session rounds; the device time stopped it at 82k steps (RESULTS.md).
#       Twenty-first session (two H200s, code 8c73ac6, three chained calls, 1,604 s held): GPU=1 ALGO=rebel LAMS="0
#       0.001" SEED=2 SEEDS=2 STEPS=150000 (looped sessions: 5.90 s plain rounds, 10.3-24.4 s session rounds, done in
#       1,134 s) and GPU=0 ALGO=surf SEED=0 SEEDS=3 STEPS=80000 with XLA_PYTHON_CLIENT_MEM_FRACTION=0.95 (done in
#       747 s; at JAX's default 75% its round asked for 72.56 GiB more and failed: SURF's pool is 13.1 GB per seed,
#       and the looped session copied every column's state; since loop_in_place one column's, BENCHMARKS.md).
#       Next (estimated from those rows, not run): 500k frames of the 4-column PEBBLE + REBEL program about 31 min,
#       of 3 SURF seeds about 63 min in tf32 (its sessions train all 20 passes); bf16 reward training
#       (--pixel-reward.precision bf16, session_parts: epochs 1.9x faster) is untried in a run. Planned for the next
#       two-GPU machine (estimated, not run): GPU=0 ALGO=surf SEED=2 SEEDS=2 STEPS=150000 (SURF on the keys of
#       PEBBLE/REBEL's seeds 2-3, to 300k frames: about 150 x 4 s + 15 sessions of 2 columns growing 0.21 s per
#       label, about 21 min) and GPU=1 ALGO=rebel LAMS="0 0.001" SEED=4 SEEDS=2 STEPS=150000 (the measured 19-min
#       program on new keys): at 300k frames 4, 4 and 2 seeds, at 160k frames 6, 6 and 5. Then SURF_ADAM=1 (SURF's
#       reward Adam stepping, notes/surf_pixel_audit.md item 3) against the same keys without it, one job per GPU.
#       Twenty-second session (code 8023f01; two one-H200 machines in turn, counted at half): ALGO=surf SEED=2 SEEDS=2
#       STEPS=150000 (3.55 s plain rounds, 1,279 s of rounds; three chained calls, LIMIT 470, 585, 585, 1,416 s
#       held), then ALGO=rebel LAMS="0 0.001" SEED=4 SEEDS=2 STEPS=150000 (5.95 s plain rounds, 1,146 s of rounds)
#       and, started in the same call once it ended, SURF_ADAM=1 ALGO=surf SEED=0 SEEDS=2 STEPS=80000 (3.42 s plain
#       rounds, 561 s; LIMIT 470, 585, 585 chained with the SURF_ADAM start, 480; about 1,930 s held). Next
#       (estimated, not run): ALGO=surf SEED=4 SEEDS=2 STEPS=150000 on one machine (about 22 min) and, on another,
#       ALGO=surf SEED=6 SEEDS=1 with ALGO=rebel LAMS="0 0.001" SEED=6 SEEDS=1, one per GPU of a two-GPU machine or
#       one after another: 5 seeds of each method at 300k frames. Twenty-third session (code 693e1cd, one machine of
#       two H200s, three chained calls, LIMIT 470, 585, 585, 1,392 s held, counted in full): GPU=0 WATCH=0 ALGO=surf
#       SEED=4 SEEDS=2 STEPS=150000 (3.46 s plain rounds, 1,259 s of rounds) beside GPU=1 ALGO=rebel LAMS="0 0.001"
#       SEED=6 SEEDS=2 STEPS=150000 (5.89 s, 1,101 s): neither slowed; at 300k frames 6, 6 and 4 seeds. A machine goes back only at the end of the call in
#       flight at 30 minutes held (1,930 s held twice), so a job of up to about 35 min fits one machine if its last
#       call starts before then. By that (projected from the 300k-frame runs' rounds by experiments/job_time.py, within
#       1.2% of each run from its first 80k steps): the 4-column PEBBLE + REBEL program to 500k frames (30-32 min of
#       rounds) fits one machine; SURF to 500k at 2 seeds (44-45 min) does not, at 1 seed (25-25.5 min, job_time.py
#       --columns 1) it does: 5 seeds of the three methods at 500k frames are about 8 machines (3 + 5). On a machine
#       of four GPUs counted in full (untried), one job per GPU: job_time.py --columns (plain rounds on the line
#       1.08 + 1.21 s per column through the 2-, 3- and 4-column H200 runs, sessions scaled by the columns; the
#       2-column SURF runs carried to 3 columns came within 5% of the 3-column run) projects the 2-column PEBBLE +
#       REBEL program (1 key each) to 500k frames at 18-19 min of rounds and 1-seed SURF at 25-25.5 min: on four
#       GPUs counted in full, SURF is at the edge of one session's 30 minutes with the machine's start. Neither size
#       has run. With REWARD_BF16=1 (if its sessions speed up
#       as its epochs did, 1.9x; untried in a run) 1-seed SURF would take about 19 min and 2-seed SURF to 500k frames
#       about 31 min, which fits a one-GPU machine counted at half; a 500k-frame campaign that takes it gives it to
#       every method. Two jobs on one GPU do not pay (twenty-third session, one H200,
#       one call, LIMIT 270: XLA_PYTHON_CLIENT_MEM_FRACTION=0.55 WATCH=0 ALGO=surf SEED=8 SEEDS=2 beside
#       XLA_PYTHON_CLIENT_MEM_FRACTION=0.4 ALGO=rebel LAMS="0 0.001" SEED=8 SEEDS=2, STEPS=150000): plain rounds
#       8.79 s and 11.8 s against 3.46 s and 5.89 s alone, about 11% less work per second than one after the other
#       (BENCHMARKS.md); one job per GPU;
#   SET "determinism": one walker PEBBLE program run twice from the same keys, compared bit for bit, without and
#       with --xla_gpu_deterministic_ops; ran in the fourteenth session (494 s: 141 of 204 leaves differ without,
#       none with; rounds 22.5 s against 28.3 s);
#   SET "pixel_smoke" with JOBS, SEEDS and MAX (issue 12): a few rounds of pixel jobs, their round seconds and peak
#       memory (benchmarks/pixel_preference_smoke.py), rows in $OUT; fifteenth session: pebble_walker at 5 seeds
#       (MAX=420, 237 s: 45.9 GiB, 22.3 s rounds) and 1 seed (MAX=200, 171 s: 10.3 s rounds);
#   SET "session_parts" with JOBS, LABELS, PRECISIONS, SESSION_COLUMNS, REPEATS and MAX (issue 12, after the
#       nineteenth session's 55-150 s sessions): a pixel preference session's parts timed apart, tf32 against bf16,
#       and whole 4-column sessions with pixel_reward.session_loop on and off (benchmarks/pixel_session_parts.py);
#       twentieth session: MAX=380 after the take-off jobs (tf32 parts and the looped session); twenty-first:
#       PRECISIONS=bf16 MAX=255 after the pixel jobs (bf16 parts and the looped session); the batched session is
#       still not reached: give it MAX=540 and its own call;
#   SET "command_buffers": walker's control step and the SAC update with CUDA graphs over while loops; ran in the
#       fifteenth session (205 s: the graphs made the step 11-18% slower and left the update unchanged);
#   SET "drqv2_bench" (issue 12): DrQ-v2's update timed by parts and with the patch-product kernel gradient; its
#       JSON rows come back in $OUT. Fourteenth session: under timeouts of 150 s and 110 s it wrote 4 parts and the XLA
#       update row, not the conv parts nor the patch rows (each part compiles its own program); now 330 s and 200 s,
#       about 9 minutes (not measured). Fifteenth session: the patch row alone, by hand (drqv2_update.py --kernel-grad
#       patches: 24.97 ms per 5-seed update against XLA's 19.49, BENCHMARKS.md);
#   SET "rebel_walker" with LAM=<lambda>: REBEL at lambda LAM (on-policy V, normalised) beside
#       lambda 0 (= PEBBLE, five more seeds) in one program of 10 columns (--seed 2); not run (rebel_ablation's
#       10-column rounds take about 31 s).
set -u
limit=${1:-520} call_limit=${1:-520}
# Installed once per machine: a second script in the same call (GPU=, below) or a chained call skips it.
[ -f /tmp/site/.installed ] || { python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl >/dev/null 2>&1 && touch /tmp/site/.installed; }
limit=$((limit - SECONDS))  # The install's seconds come out of the run's limit (its time on a fresh machine is not measured).
export PYTHONPATH=/tmp/site:src PYTHONUNBUFFERED=1
export JAX_COMPILATION_CACHE_DIR=$PWD/runs/.jax_cache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=1
# A carried cache seeds the machine's once, in its first call (cp -n warned on the device's coreutils)
[ -d .gpu_cache ] && [ ! -d runs/.jax_cache ] && mkdir -p runs && cp -r .gpu_cache runs/.jax_cache
common="--checkpoint-every 1000 --time-limit $limit --no-progress --no-tensorboard"
launch() {  # name, then the training flags
  local name=$1; shift
  local dir=runs/$name resume=""
  [ -d "$dir/checkpoints" ] && resume="--resume"
  [ -f "$dir/final.json" ] && { echo "$name: done"; return; }
  python3 -m rebel_jax.train "$@" --run-dir "$dir" $common $resume >>"runs/$name.log" 2>&1 &
}
detach() {  # name, then the training flags: one process for the machine's whole loan (see DETACH above)
  local name=$1; shift
  [ -f "runs/$name/final.json" ] && return
  pgrep -f -- "--run-dir runs/$name " >/dev/null && return
  ${GPU:+env CUDA_VISIBLE_DEVICES=$GPU} setsid python3 -m rebel_jax.train "$@" --run-dir "runs/$name" --no-progress --no-tensorboard --video-steps 0 --checkpoint-every 0 >"runs/$name.log" 2>&1 </dev/null &
  started+=($!)
}
started=()  # this call's detached jobs: until a job's process has exec'd, pgrep cannot see it by its command line
running() {  # whether a training process is left: any on the machine (pgrep), or one this call started
  pgrep -f rebel_jax.train >/dev/null && return 0
  local pid
  for pid in "${started[@]}"; do kill -0 "$pid" 2>/dev/null && return 0; done
  return 1
}
watch() {  # wait until no training process is left or the call's limit is near, then ship the logs; meanwhile
  # ship them every SHIP_EVERY seconds (default 60): a call the device ends at its limit_s (what the device time
  # left, which may be below LIMIT) returns what $OUT holds, and the twenty-fourth session lost a whole job's log so
  local shipped=$SECONDS
  while [ $SECONDS -lt $((call_limit - 20)) ] && running; do
    sleep 5
    [ $((SECONDS - shipped)) -ge "${SHIP_EVERY:-60}" ] && { ship; shipped=$SECONDS; }
  done
  running && echo "still running after ${SECONDS}s"
  finish
}
start() {  # name, then the training flags: detached under DETACH=1, else time-limited calls with resume
  if [ -n "${DETACH:-}" ]; then detach "$@"; [ "${WATCH:-1}" = 0 ] || watch; else launch "$@"; wait; finish; fi
}
ship() {  # the logs (no checkpoints) to $OUT, replaced whole: a call killed while it writes keeps the last copy
  tar czf "$OUT/runs.tar.gz.part" --exclude=checkpoints --exclude=.jax_cache runs && mv "$OUT/runs.tar.gz.part" "$OUT/runs.tar.gz"
}
finish() {  # print the tails and ship the logs
  for f in runs/*.log; do echo "== $f"; grep -v warp "$f" | tail -3; done
  for d in runs/*/; do echo "$d rounds=$(wc -l <"$d/metrics.jsonl" 2>/dev/null)"; done
  ship
  if [ "$(du -sm runs/.jax_cache 2>/dev/null | cut -f1)" -lt 15 ] 2>/dev/null; then tar czf "$OUT/jax_cache.tar.gz" -C runs .jax_cache; fi
}
mkdir -p runs
# REBEL's variants (rebel_ablation, rebel_cheetah): FORM=penalty, NORMALIZE=1, SOURCE=replay, OUTPUT=sigmoid,
# each passed as its flag and named in the run directory.
variant=(${FORM:+--rebel.form $FORM} ${NORMALIZE:+--rebel.normalize} ${SOURCE:+--rebel.source $SOURCE} ${OUTPUT:+--reward.output $OUTPUT})
variant_name=${FORM:+_$FORM}${NORMALIZE:+_normalized}${SOURCE:+_$SOURCE}${OUTPUT:+_$OUTPUT}
case "${2:-shared}" in
  utd1|pebble500)
    launch pebble_walker_100_utd1 --preset paper --algo pebble --task walker_walk --labels 100 --seeds 5
    wait; finish; exit 0 ;;
  surf500)
    launch surf_walker_100_utd1 --preset paper --algo surf --task walker_walk --labels 100 --seeds 5
    wait; finish; exit 0 ;;
  surf500bf16)
    launch surf_walker_100_utd1_bf16 --preset paper --algo surf --task walker_walk --labels 100 --seeds 5 --precision bf16
    wait; finish; exit 0 ;;
  pebble_cheetah1m|surf_cheetah1m)
    algo=${2%%_*}
    launch ${algo}_cheetah_100_1m_bf16 --preset paper --algo $algo --task cheetah_run --labels 100 --seeds 5 --total-steps 1000000 --precision bf16
    wait; finish; exit 0 ;;
  pebble1000)
    launch pebble_walker_1000_bf16 --preset paper --algo pebble --task walker_walk --labels 1000 --seeds 5 --precision bf16
    wait; finish; exit 0 ;;
  rebel_walker)
    launch rebel_walker_100_lam${LAM:?set LAM}_bf16 --preset paper --algo rebel --task walker_walk --labels 100 --seeds 5 --lam-grid 0 "$LAM" --rebel.normalize --precision bf16 --seed 2
    wait; finish; exit 0 ;;
  ladder)
    rung=(--pretrain.running-std exact)
    case ${RUNG:?set RUNG=0..3} in
      0) rung+=(--query.sampling uniform --reward.init lecun --query.pool rows --num-envs 40 --utd 0.25 --pretrain.reset-updates 0) ;;
      1) rung+=(--reward.init lecun --query.pool rows --num-envs 40 --utd 0.25 --pretrain.reset-updates 0) ;;
      2) rung+=(--query.pool rows --num-envs 40 --utd 0.25 --pretrain.reset-updates 0) ;;
      3) rung+=(--utd 0.3) ;;
    esac
    launch pebble_walker_100_rung${RUNG}_bf16_seed1 --preset paper --algo pebble --task walker_walk --labels 100 --seeds 5 --precision bf16 --seed 1 "${rung[@]}"
    wait; finish; exit 0 ;;
  rebel_ablation)  # two lambdas, 5 seeds each, the paper's V (the rebel defaults: onpolicy, lower_bound);
    # FORM=penalty runs eq. "bilevel_rlhf_fo" instead, NORMALIZE=1 the scale-free form, SOURCE=replay today's
    # replay-window V, OUTPUT=sigmoid the non-negative reward the lower bound assumes (each names the run)
    name=rebel_walker_100_lams_$(echo ${LAMS:?set LAMS} | tr ' ' '_')${variant_name}_bf16
    flags=(--preset paper --algo rebel --task walker_walk --labels 100 --seeds 5 --lam-grid $LAMS --precision bf16 --seed 2 "${variant[@]}")
    start "$name" "${flags[@]}"; exit 0 ;;
  rebel_teacher)  # issue 10's teachers: PEBBLE (lambda 0, bit for bit) and REBEL at the chosen lambda (LAM) under
    # one imperfect B-Pref teacher (TEACHER=noisy|mistake|skip|equal|myopic), 5 seeds each (--seed 2, REBEL's
    # oracle seeds), one program of 10 columns (~31 s rounds, as rebel_ablation): one machine per teacher
    name=rebel_walker_100_lams_0_${LAM:?set LAM}_${TEACHER:?set TEACHER}${variant_name}_bf16
    start "$name" --preset paper --algo rebel --task walker_walk --labels 100 --seeds 5 --lam-grid 0 "$LAM" --teacher "$TEACHER" --precision bf16 --seed 2 "${variant[@]}"
    exit 0 ;;
  rebel_cheetah)  # REBEL at the lambda chosen on walker_walk (LAM), carried unchanged to cheetah_run: 1M steps,
    # 5 seeds (PEBBLE's cheetah seeds), the variants as in rebel_ablation; ~100 rounds of ~12 s (SURF's)
    name=rebel_cheetah_100_1m_lam${LAM:?set LAM}${variant_name}_bf16
    start "$name" --preset paper --algo rebel --task cheetah_run --labels 100 --seeds 5 --total-steps 1000000 --rebel.lam "$LAM" --precision bf16 "${variant[@]}"
    exit 0 ;;
  surf_cheetah_ru)  # SURF cheetah at 1M with reward_update RU (1000 is SURF's walker command)
    launch surf_cheetah_100_1m_bf16_ru${RU:?set RU} --preset paper --algo surf --task cheetah_run --labels 100 --seeds 5 --total-steps 1000000 --precision bf16 --surf.reward-update "$RU"
    wait; finish; exit 0 ;;
  four_gpu_plan|walker_pixel_plan|walker_pixel_last)  # one detached job per GPU of four (header, drqv2_seed), each
    # this script's own set in a clean environment; the last one's watch waits for all four and ships every log.
    # four_gpu_plan ran in the twenty-fifth session, walker_pixel_plan in the twenty-sixth, walker_pixel_last in the
    # twenty-eighth: the walker pixel preference jobs, each "<algo> <key>" (rebel: PEBBLE and REBEL in one lam-grid program)
    if command -v nvidia-smi >/dev/null && [ "$(nvidia-smi -L | wc -l)" -lt 4 ]; then
      echo "$2 needs 4 GPUs, this machine has $(nvidia-smi -L | wc -l): start the jobs one by one"; exit 1
    fi
    self=(bash "$0" "$((call_limit - SECONDS))")
    clean=(env -u ALGO -u TASK -u SEED -u SEEDS -u STEPS -u LAMS -u ENVS -u SEED_STEPS -u CRITIC_F32 -u CAPACITY
      -u SURF_ADAM -u REWARD_BF16 -u GPU -u WATCH DETACH=1 PRECISION=bf16)
    walker=(TASK=walker ENVS=20 SEED_STEPS=10000 STEPS=250000)  # the issue's 500k frames, every env's episode first
    if [ "$2" = four_gpu_plan ]; then
      "${clean[@]}" GPU=0 WATCH=0 TASK=walker SEED=21 CRITIC_F32=1 "${self[@]}" drqv2_seed
      "${clean[@]}" GPU=1 WATCH=0 ALGO=surf TASK=cheetah SEED=6 SEEDS=2 STEPS=150000 "${self[@]}" pixel_seed
      "${clean[@]}" GPU=2 WATCH=0 ALGO=rebel LAMS="0 0.001" TASK=cheetah SEED=8 SEEDS=2 STEPS=150000 "${self[@]}" pixel_seed
      "${clean[@]}" GPU=3 ALGO=rebel LAMS="0 0.001" SEED=0 "${walker[@]}" "${self[@]}" pixel_seed
    else
      jobs=("rebel 1" "rebel 2" "rebel 3" "surf 0")
      [ "$2" = walker_pixel_last ] && jobs=("rebel 4" "surf 1" "surf 2" "surf 3")
      for gpu in 0 1 2 3; do
        read -r algo key <<<"${jobs[gpu]}"
        lams=() watch=(WATCH=0)
        [ "$algo" = rebel ] && lams=(LAMS="0 0.001")
        [ "$gpu" = 3 ] && watch=()  # the last job's watch waits for all four
        "${clean[@]}" GPU=$gpu "${watch[@]}" ALGO="$algo" "${lams[@]}" SEED="$key" "${walker[@]}" "${self[@]}" pixel_seed
      done
    fi
    exit 0 ;;
  drqv2_seed)  # DrQ-v2 on pixels, SEEDS seeds per job (default 1; seed_loop runs their updates one after another)
    case ${TASK:?set TASK=walker or cheetah} in
      walker) task=(--task walker_walk_pixels --drqv2.nstep 1 --drqv2.batch-size 512 --drqv2.std-steps 100000) ;;
      cheetah) task=(--task cheetah_run_pixels) ;;
    esac
    # PRECISION=bf16 runs DrQ-v2's matmuls and convolutions in bf16; ENVS=<envs per seed> (default 10): the walker
    # physics is about 13 ms a control step whatever the batch, so 20 envs halve it (2.56 s of a 4.67 s round at
    # 10); each is named in the run directory, as SEEDS above 1 (the seeds are fold_in(PRNGKey(SEED), i))
    # STEPS=<agent steps> (default 250000, 500k frames) shortens a job, e.g. the take-off test of notes/drqv2_audit.md:
    # TASK=walker SEEDS=8 STEPS=60000 PRECISION=bf16 on one GPU, and the same with CRITIC_F32=1 (the critics' output
    # layer in float32, --drqv2.critic-out-f32) or PRECISION=tf32 on the other (GPU=, above); each is named
    seeds=${SEEDS:-1} steps=${STEPS:-250000}
    name=drqv2_${TASK}_$((2 * steps / 1000))kframes_seed${SEED:?set SEED}${SEEDS:+_seeds$seeds}${ENVS:+_envs$ENVS}${PRECISION:+_$PRECISION}${CRITIC_F32:+_qf32}
    start "$name" --preset paper --algo drqv2 --seeds "$seeds" --seed "$SEED" --total-steps "$steps" --seed-steps 2000 --num-envs "${ENVS:-10}" --steps-per-round 1000 --eval-every 10000 ${PRECISION:+--drqv2.precision $PRECISION} ${CRITIC_F32:+--drqv2.critic-out-f32} "${task[@]}"
    exit 0 ;;
  pixel_seed)  # issue 12's pixel preference runs, SEEDS seeds per job (default 1; 5 walker seeds fit no machine's
    # loan; cheetah's physics is cheap, so a few seeds may: measure with pixel_smoke JOBS=pebble_cheetah first):
    # ALGO=pebble|surf|rebel, TASK=walker|cheetah, SEED=k, STEPS=<agent steps> (250000 = 500k frames, the issue's
    # walker length; SURF runs 1M frames), with benchmarks/pixel_memory.CONFIGS' flags (SURF's pixel settings,
    # notes/surf_pixel_audit.md); SEEDS above 1 is named in the run directory (seeds fold_in(PRNGKey(SEED), i));
    # CAPACITY=<transitions> sets the replay (default 100k, the issue's; SURF keeps the whole run), PRECISION=bf16
    # DrQ-v2's matmuls; LAMS="0 0.001" with ALGO=rebel runs PEBBLE (lambda 0, the same program as --algo pebble:
    # tests/test_pixel_preference.py) and REBEL side by side in one program of SEEDS columns each, sharing the
    # physics, the batched part of a round; each names the run
    [ -n "${LAMS:-}" ] && [ "$ALGO" != rebel ] && { echo "LAMS needs ALGO=rebel"; exit 1; }
    # One job per GPU: it may take 95% of the card, not JAX's default 75% (SURF's pool, 13.1 GB per seed on cheetah,
    # needed more at 3 seeds in the twenty-first session; a caller's own value stands)
    export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.95}
    root=$(cd "$(dirname "$0")/.." && pwd)
    flags=$(python3 -c "import sys; sys.path[:0] = ['$root/benchmarks', '$root/src']; from pixel_memory import CONFIGS; print(' '.join(CONFIGS['${ALGO:?set ALGO}_${TASK:?set TASK}']))") || exit 1
    # ENVS=<envs per seed> with SEED_STEPS=<agent steps> (e.g. 20 and 10000: every env ends an episode before the
    # first session, which queries complete episodes): the physics of the preset's 4 envs is about 7.5 s of a 10 s
    # one-seed round (BENCHMARKS.md, "Pixel PEBBLE on one H100"), so more envs make a seed's job fit one machine
    # SURF_ADAM=1: the reward ensemble's Adam stepped as SURF's torch code does (--pixel-reward.per-member-adam);
    # REWARD_BF16=1: the reward ensemble trained in bf16 (--pixel-reward.precision bf16, epochs 1.9x faster; SURF's
    # sessions, beyond a plain round, are 64% of its 500k-frame job, BENCHMARKS.md): a speed setting, named apart ("_rbf16"), so a
    # campaign takes it for every method or for none
    name=${ALGO}_${TASK}_pixels_${STEPS:?set STEPS}steps_seed${SEED:?set SEED}${SEEDS:+_seeds$SEEDS}${LAMS:+_lams_${LAMS// /_}}${CAPACITY:+_replay$CAPACITY}${ENVS:+_envs$ENVS}${SEED_STEPS:+_seedsteps$SEED_STEPS}${PRECISION:+_$PRECISION}${SURF_ADAM:+_surfadam}${REWARD_BF16:+_rbf16}
    start "$name" $flags --total-steps "$STEPS" --seeds "${SEEDS:-1}" --seed "$SEED" ${CAPACITY:+--buffer-capacity $CAPACITY} ${ENVS:+--num-envs $ENVS} ${SEED_STEPS:+--seed-steps $SEED_STEPS} ${PRECISION:+--drqv2.precision $PRECISION} ${LAMS:+--lam-grid $LAMS} ${SURF_ADAM:+--pixel-reward.per-member-adam} ${REWARD_BF16:+--pixel-reward.precision bf16}
    exit 0 ;;
  drqv2_bench)  # issue 12's update benchmarks before any pixel run (about 9 min after the install): where one
    # seed's DrQ-v2 update spends its time (drqv2_parts.py), and the 5-seed looped update with XLA's kernel
    # gradients against the patch product (drqv2_update.py); the rows merge into copies of the repo's tables in $OUT
    export PYTHONPATH=/tmp/site:src:benchmarks
    cp benchmarks/results/drqv2_parts.json benchmarks/results/drqv2_update.json "$OUT/" 2>/dev/null
    timeout 330 python3 benchmarks/drqv2_parts.py --precision bf16 --out "$OUT/drqv2_parts.json"
    timeout 200 python3 benchmarks/drqv2_update.py --precision bf16 --seed-loop on --kernel-grad xla patches --out "$OUT/drqv2_update.json"
    exit 0 ;;
  pixel_smoke)  # issue 12's plan: a few rounds of pixel jobs (JOBS, default pebble_walker) at SEEDS seeds (default 5):
    # compile time, seconds per round (seed steps, the first session, plain updates) and the device's peak memory,
    # whether 5 seeds of a preference job now fit (the fifth session's did not); MAX seconds in all (default 330)
    export PYTHONPATH=/tmp/site:src:benchmarks
    cp benchmarks/results/pixel_smoke.json "$OUT/" 2>/dev/null
    timeout $((${MAX:-330} + 60)) python3 benchmarks/pixel_preference_smoke.py --jobs ${JOBS:-pebble_walker} \
      --seeds "${SEEDS:-5}" --rounds 4 --max-seconds "${MAX:-330}" --out "$OUT/pixel_smoke.json"
    exit 0 ;;
  session_parts)  # issue 12: where a pixel preference session spends its time (benchmarks/pixel_session_parts.py):
    # one epoch of the pixel reward ensemble (BT alone, and with REBEL's term for a rebel job), the relabelling of the
    # replay, and whole sessions of SESSION_COLUMNS columns (default 4; not COLUMNS, the terminal's width) looped and
    # batched (pixel_reward.session_loop), at LABELS stored pairs (default 200) and PRECISIONS (default "tf32 bf16");
    # JOBS (default rebel_cheetah); REPEATS timed calls each (default 1); MAX seconds in all (default 540); rows in
    # $OUT, written as they come
    export PYTHONPATH=/tmp/site:src:benchmarks
    cp benchmarks/results/pixel_session_parts.json "$OUT/" 2>/dev/null
    timeout "${MAX:-540}" python3 benchmarks/pixel_session_parts.py --jobs ${JOBS:-rebel_cheetah} \
      --labels "${LABELS:-200}" --precisions ${PRECISIONS:-tf32 bf16} --columns "${SESSION_COLUMNS:-4}" \
      --repeats "${REPEATS:-1}" --out "$OUT/pixel_session_parts.json"
    exit 0 ;;
  command_buffers)  # the two halves of a walker round, with the H100's command buffers (CUDA graphs) extended to
    # while loops against XLA's default: walker's control step (10 physics substeps of small kernels in while loops:
    # about 12.5 ms at any batch up to 256) at batch 1 and 200 (a 10-column program's training and evaluation envs),
    # and the 10-column bf16 SAC update; about 5 minutes after the install; the rows come back in $OUT
    export PYTHONPATH=/tmp/site:src:benchmarks
    cp benchmarks/results/env_throughput.json benchmarks/results/train_throughput.json "$OUT/" 2>/dev/null
    graphs=--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,CONDITIONAL,WHILE
    for flags in "" "$graphs" "$graphs --xla_gpu_graph_min_graph_size=1"; do
      timeout 60 python3 benchmarks/env_throughput.py throughput --tasks walker_walk --solvers default \
        --batches 1 200 --xla-flags="$flags" --out "$OUT/env_throughput.json" || echo "failed: XLA_FLAGS=$flags"
      timeout 60 python3 benchmarks/train_throughput.py update --seeds 10 --precisions bf16 \
        --xla-flags="$flags" --out "$OUT/train_throughput.json" || echo "failed: XLA_FLAGS=$flags"
    done
    exit 0 ;;
  determinism)  # whether one program run twice from the same seed keys ends in the same state (RESULTS.md: the
    # teacher programs' PEBBLE columns differed before any label), without and with XLA's deterministic GPU ops,
    # and what those cost per round: walker PEBBLE, 5 seeds, bf16, 2 rounds per run (the second with the first
    # session), benchmarks/determinism.py; 494 s with the install on a fresh H100 (fourteenth session); rows in $OUT
    export PYTHONPATH=/tmp/site:src:benchmarks
    cp benchmarks/results/determinism.json "$OUT/" 2>/dev/null
    run=(--preset paper --algo pebble --task walker_walk --labels 100 --seeds 5 --precision bf16)
    for flags in "" "--xla_gpu_deterministic_ops=true"; do
      timeout 270 python3 benchmarks/determinism.py --rounds 2 --xla-flags="$flags" --out "$OUT/determinism.json" \
        -- "${run[@]}" || echo "failed: XLA_FLAGS=$flags"
    done
    exit 0 ;;
  pebble_env40)
    launch pebble_walker_100_utd1_bf16_seed1_env40 --preset paper --algo pebble --task walker_walk --labels 100 --seeds 5 --precision bf16 --seed 1 --num-envs 40
    wait; finish; exit 0 ;;
  pebble500bf16)
    launch pebble_walker_100_utd1_bf16_seed1 --preset paper --algo pebble --task walker_walk --labels 100 --seeds 5 --precision bf16 --seed 1
    wait; finish; exit 0 ;;
esac
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.3
launch pebble_walker_100 --preset paper --algo pebble --task walker_walk --labels 100 --seeds 5 --utd 0.3
launch surf_walker_100 --preset paper --algo surf --task walker_walk --labels 100 --seeds 5 --utd 0.3
launch sac_cheetah_fixed --preset paper --algo sac --task cheetah_run --seeds 5 --num-envs 40 --utd 0.25
wait; finish
