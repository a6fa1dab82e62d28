"""``--distributed``: one run in 2 processes (``jax.distributed`` on loopback, one CPU device each).

The 2 processes shard the seed axis between them. They must give the run of one process with
the same 2 devices bit for bit (the same per-device program), and the run of one process on one
device within the tolerance of ``test_train``'s sharded test (a batch of 1 and a vmapped batch of
2 round differently). Process 0 alone writes the logs; both write the checkpoints (orbax), and
a checkpoint of either kind resumes in the other. Every subprocess has a deadline, so a hang
fails the test instead of blocking CI.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from test_cli_runs import MICRO_FLAGS, ROOT, ROUNDS, _env, _metrics, _saved_arrays

from rebel_jax.run import cli

DEADLINE = 600
"""Seconds a launch of the training processes may take (a cold compile takes about a minute on 2 cores)."""

# ``python -m rebel_jax.train`` that appends every file-system write it makes under AUDIT_RUN_DIR
# (opened for writing, created, renamed onto, removed) to AUDIT_FILE as ``<operation> <relative path>``.
# Orbax's array data goes through tensorstore (C++) and is not seen; its Python-side files are.
AUDITED_TRAIN = textwrap.dedent(
    """
    import builtins, io, os, runpy, sys

    run_dir = os.path.realpath(os.environ["AUDIT_RUN_DIR"])
    audit = open(os.environ["AUDIT_FILE"], "a", buffering=1)

    def record(operation, path):
        if isinstance(path, str | os.PathLike) and isinstance(os.fspath(path), str):
            path = os.path.realpath(path)
            if path == run_dir or path.startswith(run_dir + os.sep):
                audit.write(f"{operation} {os.path.relpath(path, run_dir)}\\n")

    def audited(operation, function, argument=0, writes=lambda *a, **k: True):
        def wrapper(*args, **kwargs):
            if writes(*args, **kwargs):
                record(operation, args[argument])
            return function(*args, **kwargs)
        return wrapper

    def writes(file, mode="r", *args, **kwargs):
        return any(c in mode for c in "wax+")

    builtins.open = io.open = audited("open", io.open, writes=writes)
    os.replace = audited("replace", os.replace, argument=1)
    os.rename = audited("rename", os.rename, argument=1)
    os.mkdir = audited("mkdir", os.mkdir)
    os.unlink = os.remove = audited("remove", os.unlink)
    os.rmdir = audited("remove", os.rmdir)
    sys.argv[0] = "rebel_jax.train"
    runpy.run_module("rebel_jax.train", run_name="__main__")
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _xla_flags(devices: int) -> str:
    """This process's XLA_FLAGS (conftest's jaxlib deadlock workaround) with ``devices`` CPU devices."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if "xla_force_host_platform_device_count" not in f]
    return " ".join([*flags, f"--xla_force_host_platform_device_count={devices}"])


def _train(run_dir: pathlib.Path, processes: int, devices: int, *flags: str) -> list[list[str]]:
    """Runs the micro run in ``processes`` processes with ``devices`` CPU devices each; their audits.

    Returns:
      For each process, the writes it made under ``run_dir`` (see :data:`AUDITED_TRAIN`).
    """
    cmd = [sys.executable, "-c", AUDITED_TRAIN, *MICRO_FLAGS, "--run-dir", str(run_dir), *flags]
    audits = [run_dir.parent / f"{run_dir.name}.{time.monotonic_ns()}.audit{i}" for i in range(processes)]
    logs = [audit.with_suffix(".log") for audit in audits]
    port = _free_port()
    procs = []
    for i in range(processes):
        env = _env(
            JAX_PLATFORMS="cpu",
            XLA_FLAGS=_xla_flags(devices),
            AUDIT_RUN_DIR=str(run_dir),
            AUDIT_FILE=str(audits[i]),
        )
        if processes > 1:
            cmd_i = [*cmd, "--distributed"]
            address = f"127.0.0.1:{port}"  # Process 0 listens there only (JAX's default: every interface).
            env.update(JAX_COORDINATOR_ADDRESS=address, JAX_COORDINATOR_BIND_ADDRESS=address)
            env.update(JAX_NUM_PROCESSES=str(processes), JAX_PROCESS_ID=str(i))
        else:
            cmd_i = cmd
        with open(logs[i], "w") as log:
            procs.append(subprocess.Popen(cmd_i, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT))
    deadline = time.monotonic() + DEADLINE
    try:
        # Until all have ended, or one failed (the others would wait for it until JAX's timeouts).
        while any(proc.poll() is None for proc in procs) and not any(proc.poll() for proc in procs):
            if time.monotonic() > deadline:
                log = logs[0].read_text()[-3000:]
                pytest.fail(f"the run did not end within {DEADLINE} s; log of process 0:\n{log}")
            time.sleep(0.2)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    codes = [proc.returncode for proc in procs]
    if any(codes):
        failed = [i for i, code in enumerate(codes) if code not in (0, -signal.SIGKILL)]  # not killed here
        first = (failed or [i for i, code in enumerate(codes) if code])[0]
        log = logs[first].read_text()[-3000:]
        pytest.fail(f"exit statuses {codes} (-9: killed once another failed); log of process {first}:\n{log}")
    return [audit.read_text().splitlines() if audit.exists() else [] for audit in audits]


def _final(run_dir: pathlib.Path) -> dict:
    return json.loads((run_dir / "final.json").read_text())


def _assert_close_per_seed(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    """``test_train``'s tolerance for a sharded run against a vmapped one: 5% relative norm per seed and leaf."""
    assert a.keys() == b.keys() and len(a) > 50
    for k in a:
        for i in range(a[k].shape[0]):
            x, y = np.asarray(a[k][i], np.float64), np.asarray(b[k][i], np.float64)
            assert np.linalg.norm(x - y) <= 5e-2 * max(np.linalg.norm(y), 1e-6), (k, i, x, y)


def _assert_same_run(a: pathlib.Path, b: pathlib.Path) -> None:
    """The same metrics (but timings), final evaluation and last checkpoint, bit for bit."""
    assert _metrics(a) == _metrics(b)
    assert _final(a) == _final(b)
    saved_a, saved_b = _saved_arrays(a, ROUNDS), _saved_arrays(b, ROUNDS)
    assert saved_a.keys() == saved_b.keys() and len(saved_a) > 50
    for k in saved_a:
        np.testing.assert_array_equal(saved_a[k], saved_b[k], err_msg=f"leaf {k}")


def _killed_before_last_checkpoint(run_dir: pathlib.Path, copy: pathlib.Path) -> pathlib.Path:
    """A copy of a whole run as a kill after logging its last round leaves it: no last checkpoint, no final.json."""
    shutil.copytree(run_dir, copy)
    shutil.rmtree(copy / "checkpoints" / str(ROUNDS))
    (copy / "final.json").unlink()
    return copy


@pytest.fixture(scope="module")
def two(tmp_path_factory) -> tuple[pathlib.Path, list[list[str]]]:
    """A whole run in 2 processes (1 device each), and what each process wrote in its directory."""
    run_dir = tmp_path_factory.mktemp("two") / "run"
    return run_dir, _train(run_dir, 2, 1)


@pytest.fixture(scope="module")
def same_devices(tmp_path_factory) -> pathlib.Path:
    """The same run in 1 process with 2 devices."""
    run_dir = tmp_path_factory.mktemp("same_devices") / "run"
    _train(run_dir, 1, 2)
    return run_dir


@pytest.fixture(scope="module")
def one_device(tmp_path_factory) -> pathlib.Path:
    """The same run in this process, on one device (``test_cli_runs``' whole run: its compiled round)."""
    run_dir = tmp_path_factory.mktemp("one_device") / "run"
    cli.main([*MICRO_FLAGS, "--run-dir", str(run_dir)])
    return run_dir


@pytest.mark.heavy  # make test-heavy: 2 CLI processes, about 100 s on 2 cores with the test below
def test_two_processes_equal_one_process_and_only_process_0_writes_logs(two, same_devices, one_device):
    run_dir, (audit0, audit1) = two
    written = {line.split(" ", 1)[1] for line in audit0}
    assert {"config.json", "meta.json", "metrics.jsonl", "final.json"} <= written
    assert all(line.split(" ", 1)[1].startswith("checkpoints") for line in audit1), audit1
    meta = json.loads((run_dir / "meta.json").read_text())
    assert meta["processes"] == 2 and len(meta["devices"]) == 2
    assert [row["round"] for row in _metrics(run_dir)] == list(range(ROUNDS))  # one writer: one row per round
    assert sorted(int(p.name) for p in (run_dir / "checkpoints").iterdir()) == [ROUNDS - 1, ROUNDS]

    # One process with the same 2 devices: the same per-device program, so the same run.
    _assert_same_run(run_dir, same_devices)

    # One device (every seed in one vmapped batch): within the sharded test's tolerance.
    _assert_close_per_seed(_saved_arrays(run_dir, ROUNDS), _saved_arrays(one_device, ROUNDS))
    returns = np.array(_final(run_dir)["final_eval_return"])
    reference = np.array(_final(one_device)["final_eval_return"])
    np.testing.assert_allclose(returns, reference, rtol=5e-2, atol=1e-3)


@pytest.mark.heavy
def test_checkpoints_resume_across_process_and_device_counts(two, same_devices, one_device, tmp_path):
    whole, _ = two
    # Saved by 2 processes, resumed by 1 process on the same 2 devices: the uninterrupted run.
    two_then_one = _killed_before_last_checkpoint(whole, tmp_path / "two_then_one")
    _train(two_then_one, 1, 2, "--resume")
    _assert_same_run(whole, two_then_one)
    assert json.loads((two_then_one / "meta.json").read_text())["resumed"][0]["from_round"] == ROUNDS - 1

    # Saved by 1 process, resumed by 2: the uninterrupted run; only process 0 writes the logs.
    one_then_two = _killed_before_last_checkpoint(same_devices, tmp_path / "one_then_two")
    _, audit1 = _train(one_then_two, 2, 1, "--resume")
    _assert_same_run(whole, one_then_two)
    assert all(line.split(" ", 1)[1].startswith("checkpoints") for line in audit1), audit1

    # Saved by 2 processes, resumed on 1 device (the arrays restored into another sharding): the
    # 2-process rounds as logged, then the last round within the 1-device run's tolerance.
    on_one_device = _killed_before_last_checkpoint(whole, tmp_path / "two_then_one_device")
    cli.main([*MICRO_FLAGS, "--run-dir", str(on_one_device), "--resume"])
    assert _metrics(on_one_device)[: ROUNDS - 1] == _metrics(whole)[: ROUNDS - 1]
    assert [row["round"] for row in _metrics(on_one_device)] == list(range(ROUNDS))
    _assert_close_per_seed(_saved_arrays(on_one_device, ROUNDS), _saved_arrays(one_device, ROUNDS))


@pytest.mark.heavy  # make test-heavy: 2 processes compiling a walker run, a few minutes on 2 cores
def test_two_processes_run_an_mjx_task(tmp_path):
    """Each process builds MJX's model on its own device: ``jax.devices()[0]`` is process 0's, unreadable by 1."""
    run_dir = tmp_path / "run"
    _train(run_dir, 2, 1, "--task", "walker_walk", "--video-steps", "0")
    assert len(_final(run_dir)["final_eval_return"]) == 2
    assert [row["round"] for row in _metrics(run_dir)] == list(range(ROUNDS))


def _first_column(rows: list[dict]) -> list[dict]:
    """Each row's per-seed lists cut to their first seed, without the means over the seeds."""
    return [{k: v[:1] if isinstance(v, list) else v for k, v in row.items() if not k.endswith("_mean")} for row in rows]


@pytest.mark.heavy  # make test-heavy: 2 CLI processes, then a resume, about a minute on 2 cores
def test_seeds_that_do_not_split_over_the_devices_are_padded_and_dropped(same_devices, tmp_path):
    # 1 seed over 2 processes of one device each: the seed and a padding copy of it, one per device.
    run_dir = tmp_path / "run"
    _train(run_dir, 2, 1, "--seeds", "1")
    meta = json.loads((run_dir / "meta.json").read_text())
    assert (meta["columns"], meta["device_columns"]) == (1, 2)
    # Seed 0 runs the per-device program of the 2-seed run on 2 devices, with seed 0's key: the same numbers.
    assert _first_column(_metrics(run_dir)) == _first_column(_metrics(same_devices))
    for row in _metrics(run_dir):  # the padding is left out of the means
        assert all(row[f"{k}_mean"] == row[k][0] for k in row if f"{k}_mean" in row and row[k][0] is not None), row
    assert _final(run_dir)["final_eval_return"] == _final(same_devices)["final_eval_return"][:1]
    # Its checkpoints hold both columns; one device resumes them as they are.
    resumed = _killed_before_last_checkpoint(run_dir, tmp_path / "resumed")
    cli.main([*MICRO_FLAGS, "--seeds", "1", "--run-dir", str(resumed), "--resume"])
    assert [row["round"] for row in _metrics(resumed)] == list(range(ROUNDS))
    assert len(_final(resumed)["final_eval_return"]) == 1
    assert {np.shape(x)[0] for x in _saved_arrays(resumed, ROUNDS).values() if np.ndim(x)} == {2}
