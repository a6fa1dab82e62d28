"""What the checkpoint checksums cost: a save and a restore of a replay-sized state, with and without them.

Usage:
  python benchmarks/checkpoint_checksums.py [--gib 0.25 1 2.1] [--repeats 3] [--dir /tmp/ckpt_bench]

The state is one uint8 leaf of the given size (uniform random bytes, which the checkpoint cannot compress: a
pixel run's 100k-frame replay is 2.1 GB per seed) and a small float leaf. Each row gives the median seconds of
``Checkpointer.save`` (orbax's write, then ``checksums.json``), of ``file_checksums`` alone on the saved step
(the part of the save and of the restore that the checksums add; the files are in the page cache, as right after
a save), and of ``Checkpointer.restore`` of a step with and without ``checksums.json``. They run on the host,
whatever the accelerator, so the ``device`` of a row is the host's CPU.
"""

from __future__ import annotations

import argparse
import pathlib
import platform
import shutil
import statistics
import sys
import time

import jax.numpy as jnp
import numpy as np
from timing import merge_rows, provenance

from rebel_jax.run.checkpoint import CHECKSUMS, Checkpointer, file_checksums

RESULTS = pathlib.Path(__file__).parent / "results" / "checkpoint_checksums.json"


def cpu_name() -> str:
    """The host CPU's model name (``/proc/cpuinfo``), else ``platform.processor()``."""
    cpuinfo = pathlib.Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def _seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def row(gib: float, repeats: int, scratch: pathlib.Path) -> dict:
    rng = np.random.default_rng(0)
    state = {
        "frames": jnp.asarray(rng.integers(0, 256, size=int(gib * 2**30), dtype=np.uint8)),
        "params": jnp.asarray(rng.normal(size=(256, 256)), jnp.float32),
    }
    shutil.rmtree(scratch, ignore_errors=True)
    # Steps without checksums read unchecked, as a run written before they existed.
    ckpt = Checkpointer(scratch / "checkpoints", max_to_keep=repeats + 1, require_checksums=False)
    steps = iter(range(repeats))
    save = _seconds(lambda: ckpt.save(next(steps), state), repeats)
    checked_dir, unchecked_dir = (scratch / "checkpoints" / str(repeats - k) for k in (1, 2))
    checksum = _seconds(lambda: file_checksums(checked_dir), repeats)
    (unchecked_dir / CHECKSUMS).unlink()  # the same state, read unchecked
    restore = {True: [], False: []}
    for _ in range(repeats + 1):  # alternately, the first of each a warm-up (orbax's first restore costs more)
        for checked, step_dir in ((True, checked_dir), (False, unchecked_dir)):
            t0 = time.perf_counter()
            ckpt.restore(state, step=int(step_dir.name))
            restore[checked].append(time.perf_counter() - t0)
    checked, unchecked = (statistics.median(restore[k][1:]) for k in (True, False))
    ckpt.close()
    size = sum(p.stat().st_size for p in checked_dir.rglob("*") if p.is_file())
    shutil.rmtree(scratch)
    return {
        **provenance(),
        "device": cpu_name(),
        "gib": gib,
        "repeats": repeats,
        "save_s": round(save, 3),
        "checksums_s": round(checksum, 3),
        "restore_checked_s": round(checked, 3),
        "restore_unchecked_s": round(unchecked, 3),
        "step_bytes": size,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gib", nargs="+", type=float, default=[0.25, 1.0, 2.1], help="sizes of the uint8 leaf")
    p.add_argument("--repeats", type=int, default=3, help="timed calls of each (at least 2: two steps are restored)")
    p.add_argument("--dir", type=pathlib.Path, default=pathlib.Path("/tmp/ckpt_bench"), help="scratch directory")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    args = p.parse_args()
    if args.repeats < 2:
        p.error("--repeats must be at least 2")
    for gib in args.gib:
        result = row(gib, args.repeats, args.dir)
        print(
            f"{gib:5.2f} GiB: save {result['save_s']:.2f} s (checksums {result['checksums_s']:.2f} s), restore "
            f"{result['restore_checked_s']:.2f} s checked, {result['restore_unchecked_s']:.2f} s unchecked",
            file=sys.stderr,
        )
        merge_rows(args.out, [result], ("device", "commit", "gib"))


if __name__ == "__main__":
    main()
