"""Copies finished runs from a device call's run logs into ``results/runs/<group>/``.

Usage:
  python experiments/collect.py SOURCE GROUP [--only NAME ...] [--results results/runs]

SOURCE is a ``runs.tar.gz`` that a device call left under ``$OUT`` (``experiments/baselines_h100.sh``'s
``ship``, or ``gpu_batch.py --out``), or a ``runs/`` directory extracted from one. A run is a directory of
SOURCE holding ``config.json``. Of a finished run (one with ``final.json``) the logs are copied:
``gpu_batch.LOGS``, ``learning_curve.png``, and its stdout as ``stdout.log`` (``<name>.log`` beside the run
directory, as the device script writes it, or ``<name>/stdout.log``, as ``gpu_batch.py`` does). An unfinished run
is listed, not copied. Nothing is overwritten: a run already collected with the same logs is left as it is (its
figure may have been drawn again), and one collected with other logs stops the command (exit status 2) before
anything is copied.

The last lines printed are a table of every run: whether it was copied, its environment steps and its last
evaluation's mean return.
"""

from __future__ import annotations

import argparse
import gzip
import pathlib
import shutil
import sys
import tarfile
import tempfile
import zlib

from gpu_batch import LOGS, run_summary

RESULTS = pathlib.Path(__file__).resolve().parents[1] / "results" / "runs"
FILES = (*LOGS, "learning_curve.png")


def run_files(runs: pathlib.Path, name: str) -> dict[str, pathlib.Path]:
    """The files of run ``name`` under ``runs`` to collect, by their name in the collected directory."""
    run_dir = runs / name
    files = {file: run_dir / file for file in FILES if (run_dir / file).is_file()}
    for log in (runs / f"{name}.log", run_dir / "stdout.log"):
        if log.is_file():
            files["stdout.log"] = log
            break
    return files


def differing(files: dict[str, pathlib.Path], dest: pathlib.Path) -> list[str]:
    """The logs (not the figure, which may have been drawn again since) that ``dest``, a collected run, holds with
    other bytes or lacks."""
    logs = {name: path for name, path in files.items() if name != "learning_curve.png"}
    if not dest.exists():
        return []
    return [
        name
        for name, path in logs.items()
        if not (dest / name).is_file() or (dest / name).read_bytes() != path.read_bytes()
    ]


def collect(runs: pathlib.Path, dest_root: pathlib.Path, only: list[str] | None = None) -> list[tuple[str, str]]:
    """Copies the finished runs under ``runs`` (those named in ``only``, if given) to ``dest_root/<name>``.

    Returns:
      ``(name, what happened)`` per run: ``copied``, ``already collected`` or ``unfinished (not copied)``.

    Raises:
      FileExistsError: if a run was collected before with other logs (nothing is copied then).
      FileNotFoundError: if ``runs`` holds no run, or none of a name in ``only``.
    """
    names = sorted(p.parent.name for p in runs.glob("*/config.json"))
    missing = sorted(set(only or []) - set(names))
    if not names or missing:
        raise FileNotFoundError(f"no run {', '.join(missing) if missing else 'at all'} in {runs}")
    names = [name for name in names if only is None or name in only]
    finished = {name: run_files(runs, name) for name in names if (runs / name / "final.json").is_file()}
    clashes = {name: differing(files, dest_root / name) for name, files in finished.items()}
    clashes = {name: files for name, files in clashes.items() if files}
    if clashes:
        raise FileExistsError(
            "collected before with other logs (move them away first; nothing was copied): "
            + "; ".join(f"{dest_root / name}: {', '.join(files)}" for name, files in clashes.items())
        )
    outcome = []
    for name in names:
        if name not in finished:
            outcome.append((name, "unfinished (not copied)"))
        elif (dest_root / name).exists():
            outcome.append((name, "already collected"))
        else:
            (dest_root / name).mkdir(parents=True)
            for file, path in finished[name].items():
                shutil.copyfile(path, dest_root / name / file)
            outcome.append((name, "copied"))
    return outcome


def _runs_dir(source: pathlib.Path, scratch: pathlib.Path) -> pathlib.Path:
    """SOURCE's ``runs/`` directory, extracted into ``scratch`` when SOURCE is an archive.

    Raises:
      ValueError: if SOURCE is a file but no readable archive.
    """
    if source.is_dir():
        return source
    try:
        with tarfile.open(source) as archive:
            archive.extractall(scratch, filter="data")
    except (tarfile.TarError, EOFError, zlib.error, gzip.BadGzipFile) as err:  # not an archive, or one cut short
        raise ValueError(f"{source} is no readable archive ({type(err).__name__}: {err})") from err
    return scratch / "runs" if (scratch / "runs").is_dir() else scratch


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("source", type=pathlib.Path, help="runs.tar.gz from a device call, or an extracted runs/ directory")
    p.add_argument("group", help="the folder under --results to copy the runs into (e.g. pixels)")
    p.add_argument("--only", nargs="+", default=None, metavar="NAME", help="collect only these runs")
    p.add_argument("--results", type=pathlib.Path, default=RESULTS)
    args = p.parse_args(argv)
    if not args.source.exists():
        p.error(f"{args.source} does not exist")
    with tempfile.TemporaryDirectory() as scratch:
        try:
            runs = _runs_dir(args.source, pathlib.Path(scratch))
            outcome = collect(runs, args.results / args.group, args.only)
        except (ValueError, FileExistsError, FileNotFoundError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        width = max(len(name) for name, _ in outcome)
        print(f"{'run':{width}s} {'':24s} {'env steps':>10s} {'last eval':>10s}")
        for name, what in outcome:
            steps, last = run_summary(runs / name)
            print(f"{name:{width}s} {what:24s} {steps:>10d} {last:>10s}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
