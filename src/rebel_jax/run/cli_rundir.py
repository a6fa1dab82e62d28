"""The run directory of a command-line run: its checks before anything is written, ``config.json`` and
``meta.json``, and what ``--resume`` compares and keeps."""

from __future__ import annotations

import datetime
import importlib.metadata
import json
import os
import pathlib
import shlex
import shutil
import subprocess
import sys
import time

import jax

from rebel_jax.config import Config, ConfigError, to_dict
from rebel_jax.run import compile_cache, rundir
from rebel_jax.run.cli_args import Args, swept_knob
from rebel_jax.run.human import redact_token
from rebel_jax.run.logging import write_json
from rebel_jax.train import placement

RUN_FILES = (
    "config.json",
    "meta.json",
    "metrics.jsonl",
    "final.json",
    "checkpoints",
    "checkpoints_damaged",
    "tb",
    "learning_curve.png",
    "eval.gif",
)
"""What a run writes in its directory (other files there, such as a caller's log, are left alone)."""


PACKAGE_DIR = pathlib.Path(__file__).resolve().parent
"""The package's own source directory: its repository (if any) is the code that runs, whatever the caller's."""


def _git_commit(package_dir: pathlib.Path = PACKAGE_DIR) -> str | None:
    """The commit of the code that runs: ``REBEL_JAX_GIT_COMMIT`` where set (a tree copied without its history),
    else the commit of the repository that tracks the package's own source (``git -C <package dir>``, never the
    caller's working directory), else the installed distribution's version (``installed 0.1.0``), else None."""
    if os.environ.get("REBEL_JAX_GIT_COMMIT"):
        return os.environ["REBEL_JAX_GIT_COMMIT"]
    git = ["git", "-C", str(package_dir)]
    try:  # the package's __init__.py tracked there: a venv's site-packages inside another repository is not it
        tracked = subprocess.run([*git, "ls-files", "--error-unmatch", "__init__.py"], capture_output=True, timeout=5)
        out = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        if tracked.returncode == 0 and out.returncode == 0:
            return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        return f"installed {importlib.metadata.version('rebel_jax')}"
    except importlib.metadata.PackageNotFoundError:
        return None


def command_line(argv: list[str]) -> str:
    """The command as typed, independent of where the package lives: ``python -m rebel_jax.train ARGS``
    (the labelling page's token, a secret, written ``...``)."""
    return shlex.join(["python", "-m", "rebel_jax.train", *redact_token(argv)])


def flatten(tree: dict, prefix: str = "") -> dict:
    """A nested dict's leaves keyed by their dotted paths: ``{"a": {"b": 1}}`` gives ``{"a.b": 1}``."""
    out = {}
    for k, v in tree.items():
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def _run_fields(args: Args) -> dict:
    """What fixes a run besides its config: the columns (as meta.json records them)."""
    return {
        "seeds": args.seeds,
        "lams": [lam for lam, _ in args.grid()] if swept_knob(args.config) else None,
        "teachers": [t for _, t in args.grid()] if args.teacher_grid else None,
    }


def resume_changes(run_dir: pathlib.Path, args: Args) -> list[str]:
    """The fields in which ``args`` differ from the run saved in ``run_dir``, but a larger ``train.total_steps``.

    A field the saved config lacks (added to :class:`Config` since) counts as unchanged at its default.

    Raises:
      ConfigError: if ``config.json`` or ``meta.json`` cannot be read.
    """
    try:
        saved = json.loads((run_dir / "config.json").read_text())
        meta = json.loads((run_dir / "meta.json").read_text())
    except (OSError, ValueError) as err:
        raise ConfigError(f"--resume: cannot read the saved run's config.json / meta.json ({err})") from err
    now = json.loads(json.dumps(to_dict(args.config)))  # tuples as lists, like the saved file
    old, new = flatten(saved), flatten(now)
    for name, value in _run_fields(args).items():
        old[name], new[name] = meta.get(name), json.loads(json.dumps(value))
    defaults = flatten(json.loads(json.dumps(to_dict(Config()))))
    changes = []
    for name in sorted(old.keys() | new.keys()):
        before, after = old.get(name, "<absent>"), new.get(name, "<absent>")
        if before == after or (name == "train.total_steps" and isinstance(before, int) and after > before):
            continue
        if name not in old and name in defaults and after == defaults[name]:
            continue
        changes.append(f"{name} (saved {before!r}, now {after!r})")
    return changes


def prepare_run_dir(args: Args, lock: rundir.RunLock | None = None) -> pathlib.Path:
    """Checks ``args.run_dir`` for this run, then creates it; nothing is written before every check passed.

    With ``lock``, the directory is created first and locked (:class:`rundir.RunLock`) before its content is read;
    the lock stays held (the caller releases it).

    Raises:
      ConfigError: an empty path, a path that is not a writable directory, a directory that holds
        another run (without ``--resume`` or ``--overwrite``), or ``--resume`` with a changed configuration.
    """
    cfg = args.config
    if args.run_dir is None:
        run_dir = pathlib.Path("runs") / f"{cfg.algo}_{cfg.env.task}_{time.strftime('%Y%m%d-%H%M%S')}"
    elif not args.run_dir.strip():
        raise ConfigError(
            f"run_dir={args.run_dir!r} is invalid: allowed a directory path"
            " (leave --run-dir out for runs/<algo>_<task>_<time>)"
        )
    else:
        run_dir = pathlib.Path(args.run_dir)
    try:  # a name the file system refuses (too long, a NUL byte): before anything is created
        run_dir.exists()
    except (OSError, ValueError) as err:
        cause = getattr(err, "strerror", None) or str(err)
        raise ConfigError(f"run_dir={str(run_dir)!r} is invalid: the file system refuses the name ({cause})") from None
    too_long = [part for part in run_dir.absolute().parts if len(os.fsencode(part)) > 255]
    if too_long:
        raise ConfigError(
            f"run_dir={str(run_dir)!r} is invalid: allowed names of at most 255 bytes per directory "
            f"({len(os.fsencode(too_long[0]))} bytes: {too_long[0][:40]}...)"
        )
    if args.resume and args.overwrite:
        raise ConfigError("overwrite=True is invalid with --resume: allowed one of --resume (continue) or --overwrite")
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"run_dir={str(run_dir)!r} is invalid: allowed a directory (it is an existing file)")
    if lock is not None:
        _writable_dir(run_dir)
        lock.acquire(run_dir)
    existing = [name for name in RUN_FILES if (run_dir / name).exists() or (run_dir / name).is_symlink()]
    if existing and not (args.resume or args.overwrite):
        raise ConfigError(
            f"run_dir={str(run_dir)!r} is invalid: it holds a run ({', '.join(existing)}); "
            "allowed --resume to continue it, --overwrite to replace it, or a new --run-dir"
        )
    if args.resume:
        rundir.check_resumable(run_dir)
    if args.resume and (run_dir / "config.json").exists():
        changes = resume_changes(run_dir, args)
        if changes:
            raise ConfigError(
                f"--resume: the flags differ from the saved run in {'; '.join(changes)}. "
                "Allowed: the saved values, except a larger --total-steps to extend the run "
                "(or start a new run with another --run-dir)"
            )
    _writable_dir(run_dir)
    if args.overwrite and existing:
        for name in existing:
            path = run_dir / name
            try:
                shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
            except OSError as err:
                raise ConfigError(
                    f"--overwrite: cannot delete {path} ({err.strerror or err}); fix it, or remove it"
                ) from err
        print(f"--overwrite: deleted the previous run's {', '.join(existing)} in {run_dir}", file=sys.stderr)
    return run_dir


def _writable_dir(run_dir: pathlib.Path) -> None:
    """Creates ``run_dir`` and checks that files can be written in it (raises ConfigError)."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        with open(run_dir / ".write-test", "w"):
            pass
        (run_dir / ".write-test").unlink()
    except OSError as err:
        raise ConfigError(f"run_dir={str(run_dir)!r} is invalid: allowed a writable directory ({err})") from err


def _write_config(run_dir: pathlib.Path, args: Args) -> None:
    write_json(run_dir / "config.json", to_dict(args.config), strict_json=False)  # keeps beta = inf


def _write_meta(run_dir: pathlib.Path, args: Args, command: str, device_columns: int) -> None:
    meta = {
        "jax": jax.__version__,
        "devices": [d.device_kind for d in jax.devices()],
        "processes": jax.process_count(),
        "backend": jax.default_backend(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "git_commit": _git_commit(),
        "compile_cache": compile_cache.in_use(),
        "command": command,
        **_run_fields(args),
        "columns": args.columns,
        "device_columns": device_columns,  # the columns computed, padding included
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
        rundir.CHECKSUMS_FIELD: True,  # every checkpoint has checksums.json: one without it is damaged
    }
    write_json(run_dir / "meta.json", meta)
    _write_config(run_dir, args)  # last: a run counts as saved (for --resume) once config.json exists


def device_columns(run_dir: pathlib.Path, args: Args, devices: int, resuming: bool) -> int:
    """The columns this run computes over ``devices`` (``placement.padded_columns``); a resumed run keeps the
    padding its checkpoints hold, which must split over ``devices`` (raises ConfigError)."""
    total = placement.padded_columns(args.columns, devices)
    if not resuming:
        return total
    saved = json.loads((run_dir / "meta.json").read_text()).get("device_columns", args.columns)
    if saved != total and saved % devices:
        counts = ", ".join(str(d) for d in range(1, saved + 1) if saved % d == 0)
        raise ConfigError(
            f"{run_dir}'s checkpoints hold {saved} columns ({args.columns} and {saved - args.columns} padding): "
            f"resume on {counts} devices, not {devices}"
        )
    return saved


def start_run_files(
    run_dir: pathlib.Path, args: Args, command: str, device_columns: int, resuming: bool, start: int
) -> None:
    """The run directory's files as the rounds start (process 0): ``metrics.jsonl`` kept up to round ``start``,
    the first to run, and ``meta.json`` written for a new run or the resume recorded in it."""
    if resuming:
        keep_rounds_before(run_dir / "metrics.jsonl", start)
        _record_resume(run_dir, args, command, start)
        return
    if args.resume:
        print(f"note: --resume: no run in {run_dir} yet; starting the run from scratch", file=sys.stderr)
    keep_rounds_before(run_dir / "metrics.jsonl", 0)
    _write_meta(run_dir, args, command, device_columns)


def _record_resume(run_dir: pathlib.Path, args: Args, command: str, start: int) -> None:
    """Appends this call to meta.json's ``resumed`` list; saves the config (a larger total_steps)."""
    meta = json.loads((run_dir / "meta.json").read_text())
    resumed = {"command": command, "started": datetime.datetime.now().isoformat(timespec="seconds")}
    resumed["compile_cache"] = compile_cache.in_use()
    meta["resumed"] = [*meta.get("resumed", []), {**resumed, "from_round": start}]
    write_json(run_dir / "meta.json", meta)
    _write_config(run_dir, args)


def keep_rounds_before(metrics: pathlib.Path, rounds: int) -> None:
    """Keeps the first ``rounds`` rounds of a resumed run's log: later ones are run (and logged) again.

    A last line cut mid-write (the process was killed while writing it) is dropped with a notice;
    an unreadable line before the last is an error, as the log would otherwise lose a round, and so is a log
    without each of the first ``rounds`` rounds once, in order (raises ConfigError).
    """
    if not metrics.exists():
        return
    rundir.check_log_order(metrics, rounds)  # each round before the checkpoint once, in order (raises ConfigError)
    records, cut = rundir.log_records(metrics)
    if cut is not None:
        print(f"note: {metrics}: dropped its last line, cut mid-write ({len(cut)} chars)", file=sys.stderr)
    kept = [line + "\n" for line, record in records if record["round"] < rounds]
    tmp = metrics.with_name(metrics.name + ".tmp")
    tmp.write_text("".join(kept))
    os.replace(tmp, metrics)
