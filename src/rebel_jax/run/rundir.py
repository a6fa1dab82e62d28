"""Run-directory and process faults: one process per run directory, runs that ``--resume`` must not touch, I/O
failures as one line, and the state's memory before it is allocated.

- :class:`RunLock`: an advisory ``flock`` on ``RUN_DIR/.lock``, held for the whole run by the process that
  prepares the directory (process 0 of a ``--distributed`` run; the others only write checkpoints where it
  says). The kernel releases it when that process ends, however it ends. A second run in the directory is
  refused, naming the first one's pid and host.
- :func:`check_resumable`: a run directory whose ``config.json`` or ``meta.json`` is missing or unreadable while it
  holds a run's data, a run file of the wrong kind (a ``checkpoints`` that is a file, a ``config.json`` that is a
  FIFO), a file the run cannot read or write, and a ``metrics.jsonl`` that is not a log of the checkpointed rounds,
  are refused before anything is written or moved.
- :func:`io_error_line`: an ``OSError`` (disk full, a failed checkpoint save, a permission changed during the run)
  as one line naming the path and the cause.
- :func:`check_memory`: the state's bytes (from ``jax.eval_shape``, nothing allocated) against the device's memory
  (the machine's RAM on a CPU), naming the flags that drive the largest part.

Exit statuses of ``python -m rebel_jax.train`` set here: :data:`EXIT_USAGE` (2) a bad flag or run directory, found
before anything is written; :data:`EXIT_IO` (4) an I/O failure during the run, the last complete checkpoint kept as
it was; :data:`EXIT_INTERRUPTED` (130) Ctrl-C.
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import json
import math
import os
import pathlib
import socket

from rebel_jax.core.errors import ConfigError

EXIT_USAGE = 2
EXIT_IO = 4
EXIT_INTERRUPTED = 130
"""128 + SIGINT, as a shell reports a process that Ctrl-C ended."""
EXIT_TERMINATED = 143
"""128 + SIGTERM."""
LOCK = ".lock"
"""The lock file in a run directory (its content: the holder's pid and host)."""
SAVED = ("config.json", "meta.json")
"""What makes a directory's run resumable: its configuration and the columns it ran (written first)."""
DATA = ("metrics.jsonl", "final.json", "checkpoints", "checkpoints_damaged", "tb", "learning_curve.png", "eval.gif")
"""A run's results: a directory holding one of them holds a run that ``--resume`` must not start afresh."""
KINDS = {
    "config.json": "file",
    "meta.json": "file",
    "metrics.jsonl": "file",
    "final.json": "file",
    "learning_curve.png": "file",
    "eval.gif": "file",
    "checkpoints": "dir",
    "checkpoints_damaged": "dir",
    "tb": "dir",
}
"""The kind of each run file that ``--resume`` reads or writes, for :func:`check_resumable`."""


# -- one process per run directory ----------------------------------------------------------------------------
class RunLock:
    """The run directory's lock: ``with RunLock() as lock: lock.acquire(run_dir)``; released on leaving the block.

    ``flock`` locks belong to an open file, so a second :meth:`acquire` of one directory fails in the same process
    too. The lock file is removed when released; a process that opened it just before then finds that the file it
    locked is no longer the directory's and opens the new one.
    """

    def __init__(self):
        self.path: pathlib.Path | None = None
        self._file = None

    def acquire(self, run_dir: pathlib.Path) -> None:
        """Takes ``run_dir``'s lock (the directory must exist) and writes this process's pid and host into it.

        Raises:
          ConfigError: if another process holds it, or the lock file cannot be opened.
        """
        path = run_dir / LOCK
        while True:
            try:
                file = open(path, "a+")  # noqa: SIM115 - held until release()
            except OSError as err:
                raise ConfigError(f"run_dir={str(run_dir)!r} is invalid: cannot open its lock {path} ({err})") from err
            try:
                fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                file.seek(0)
                holder = file.read().strip() or "another process"
                file.close()
                if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                    raise ConfigError(f"run_dir={str(run_dir)!r} is invalid: cannot lock {path} ({err})") from err
                raise ConfigError(
                    f"run_dir={str(run_dir)!r} is in use by {holder} (it holds {path}): wait for that run to end, "
                    "or choose another --run-dir"
                ) from None
            if _same_file(file, path):
                break
            file.close()  # its last holder removed it after we opened it: lock the directory's current one
        file.seek(0)
        file.truncate()
        file.write(f"process {os.getpid()} on {socket.gethostname()}\n")
        file.flush()
        self.path, self._file = path, file

    def release(self) -> None:
        """Removes the lock file and releases the lock (nothing if none is held)."""
        if self._file is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        except OSError:
            pass  # a lock file left behind is harmless: the next run takes it
        self._file.close()
        self.path, self._file = None, None

    def __enter__(self) -> RunLock:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _same_file(file, path: pathlib.Path) -> bool:
    try:
        return os.path.samestat(os.fstat(file.fileno()), os.stat(path))
    except FileNotFoundError:
        return False


# -- a run directory that --resume must refuse --------------------------------------------------------------------
def _kind_problem(path: pathlib.Path, kind: str) -> str | None:
    """Why the existing ``path`` cannot be used as a run's ``kind`` (``file`` or ``dir``), or None."""
    if kind == "file" and not path.is_file():
        return "is not a regular file" if path.exists() else "is a broken link"
    if kind == "dir" and not path.is_dir():
        return "is not a directory"
    return None


def _access_problem(path: pathlib.Path, kind: str) -> str | None:
    """The ``chmod`` that lets this process read and write ``path`` (a ``file`` or ``dir``), or None if it can."""
    if kind == "dir" and not os.access(path, os.R_OK | os.W_OK | os.X_OK):
        return f"chmod u+rwx {path}"
    if kind == "file" and not os.access(path, os.R_OK | os.W_OK):
        return f"chmod u+rw {path}"
    return None


def _json_object_problem(path: pathlib.Path) -> str | None:
    """Why ``path`` is not a readable JSON object, or None."""
    if not path.exists() and not path.is_symlink():
        return "is missing"
    kind = _kind_problem(path, "file")
    if kind:
        return kind
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        return f"is unreadable ({type(err).__name__}: {str(err).splitlines()[0][:120]})"
    return None if isinstance(value, dict) else f"holds a JSON {type(value).__name__}, not an object"


def saved_steps(run_dir: pathlib.Path) -> list[int]:
    """The complete checkpoint steps in ``run_dir/checkpoints`` (orbax renames a step to its number once written)."""
    directory = run_dir / "checkpoints"
    try:
        return sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit() and p.is_dir())
    except OSError:
        return []


def log_records(metrics: pathlib.Path) -> tuple[list[tuple[str, dict]], str | None]:
    """The round records of ``metrics.jsonl`` with their lines, and its last line if it was cut mid-write (else
    None; ``--resume`` drops it).

    Raises:
      ConfigError: a line before the last that is not a JSON object with an integer ``round``.
    """
    lines = metrics.read_text().splitlines()
    records, cut = [], None
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError as err:
            if i == len(lines) - 1:
                cut = line
                continue
            raise ConfigError(
                f"--resume: {metrics}: line {i + 1} is not JSON ({err}); repair or remove that line"
            ) from None
        if not isinstance(record, dict) or not isinstance(record.get("round"), int):
            raise ConfigError(
                f"--resume: {metrics}: line {i + 1} is not a round's record (a JSON object with an integer "
                "'round'); repair or remove that line"
            )
        records.append((line, record))
    return records, cut


def logged_rounds(metrics: pathlib.Path) -> set[int]:
    """The rounds ``metrics.jsonl`` logs (:func:`log_records`)."""
    return {record["round"] for _, record in log_records(metrics)[0]}


META_TYPES: dict[str, tuple[type, ...]] = {
    "git_commit": (str, type(None)),
    "command": (str,),
    "seeds": (int,),
    "columns": (int,),
    "device_columns": (int,),
    "lams": (list, type(None)),
    "teachers": (list, type(None)),
    "resumed": (list,),
    "checkpoint_checksums": (bool,),
}
"""The types of the ``meta.json`` fields that ``--resume`` reads (a field may be absent: older runs lack some)."""
CHECKSUMS_FIELD = "checkpoint_checksums"
"""``meta.json``'s mark of a run whose every checkpoint has its checksums (runs written before checksums lack it)."""


def _type_names(kinds: tuple[type, ...]) -> str:
    names = {int: "an integer", str: "a string", list: "a list", bool: "true or false", type(None): "null"}
    return " or ".join(names[k] for k in kinds)


def check_meta(path: pathlib.Path, what: str = "--resume") -> dict:
    """``meta.json`` read against :data:`META_TYPES`: each field it has of its type, the counts >= 1.

    Raises:
      ConfigError: one line naming the first field of another type or out of range.
    """
    meta = json.loads(path.read_text())
    for name, kinds in META_TYPES.items():
        if name not in meta:
            continue
        value = meta[name]
        ok = isinstance(value, kinds) and not (isinstance(value, bool) and bool not in kinds)
        if ok and name in ("seeds", "columns", "device_columns"):
            ok = value >= 1
        if ok and name == "resumed":
            ok = all(isinstance(item, dict) for item in value)
        if not ok:
            allowed = "a list of objects" if name == "resumed" else _type_names(kinds)
            allowed += " >= 1" if name in ("seeds", "columns", "device_columns") else ""
            raise ConfigError(
                f"{what}: {path}: {name}={value!r} is invalid: allowed {allowed}; restore meta.json"
                + (", or replace the run with --overwrite" if what == "--resume" else "")
            )
    if meta.get("device_columns", 1) < meta.get("columns", 1):
        raise ConfigError(
            f"{what}: {path}: device_columns={meta['device_columns']!r} is invalid: allowed >= columns="
            f"{meta['columns']} (the run's columns and their padding); restore meta.json"
        )
    return meta


def check_log_order(metrics: pathlib.Path, rounds: int, complete: bool = True) -> None:
    """Refuses a ``metrics.jsonl`` whose records of the rounds before ``rounds`` are not rounds 0, 1, ... once each
    and in order (a round lost, repeated or moved); later records are run and logged again on resume. Without
    ``complete``, a log that ends early passes (the newest checkpoint may be damaged, and the resume start earlier:
    :func:`rebel_jax.run.cli_rundir.keep_rounds_before` checks the log up to the checkpoint it resumes from).

    Raises:
      ConfigError: naming the first round out of place.
    """
    records = [record["round"] for _, record in log_records(metrics)[0] if record["round"] < rounds]
    end = [None] if complete and len(records) < rounds else []  # with ``complete``, the log must reach ``rounds``
    for expected, found in enumerate([*records, *end]):
        if found is None:
            found = rounds  # the log ends before the checkpoint's rounds do
        if found == expected:
            continue
        if found < expected:
            what = f"holds round {found} twice" if found in records[:expected] else f"holds round {found} late"
        else:
            what = f"lacks round {expected}"
        raise ConfigError(
            f"--resume: {metrics} {what} (line {expected + 1}), but the rounds before a checkpoint must be logged "
            "once each, in order: repair the log, or replace the run with --overwrite"
        )


def check_resumable(run_dir: pathlib.Path) -> None:
    """Refuses (nothing written or moved) a run directory that ``--resume`` cannot continue as the run it holds.

    Raises:
      ConfigError: ``config.json`` or ``meta.json`` missing or unreadable while the directory holds a run's data
        (or one of them present and unreadable), a run file of the wrong kind or without read and write permission,
        or a ``metrics.jsonl`` that is not a log of every round its oldest checkpoint holds.
    """
    data = [name for name in DATA if (run_dir / name).exists() or (run_dir / name).is_symlink()]
    present = [name for name in SAVED if (run_dir / name).exists()]
    for name in SAVED:
        problem = _json_object_problem(run_dir / name)
        if problem == "is missing" and not data and not present:
            return  # no run yet (or one killed before it saved its configuration): it starts from scratch
        if problem:
            raise ConfigError(
                f"--resume: {run_dir / name} {problem}, but {run_dir} holds a run ({', '.join(data or present)}): "
                f"restore {name}, or replace the run with --overwrite"
            )
    for name in (*SAVED, *data):
        problem = _kind_problem(run_dir / name, KINDS[name])
        if problem:
            raise ConfigError(
                f"--resume: {run_dir / name} {problem}: make it the run's {name}"
                f" (a {'directory' if KINDS[name] == 'dir' else 'file'}) again, or remove it"
            )
        chmod = _access_problem(run_dir / name, KINDS[name])
        if chmod:
            raise ConfigError(f"--resume: {run_dir / name} cannot be read and written by this user: {chmod}")
    check_meta(run_dir / "meta.json")
    steps = saved_steps(run_dir)
    if not steps and (run_dir / "final.json").exists():
        raise ConfigError(
            f"--resume: {run_dir} holds a finished run (final.json) and no checkpoint to continue from: it would "
            "start over and replace it; use another --run-dir, or --overwrite to replace it"
        )
    needed = set(range(steps[0])) if steps else set()
    metrics = run_dir / "metrics.jsonl"
    missing = sorted(needed - (logged_rounds(metrics) if metrics.exists() else set()))
    if missing:
        which = f"round {missing[0]}" if len(missing) == 1 else f"rounds {missing[0]}-{missing[-1]}"
        lacks = "is missing" if not metrics.exists() else f"lacks {which}"
        raise ConfigError(
            f"--resume: {metrics} {lacks}, but checkpoint {steps[0]} holds rounds 0-{steps[0] - 1}: restore the "
            "log, or replace the run with --overwrite"
        )
    if steps and metrics.exists():
        check_log_order(metrics, steps[-1], complete=False)


# -- failures during the run ----------------------------------------------------------------------------------------
def first_failure(err: OSError) -> OSError:
    """The ``OSError`` that ``err`` was raised while handling, and so on back (closing files after a failed write
    fails again): the first failure, which names what failed."""
    while isinstance(err.__context__, OSError) and not err.__suppress_context__:
        err = err.__context__
    return err


def kept_line(run_dir: pathlib.Path | None) -> str:
    """What a stopped run leaves to continue from: ``checkpoint 3 is saved`` or ``no checkpoint was written``."""
    steps = [step for step in saved_steps(run_dir) if _has_checksums(run_dir, step)] if run_dir is not None else []
    return f"checkpoint {steps[-1]} is saved" if steps else "no checkpoint was written"


def _has_checksums(run_dir: pathlib.Path, step: int) -> bool:
    return (run_dir / "checkpoints" / str(step) / "checksums.json").is_file()


def io_error_line(err: OSError, run_dir: pathlib.Path | None = None) -> str:
    """``err`` (disk full, permission denied, a failed checkpoint save; its :func:`first_failure`) as one line
    naming the path, the cause, and the checkpoint ``run_dir`` keeps (:func:`kept_line`)."""
    err = first_failure(err)
    text = str(err).strip()
    cause = err.strerror or (text.splitlines()[0] if text else type(err).__name__)
    where = f"{err.filename}: " if err.filename else ""
    if err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        advice = "free space on its disk"
    elif err.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        advice = "make it writable"
    else:
        advice = "fix the cause"
    then = "then --resume" if run_dir is not None and saved_steps(run_dir) else "then run it again"
    return f"error: {where}{cause}; the run stopped ({kept_line(run_dir)}): {advice}, {then}"


def close_all(parts) -> None:
    """Closes each of ``parts`` (None left out) in turn, even when one fails; then raises the first failure.

    For a ``finally`` clause: each ``close`` runs (orbax's threads end, files are closed), and the error that
    stopped the run stays the first one in the chain (:func:`first_failure`).
    """
    failure = None
    for part in parts:
        if part is None:
            continue
        try:
            part.close()
        except Exception as err:  # noqa: BLE001 - raised below, once the others are closed
            failure = failure or err
    if failure is not None:
        raise failure


def interrupted_line(run_dir: pathlib.Path | None, what: str = "interrupted") -> str:
    """What Ctrl-C (``interrupted``) or SIGTERM (``terminated``) prints: the last round a ``--resume`` continues
    after."""
    steps = saved_steps(run_dir) if run_dir is not None else []
    if not steps:
        return f"{what} before the first checkpoint; --resume starts the run again"
    return f"{what} after round {steps[-1] - 1}; continue with --resume"


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread as Ctrl-C's ``KeyboardInterrupt`` is (:func:`terminate_as_interrupt`)."""


def terminate_as_interrupt():
    """Makes SIGTERM end the run as Ctrl-C does (the checkpoints closed, one line, exit status 143); returns the
    handler it replaces (None outside the main thread, where none is set), for :func:`restore_sigterm`."""
    import signal
    import threading

    def raise_terminated(signum, frame):
        raise Terminated

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, raise_terminated)


def restore_sigterm(previous) -> None:
    """Puts back the SIGTERM handler :func:`terminate_as_interrupt` replaced (nothing if it set none)."""
    import signal

    if previous is not None:
        signal.signal(signal.SIGTERM, previous)


def check_listen_address(host: str, port: int, flags: str = "--human.host, --human.port") -> None:
    """Refuses ``host:port`` if a server cannot listen there (no such address, the port in use); nothing stays open.

    Raises:
      ConfigError: naming the address, the cause and ``flags``.
    """
    try:
        family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as http.server's servers do
            sock.bind((host, port))
    except OSError as err:
        cause = err.strerror or str(err)
        raise ConfigError(
            f"human.host={host!r}, human.port={port} is invalid: cannot listen there ({cause}); allowed an address "
            f"of this machine (127.0.0.1: this machine only) and a free port (0: any) ({flags})"
        ) from None


# -- memory -----------------------------------------------------------------------------------------------------
def tree_bytes(tree) -> dict[str, int]:
    """Bytes of each top-level field of a (flax.struct) state of arrays or ``jax.ShapeDtypeStruct`` leaves."""
    import jax

    if dataclasses.is_dataclass(tree):
        parts = {field.name: getattr(tree, field.name) for field in dataclasses.fields(tree)}
    else:
        parts = {"state": tree}
    return {
        name: sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(part)) for name, part in parts.items()
    }


def device_memory(device) -> tuple[int | None, str]:
    """(bytes, what they are) of ``device``: its allocator's limit, or the machine's RAM for a CPU (None: unknown)."""
    stats = None
    if device.platform != "cpu":
        try:
            stats = device.memory_stats()
        except Exception:  # noqa: BLE001 - a backend without statistics
            stats = None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"{device.device_kind}'s memory"
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "this machine's RAM"
    except (ValueError, OSError):
        return None, "unknown"


def _gb(n: int) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e8 else f"{n / 1e6:.1f} MB"


def check_memory(sizes: dict[str, int], devices: list, flags: dict[str, str], memory_of=None) -> None:
    """Refuses a state of ``sizes`` (:func:`tree_bytes`, every column) that cannot fit in ``devices``' memory.

    The columns are split evenly over ``devices`` (``placement.seed_sharding``), so each holds its share; CPU devices
    share the machine's RAM, so the whole state counts against it.

    Args:
      sizes: bytes of each part of the state.
      devices: the devices the state is placed on.
      flags: the flags that drive each part's size (``buffer``: ``--buffer-capacity``, ...).
      memory_of: the device whose memory is read (default ``devices[0]``); with several processes, one of
        this process's devices (another process's device has no statistics here).

    Raises:
      ConfigError: naming the state's size, the largest part's flags, and the memory it exceeds.
    """
    total = sum(sizes.values())
    on_cpu = devices[0].platform == "cpu"
    need = total if on_cpu else math.ceil(total / len(devices))
    have, what = device_memory(memory_of or devices[0])
    if have is None or need <= have:
        return
    largest = max(sizes, key=sizes.get)
    where = "" if on_cpu or len(devices) == 1 else f" on each of {len(devices)} devices"
    raise ConfigError(
        f"the run's state needs {_gb(need)}{where} ({largest}: {_gb(sizes[largest])}), more than the {_gb(have)} of "
        f"{what}: lower {flags.get(largest, 'the sizes of ' + largest)} (or --seeds)"
    )
