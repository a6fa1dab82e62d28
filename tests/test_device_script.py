"""``experiments/baselines_h100.sh``: every set's training command parses, before any device time is spent.

The script runs here with ``python3`` and ``setsid`` replaced by a stub that records its arguments, so no
training starts; each recorded ``python3 -m rebel_jax.train`` command line then goes through the CLI's own
parser (``cli.parse``), which rejects unknown flags, bad values and bad combinations.
"""

from __future__ import annotations

import importlib
import os
import pathlib
import re
import shlex
import signal
import subprocess
import sys
import time

import pytest

from rebel_jax import cli, teachers

SCRIPT = pathlib.Path(__file__).parents[1] / "experiments" / "baselines_h100.sh"
STUB = """#!/usr/bin/env bash
[ "$1" = -c ] && exec "$REAL_PYTHON" "$@"  # python3 -c: a set reading its flags from Python runs it for real
[ "$1" = python3 ] && shift  # setsid python3 ...
printf '%s\\n' "$(printf '%q ' "$@")" >>"$CALLS"
printf '%s\\t%s\\n' "${CUDA_VISIBLE_DEVICES-all}" "$(printf '%q ' "$@")" >>"$CALLS.gpu"  # the GPUs it may see
case "$*" in *rebel_jax.train*) [ -n "${STUB_SECONDS:-}" ] && sleep "$STUB_SECONDS" ;; esac  # a job that runs a while
"""
SETS = [  # (SET, environment): the sets the script documents, with the variables each needs
    ("rebel_ablation", {"LAMS": "0.001 -0.001"}),
    ("rebel_ablation", {"LAMS": "0.1 -0.1", "FORM": "penalty", "NORMALIZE": "1"}),
    ("rebel_ablation", {"LAMS": "0.001 0.01", "SOURCE": "replay", "OUTPUT": "sigmoid"}),
    ("rebel_cheetah", {"LAM": "0.001"}),
    ("rebel_teacher", {"LAM": "0.001", "TEACHER": "mistake"}),
    ("rebel_walker", {"LAM": "0.01"}),
    ("drqv2_seed", {"TASK": "walker", "SEED": "0", "PRECISION": "bf16"}),
    ("drqv2_seed", {"TASK": "cheetah", "SEED": "1"}),
    ("drqv2_seed", {"TASK": "walker", "SEED": "3", "SEEDS": "2", "ENVS": "20", "PRECISION": "bf16"}),
    ("drqv2_seed", {"TASK": "walker", "SEED": "10", "SEEDS": "8", "STEPS": "60000", "PRECISION": "tf32"}),
    (
        "drqv2_seed",
        {"TASK": "walker", "SEED": "10", "SEEDS": "8", "STEPS": "60000", "PRECISION": "bf16", "CRITIC_F32": "1"},
    ),
    ("pixel_seed", {"ALGO": "surf", "TASK": "cheetah", "SEED": "2", "STEPS": "500000", "CAPACITY": "500000"}),
    ("pixel_seed", {"ALGO": "rebel", "TASK": "walker", "SEED": "0", "STEPS": "250000", "PRECISION": "bf16"}),
    (
        "pixel_seed",
        {"ALGO": "pebble", "TASK": "walker", "SEED": "1", "STEPS": "250000", "ENVS": "20", "SEED_STEPS": "10000"},
    ),
    ("pixel_seed", {"ALGO": "pebble", "TASK": "cheetah", "SEED": "0", "SEEDS": "3", "STEPS": "250000"}),
    ("pixel_seed", {"ALGO": "surf", "TASK": "cheetah", "SEED": "2", "SEEDS": "2", "STEPS": "150000", "SURF_ADAM": "1"}),
    ("pixel_seed", {"ALGO": "surf", "TASK": "cheetah", "SEED": "4", "STEPS": "250000", "REWARD_BF16": "1"}),
    (
        "pixel_seed",
        {"ALGO": "rebel", "TASK": "cheetah", "SEED": "0", "SEEDS": "2", "STEPS": "250000", "LAMS": "0 0.001"},
    ),
    ("surf_cheetah_ru", {"RU": "100"}),
    *[("ladder", {"RUNG": str(rung)}) for rung in range(4)],
    *[(name, {}) for name in ("pebble500", "surf500", "surf500bf16", "pebble500bf16", "pebble1000")],
    *[(name, {}) for name in ("pebble_cheetah1m", "surf_cheetah1m", "shared")],
]


def _stubbed(tmp_path: pathlib.Path, env: dict[str, str], detach: bool) -> tuple[pathlib.Path, dict[str, str]]:
    """A working directory and the environment that runs the script with ``python3`` and ``setsid`` stubbed
    (``STUB``), recording into ``tmp_path / "calls.txt"`` and shipping into ``tmp_path`` as ``$OUT``."""
    bin_dir, work = tmp_path / "bin", tmp_path / "work"
    bin_dir.mkdir(exist_ok=True)
    work.mkdir(exist_ok=True)
    for tool in ("python3", "setsid"):
        (bin_dir / tool).write_text(STUB)
        (bin_dir / tool).chmod(0o755)
    calls = tmp_path / "calls.txt"
    calls.unlink(missing_ok=True)
    full_env = {
        **{k: v for k, v in os.environ.items() if k not in ("LAMS", "LAM", "DETACH")},
        "PATH": f"{bin_dir}:{os.environ['PATH']}",
        "CALLS": str(calls),
        "REAL_PYTHON": sys.executable,
        "OUT": str(tmp_path),
        **env,
        **({"DETACH": "1"} if detach else {}),
    }
    return work, full_env


def _commands(
    tmp_path: pathlib.Path, name: str, env: dict[str, str], detach: bool, program: str = "rebel_jax.train"
) -> list[list[str]]:
    """The argument lists the script passes to ``python3`` that name ``program`` (pip's install left out)."""
    work, full_env = _stubbed(tmp_path, env, detach)
    calls = tmp_path / "calls.txt"
    # LIMIT 20: the detached sets' watch loop (until the call's limit - 20 s) ends at once.
    done = subprocess.run(["bash", str(SCRIPT), "20", name], cwd=work, env=full_env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    for _ in range(100):  # WATCH=0 returns as soon as it starts its job: wait for the job's stub to record it
        if env.get("WATCH") != "0" or (calls.exists() and program in calls.read_text()):
            break
        time.sleep(0.1)
    lines = calls.read_text().splitlines() if calls.exists() else []
    return [shlex.split(line) for line in lines if program in line]


@pytest.mark.parametrize(("name", "env"), SETS, ids=[f"{n}-{'-'.join(e.values()) or 'default'}" for n, e in SETS])
def test_every_set_of_the_device_script_passes_a_command_the_cli_accepts(tmp_path, name, env):
    detach = name in ("rebel_ablation", "rebel_cheetah", "rebel_teacher", "drqv2_seed", "pixel_seed")
    commands = _commands(tmp_path, name, env, detach)
    assert commands, f"{name}: no training command"
    for argv in commands:
        assert argv[:2] == ["-m", "rebel_jax.train"], argv
        args = cli.parse(argv[2:])
        run_dir = pathlib.Path(argv[argv.index("--run-dir") + 1])
        assert run_dir.parent == pathlib.Path("runs")
        if name.startswith("rebel_"):
            assert args.config.algo == "rebel"
        if "LAMS" in env:
            assert args.lams == tuple(float(lam) for lam in env["LAMS"].split())
            assert args.columns == args.seeds * len(args.lams)
            prefix = "rebel_walker_100" if name == "rebel_ablation" else f"rebel_{env.get('TASK')}_pixels"
            assert run_dir.name.startswith(prefix) and "_lams_" + env["LAMS"].replace(" ", "_") in run_dir.name
        if "TEACHER" in env:
            assert args.config.teacher == teachers.PRESETS[env["TEACHER"]] and env["TEACHER"] in run_dir.name
        if detach:
            assert args.checkpoint_every == 0 and args.video_steps == 0  # nothing that cannot leave the machine
        if name == "pixel_seed":  # pixel_memory.CONFIGS' run, at STEPS, one seed, the replay CAPACITY
            task = {"walker": "walker_walk_pixels", "cheetah": "cheetah_run_pixels"}[env["TASK"]]
            assert (args.config.algo, args.config.env.task) == (env["ALGO"], task)
            assert (args.seeds, args.config.train.seed, args.config.train.total_steps) == (
                int(env.get("SEEDS", 1)),
                int(env["SEED"]),
                int(env["STEPS"]),
            )
            assert ("SEEDS" in env) == bool(re.search(r"_seeds\d", run_dir.name))  # not "_seedsteps"
            assert args.config.train.buffer_capacity == int(env.get("CAPACITY", 0))
            assert args.config.env.num_envs == int(env.get("ENVS", 4))  # the preset's unless ENVS
            assert args.config.train.seed_steps == int(env.get("SEED_STEPS", 2_000))
            assert ("ENVS" in env) == ("_envs" in run_dir.name)
            assert args.config.pixel_reward.per_member_adam == ("SURF_ADAM" in env) == ("_surfadam" in run_dir.name)
            reward_bf16 = args.config.pixel_reward.precision == "bf16"
            assert reward_bf16 == ("REWARD_BF16" in env) == run_dir.name.endswith("_rbf16")
            assert args.config.query.sampling == "uniform"
        if name == "drqv2_seed":  # SEEDS seeds (default 1) from SEED, ENVS envs each (default 10), 500k frames
            assert (args.config.algo, args.seeds, args.config.train.seed) == (
                "drqv2",
                int(env.get("SEEDS", 1)),
                int(env["SEED"]),
            )
            steps = int(env.get("STEPS", 250_000))
            assert (args.config.env.num_envs, args.config.train.total_steps) == (int(env.get("ENVS", 10)), steps)
            assert run_dir.name.startswith(f"drqv2_{env['TASK']}_{2 * steps // 1000}kframes_seed{env['SEED']}")
            assert args.config.drqv2.precision == env.get("PRECISION", "tf32")
            assert args.config.drqv2.critic_out_f32 == ("CRITIC_F32" in env) == run_dir.name.endswith("_qf32")
            assert ("SEEDS" in env) == bool(re.search(r"_seeds\d", run_dir.name))
            assert ("ENVS" in env) == ("_envs" in run_dir.name)
            assert args.config.pixel_reward.per_member_adam == ("SURF_ADAM" in env) == ("_surfadam" in run_dir.name)
            assert args.config.drqv2.batch_size == (512 if env["TASK"] == "walker" else 256)


def _gpus(tmp_path: pathlib.Path) -> dict[str, str]:
    """Each recorded training command's run directory -> the GPUs it could see (``STUB``'s ``calls.txt.gpu``)."""
    out = {}
    for line in (tmp_path / "calls.txt.gpu").read_text().splitlines():
        gpu, command = line.split("\t")
        argv = shlex.split(command)
        if "rebel_jax.train" in argv:
            out[argv[argv.index("--run-dir") + 1]] = gpu
    return out


def test_one_call_starts_a_detached_job_per_gpu_and_the_last_script_ships_every_log(tmp_path):
    walker = {"TASK": "walker", "SEED": "0", "PRECISION": "bf16"}
    cheetah = {"ALGO": "rebel", "TASK": "cheetah", "LAMS": "0 0.001", "SEED": "0", "SEEDS": "2", "STEPS": "150000"}
    (first,) = _commands(tmp_path, "drqv2_seed", walker | {"GPU": "0", "WATCH": "0"}, detach=True)
    assert not (tmp_path / "runs.tar.gz").exists()  # WATCH=0 starts its job and returns: nothing shipped yet
    (second,) = _commands(tmp_path, "pixel_seed", cheetah | {"GPU": "1"}, detach=True)
    gpus = _gpus(tmp_path)
    assert [gpus[argv[argv.index("--run-dir") + 1]] for argv in (first, second)] == ["0", "1"]
    listed = subprocess.run(["tar", "tzf", tmp_path / "runs.tar.gz"], capture_output=True, text=True, check=True)
    logs = {pathlib.Path(name).name for name in listed.stdout.split() if name.endswith(".log")}
    names = {pathlib.Path(argv[argv.index("--run-dir") + 1]).name + ".log" for argv in (first, second)}
    assert logs == names  # the last script's watch ships both jobs' logs


def test_the_four_gpu_plan_starts_one_planned_job_per_gpu_and_ships_all_their_logs(tmp_path):
    # The caller's variables must not reach the planned jobs. Each stubbed job lives 1 s, so that the last watch
    # (LIMIT 45) waits for all four, as on the device, before it ships their logs.
    env = {"SEEDS": "5", "LAMS": "0.1", "ENVS": "40", "STUB_SECONDS": "1"}
    work, full_env = _stubbed(tmp_path, env, detach=False)
    done = subprocess.run(["bash", str(SCRIPT), "45", "four_gpu_plan"], cwd=work, env=full_env, capture_output=True)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = (tmp_path / "calls.txt").read_text().splitlines()
    commands = [shlex.split(line) for line in lines if "rebel_jax.train" in line]
    planned = {
        "runs/drqv2_walker_500kframes_seed21_bf16_qf32": "0",
        "runs/surf_cheetah_pixels_150000steps_seed6_seeds2_bf16": "1",
        "runs/rebel_cheetah_pixels_150000steps_seed8_seeds2_lams_0_0.001_bf16": "2",
        "runs/rebel_walker_pixels_250000steps_seed0_lams_0_0.001_envs20_seedsteps10000_bf16": "3",
    }
    assert _gpus(tmp_path) == planned
    for argv in commands:
        args = cli.parse(argv[2:])
        assert args.checkpoint_every == 0 and args.config.drqv2.precision == "bf16"
        assert args.seeds == (2 if "_seeds2" in argv[argv.index("--run-dir") + 1] else 1)
    walker = cli.parse(next(a for a in commands if "runs/rebel_walker" in " ".join(a))[2:])
    assert (walker.config.env.num_envs, walker.config.train.seed_steps, walker.lams) == (20, 10_000, (0.0, 0.001))
    listed = subprocess.run(["tar", "tzf", tmp_path / "runs.tar.gz"], capture_output=True, text=True, check=True)
    logs = {name for name in listed.stdout.split() if name.endswith(".log")}
    assert logs == {f"{run}.log" for run in planned}  # the last job's watch ships all four
    (tmp_path / "bin" / "nvidia-smi").write_text("#!/usr/bin/env bash\necho 'GPU 0: NVIDIA H100'\n")
    (tmp_path / "bin" / "nvidia-smi").chmod(0o755)
    refused = subprocess.run(["bash", str(SCRIPT), "45", "four_gpu_plan"], cwd=work, env=full_env, capture_output=True)
    assert refused.returncode == 1 and b"needs 4 GPUs, this machine has 1" in refused.stdout


def test_a_carried_compilation_cache_seeds_the_machines_cache_once(tmp_path):
    work, env = _stubbed(tmp_path, {"TASK": "walker", "SEED": "0"}, detach=True)
    (work / ".gpu_cache").mkdir()
    (work / ".gpu_cache" / "entry").write_text("carried")
    for call in range(2):  # the first call of a machine, then a chained one
        done = subprocess.run(["bash", str(SCRIPT), "20", "drqv2_seed"], cwd=work, env=env, capture_output=True)
        assert done.returncode == 0 and b"cp:" not in done.stderr, done.stderr[-2000:]
        assert (work / "runs" / ".jax_cache" / "entry").read_text() == ("carried" if call == 0 else "compiled")
        (work / "runs" / ".jax_cache" / "entry").write_text("compiled")  # the job's own entry, kept by the next call


WALKER_PLANS = {
    "walker_pixel_plan": [("rebel", 1), ("rebel", 2), ("rebel", 3), ("surf", 0)],
    "walker_pixel_last": [("rebel", 4), ("surf", 1), ("surf", 2), ("surf", 3)],
}


@pytest.mark.parametrize("plan", sorted(WALKER_PLANS))
def test_the_walker_pixel_plans_run_their_pebble_rebel_and_surf_keys_one_per_gpu_at_the_issues_length(tmp_path, plan):
    work, full_env = _stubbed(tmp_path, {"SEED": "9", "ALGO": "drqv2", "STUB_SECONDS": "1"}, detach=False)
    done = subprocess.run(["bash", str(SCRIPT), "45", plan], cwd=work, env=full_env, capture_output=True)
    assert done.returncode == 0, done.stderr[-2000:]
    tail = "_envs20_seedsteps10000_bf16"
    names = {
        "rebel": "runs/rebel_walker_pixels_250000steps_seed{}_lams_0_0.001" + tail,
        "surf": "runs/surf_walker_pixels_250000steps_seed{}" + tail,
    }
    planned = {names[algo].format(key): str(gpu) for gpu, (algo, key) in enumerate(WALKER_PLANS[plan])}
    assert _gpus(tmp_path) == planned
    lines = (tmp_path / "calls.txt").read_text().splitlines()
    for argv in (shlex.split(line) for line in lines if "rebel_jax.train" in line):
        args = cli.parse(argv[2:])
        run = argv[argv.index("--run-dir") + 1]
        assert args.config.env.task == "walker_walk_pixels" and args.config.train.total_steps == 250_000
        assert (args.config.env.num_envs, args.config.train.seed_steps, args.seeds) == (20, 10_000, 1)
        assert args.config.algo == ("surf" if "surf_" in run else "rebel")
        assert args.lams == ((0.0,) if "surf_" in run else (0.0, 0.001))  # SURF: its one lambda, unused
    listed = subprocess.run(["tar", "tzf", tmp_path / "runs.tar.gz"], capture_output=True, text=True, check=True)
    assert {name for name in listed.stdout.split() if name.endswith(".log")} == {f"{run}.log" for run in planned}


@pytest.mark.parametrize("pgrep", ["real", "blind"])
def test_a_watching_call_ships_the_logs_while_its_job_runs_so_a_call_ended_early_keeps_them(tmp_path, pgrep):
    """The device ends a call at its ``limit_s``, which the device time left may put below the script's LIMIT:
    the logs shipped during the watch come back even though ``finish`` never ran. With pgrep blind (as it is to a
    job forked but not yet exec'd, whose command line is still the script's), the watch follows the job it started
    by its PID."""
    job = {"TASK": "walker", "SEED": "21", "PRECISION": "bf16", "SHIP_EVERY": "1", "STUB_SECONDS": "60"}
    work, env = _stubbed(tmp_path, job, detach=True)
    if pgrep == "blind":
        (tmp_path / "bin" / "pgrep").write_text("#!/usr/bin/env bash\nexit 1\n")
        (tmp_path / "bin" / "pgrep").chmod(0o755)
    call = subprocess.Popen(["bash", str(SCRIPT), "300", "drqv2_seed"], cwd=work, env=env, start_new_session=True)
    shipped = tmp_path / "runs.tar.gz"
    try:
        for _ in range(300):
            if shipped.exists() or call.poll() is not None:
                break
            time.sleep(0.1)
        assert call.poll() is None, "the watch ended before its job did"
        assert shipped.exists(), "nothing shipped while the job ran"
    finally:
        os.killpg(call.pid, signal.SIGKILL)  # as the device ends a call: the script, its job and its watch
        call.wait()
    listed = subprocess.run(["tar", "tzf", shipped], capture_output=True, text=True, check=True).stdout.split()
    assert "runs/drqv2_walker_500kframes_seed21_bf16.log" in listed
    assert not (tmp_path / "runs.tar.gz.part").exists()


def test_the_drqv2_bench_set_passes_arguments_its_benchmarks_accept(tmp_path, monkeypatch):
    benchmarks = SCRIPT.parents[1] / "benchmarks"
    monkeypatch.syspath_prepend(str(benchmarks))
    commands = _commands(tmp_path, "drqv2_bench", {}, detach=False, program="benchmarks/")
    assert [argv[0] for argv in commands] == ["benchmarks/drqv2_parts.py", "benchmarks/drqv2_update.py"]
    for argv in commands:
        module = importlib.import_module(pathlib.Path(argv[0]).stem)
        args = module.parser().parse_args(argv[1:])
        assert args.precision == "bf16"
        assert args.out.parent == tmp_path  # $OUT: the rows come back from the device
    assert args.seed_loop == ["on"] and args.kernel_grad == ["xla", "patches"]


def test_the_command_buffers_set_times_walker_and_the_update_with_and_without_cuda_graphs(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPT.parents[1] / "benchmarks"))
    commands = _commands(tmp_path, "command_buffers", {}, detach=False, program="benchmarks/")
    scripts = ["benchmarks/env_throughput.py", "benchmarks/train_throughput.py"]
    assert [argv[0] for argv in commands] == scripts * 3
    runs = [importlib.import_module(pathlib.Path(argv[0]).stem).parser().parse_args(argv[1:]) for argv in commands]
    for env, update in zip(runs[::2], runs[1::2], strict=True):
        assert (env.mode, env.tasks, env.solvers, env.batches) == ("throughput", ["walker_walk"], ["default"], [1, 200])
        assert (update.mode, update.seeds, update.precisions) == ("update", [10], ["bf16"])
        assert env.xla_flags == update.xla_flags
        assert (env.out, update.out) == (tmp_path / "env_throughput.json", tmp_path / "train_throughput.json")
    default, graphs, small = (a.xla_flags for a in runs[::2])
    assert default == "" and "WHILE" in graphs.split("=")[1].split(",") and small.startswith(graphs + " ")


@pytest.mark.parametrize(
    ("env", "jobs", "seeds", "seconds"),
    [({}, ["pebble_walker"], 5, 330.0), ({"JOBS": "drqv2_walker surf_cheetah", "SEEDS": "1", "MAX": "200"},
                                          ["drqv2_walker", "surf_cheetah"], 1, 200.0)],
)  # fmt: skip
def test_the_pixel_smoke_set_passes_its_jobs_seeds_and_time_cap(tmp_path, monkeypatch, env, jobs, seeds, seconds):
    monkeypatch.syspath_prepend(str(SCRIPT.parents[1] / "benchmarks"))
    commands = _commands(tmp_path, "pixel_smoke", env, detach=False, program="benchmarks/")
    assert [argv[0] for argv in commands] == ["benchmarks/pixel_preference_smoke.py"]
    args = importlib.import_module("pixel_preference_smoke").parser().parse_args(commands[0][1:])
    assert (args.jobs, args.seeds, args.max_seconds, args.rounds) == (jobs, seeds, seconds, 4)
    assert args.out == tmp_path / "pixel_smoke.json"


def test_the_session_parts_set_times_both_precisions_of_its_jobs(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPT.parents[1] / "benchmarks"))
    parse = importlib.import_module("pixel_session_parts").parser().parse_args
    default = parse(_commands(tmp_path, "session_parts", {}, detach=False, program="benchmarks/")[0][1:])
    assert (default.jobs, default.labels, default.precisions) == (["rebel_cheetah"], 200, ["tf32", "bf16"])
    assert (default.columns, default.session_loops, default.repeats) == (4, ["on", "off"], 1)
    env = {"JOBS": "rebel_walker surf_cheetah", "LABELS": "100", "PRECISIONS": "bf16", "SESSION_COLUMNS": "2"}
    commands = _commands(tmp_path, "session_parts", env, detach=False, program="benchmarks/")
    assert [argv[0] for argv in commands] == ["benchmarks/pixel_session_parts.py"]
    args = parse(commands[0][1:])
    assert (args.jobs, args.labels, args.precisions, args.columns) == (
        ["rebel_walker", "surf_cheetah"],
        100,
        ["bf16"],
        2,
    )
    assert args.out == tmp_path / "pixel_session_parts.json"


def test_the_determinism_set_runs_one_walker_program_twice_without_and_with_deterministic_ops(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPT.parents[1] / "benchmarks"))
    commands = _commands(tmp_path, "determinism", {}, detach=False, program="benchmarks/")
    assert [argv[0] for argv in commands] == ["benchmarks/determinism.py"] * 2
    runs = [importlib.import_module("determinism").parser().parse_args(argv[1:]) for argv in commands]
    assert [a.xla_flags for a in runs] == ["", "--xla_gpu_deterministic_ops=true"]
    for a in runs:
        assert a.rounds == 2 and a.out == tmp_path / "determinism.json"
        args = cli.parse(a.flags)
        assert (args.config.algo, args.config.env.task, args.seeds, args.config.sac.precision) == (
            "pebble",
            "walker_walk",
            5,
            "bf16",
        )


def test_a_set_without_its_variable_stops_with_its_name(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "python3").write_text("#!/usr/bin/env bash\n")
    (bin_dir / "python3").chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k not in ("LAMS", "LAM")} | {
        "PATH": f"{bin_dir}:{os.environ['PATH']}"
    }
    done = subprocess.run(
        ["bash", str(SCRIPT), "20", "rebel_cheetah"],
        cwd=tmp_path,
        env=env | {"OUT": str(tmp_path)},
        capture_output=True,
        text=True,
    )
    assert done.returncode != 0 and "set LAM" in done.stderr
