"""The human teacher's label file, ``RUN_DIR/labels.jsonl``, and the answer -> label mapping.

The file is a journal: one JSON object per line, appended as things happen and never rewritten,
so a crash or a closed tab loses nothing that was answered. Three kinds of line:

- ``answer``: a labeller's answer to one query (see :func:`answer_record`);
- ``undo``: the last answer of the session is withdrawn (the query is asked again);
- ``close``: the session ended (``reason``: ``finished``, ``budget``, ``timeout``); queries it
  left unanswered are dropped, as skips are.

Each line is written with one ``write`` of the whole line and its newline, then flushed and
``fsync``-ed before the answer is acknowledged. A crash can therefore only leave a *torn last
line* (a prefix of one line, without its newline); reading repairs it: the torn bytes are moved
to ``labels.jsonl.torn`` (nothing is deleted) and the file is cut back to its last whole line.
Any other unreadable line is an error.

Label convention (the package's): ``label = P(segment b preferred)``; ``mask = 0`` drops the pair.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import pathlib
import sys
import threading
from typing import Any

ANSWERS = ("left", "right", "equal", "skip")
"""What a labeller can answer: the left clip is better, the right one, both equal, or can't tell."""


class LabelError(ValueError):
    """A bad answer, a bad label file, or labels that do not belong to this run."""


def to_label(answer: str, left: str) -> tuple[float, float]:
    """The (label, mask) of an answer, given which segment (``"a"`` or ``"b"``) was shown on the left.

    ``label`` is P(segment b preferred): 0 for a, 1 for b, 0.5 for equal (B-Pref's ``equal``
    teacher); a skip has ``mask = 0`` and label 0 (B-Pref's ``skip`` teacher: dropped; it counts against
    the budget only as an asked pair, under ``feedback.budget`` ``asked``).
    """
    if left not in ("a", "b"):
        raise LabelError(f"left={left!r} is invalid: allowed 'a' or 'b'")
    if answer == "equal":
        return 0.5, 1.0
    if answer == "skip":
        return 0.0, 0.0
    if answer not in ("left", "right"):
        raise LabelError(f"answer={answer!r} is invalid: allowed {', '.join(ANSWERS)}")
    right = "b" if left == "a" else "a"
    preferred = left if answer == "left" else right
    return (1.0 if preferred == "b" else 0.0), 1.0


def now() -> str:
    """The server's clock, ISO 8601 UTC with milliseconds."""
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")


def query_id(round_index: int, index: int) -> str:
    """The id of query ``index`` of the session that starts round ``round_index`` (stable across resumes)."""
    return f"r{round_index}-q{index}"


@dataclasses.dataclass
class SessionAnswers:
    """The answers in force for one session, after undos.

    Attributes:
      answers: query id -> its ``answer`` record.
      order: answered query ids, oldest first (an undo withdraws the last one).
      closed: the session's ``close`` record, or None while it is open.
    """

    answers: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    order: list[str] = dataclasses.field(default_factory=list)
    closed: dict[str, Any] | None = None

    def apply(self, record: dict[str, Any]) -> None:
        kind, query = record.get("kind"), record.get("query")
        if kind == "answer":
            if query in self.answers:
                raise LabelError(f"query {query} answered twice without an undo between")
            self.answers[query] = record
            self.order.append(query)
        elif kind == "undo":
            if not self.order or self.order[-1] != query:
                raise LabelError(f"undo of {query}, which is not the session's last answer")
            self.order.pop()
            del self.answers[query]
        elif kind == "close":
            self.closed = record
        else:
            raise LabelError(f"unknown record kind {kind!r}")

    @property
    def kept(self) -> int:
        """Answers the reward model keeps (all but skips)."""
        return sum(1 for r in self.answers.values() if r["mask"] > 0)


def _read(path: pathlib.Path, repair: bool) -> list[dict[str, Any]]:
    data = path.read_bytes()
    cut = data.rfind(b"\n") + 1
    whole, tail = data[:cut], data[cut:]
    records = []
    for number, line in enumerate(whole.splitlines(), 1):
        try:
            records.append(json.loads(line))
        except ValueError as err:
            raise LabelError(f"{path}:{number}: not a JSON line ({err}); the file is damaged") from err
    if tail:
        try:  # A whole line that lost only its newline.
            records.append(json.loads(tail))
            if repair:
                with open(path, "ab") as f:
                    f.write(b"\n")
                    f.flush()
                    os.fsync(f.fileno())
        except ValueError:
            where = path.with_name(path.name + ".torn")
            print(f"{path}: torn last line ({len(tail)} bytes) moved to {where}", file=sys.stderr)
            if repair:
                with open(where, "ab") as f:
                    f.write(tail + b"\n")
                    f.flush()
                    os.fsync(f.fileno())
                with open(path, "r+b") as f:
                    f.truncate(cut)
                    f.flush()
                    os.fsync(f.fileno())
    return records


class LabelFile:
    """``labels.jsonl``: read (repairing a torn last line) at open, then appended line by line.

    Args:
      path: the file; created empty if missing and ``writable``.
      writable: False for a file only read (``--teacher replay``): no repair, no appends.

    Thread-safe: the labelling page's request threads append through one lock.
    """

    def __init__(self, path: pathlib.Path, writable: bool = True):
        self.path = pathlib.Path(path)
        self.writable = writable
        self._lock = threading.Lock()
        if not self.path.exists():
            if not writable:
                raise LabelError(f"label file {self.path} does not exist")
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.touch()
        self.records = _read(self.path, repair=writable)
        for round_index in {r.get("round") for r in self.records}:
            self.session(round_index)  # Checks every session's journal now rather than mid-run.

    def append(self, record: dict[str, Any]) -> None:
        """Appends one record as one line: a single write, flushed and fsync-ed before returning."""
        if not self.writable:
            raise LabelError(f"{self.path} is opened read-only")
        line = (json.dumps(record, sort_keys=True) + "\n").encode()
        with self._lock:
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                view = memoryview(line)
                while view:
                    view = view[os.write(fd, view) :]
                os.fsync(fd)
            finally:
                os.close(fd)
            self.records.append(record)

    def session(self, round_index: int) -> SessionAnswers:
        """The answers in force for the session of round ``round_index``."""
        state = SessionAnswers()
        with self._lock:
            records = [r for r in self.records if r.get("round") == round_index]
        for record in records:
            state.apply(record)
        return state
