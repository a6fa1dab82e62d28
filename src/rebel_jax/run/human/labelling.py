"""The labelling page's sessions: the queries a page shows, the answers it sends, and the checks of each request's
body (:class:`Labelling`, shared by the trainer's thread and the page server's request threads, :mod:`.server`)."""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import threading
import time
from http import HTTPStatus
from typing import Any

from rebel_jax.run.human.labels import ANSWERS, LabelFile, SessionAnswers, now, to_label

_EARLIEST_MS, _LATEST_MS = 946_684_800_000, 4_102_444_800_000  # 2000-01-01 and 2100-01-01 UTC
_FAREWELL_S = 2.0  # At the end of a run, how long an open page is given to read that it is over.


class RequestError(Exception):
    """A request the page's API refuses: its HTTP status and a one-line message."""

    def __init__(self, status: HTTPStatus, message: str):
        super().__init__(message)
        self.status = status


def _short(value: Any, limit: int = 60) -> str:
    """``repr(value)``, cut to ``limit`` characters (a client's value quoted in an error)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


@dataclasses.dataclass
class Query:
    """One pair as the page sees it (``record`` holds what goes into its answer's line)."""

    id: str
    index: int
    left: str  # "a" or "b": which segment is on the left
    record: dict[str, Any]  # segment indices, scripted answer, ... (not sent to the page)
    clips: dict[str, tuple[bytes, str]] = dataclasses.field(default_factory=dict)  # side -> (image, mime)
    shown: bool = False  # the page reported that it shows the clips


@dataclasses.dataclass
class Session:
    round: int
    queries: list[Query]
    answers: SessionAnswers
    remaining: int  # labels left in the budget when the session started
    fps: float
    frames: int
    closed: str | None = None  # the close reason

    @property
    def complete(self) -> bool:
        """Nothing more to ask: every query answered, or the budget spent."""
        return len(self.answers.answers) == len(self.queries) or self.answers.kept >= self.remaining


def _iso(name: str, ms: Any) -> str | None:
    """A client time (milliseconds since the epoch, from 2000 to 2100) as ISO 8601 UTC; None stays None."""
    if ms is None:
        return None
    if not isinstance(ms, int | float) or isinstance(ms, bool) or not math.isfinite(ms):
        raise RequestError(HTTPStatus.BAD_REQUEST, f"{name} must be milliseconds since the epoch, not {_short(ms)}")
    if not _EARLIEST_MS <= ms < _LATEST_MS:
        raise RequestError(
            HTTPStatus.BAD_REQUEST, f"{name} must be milliseconds since the epoch in 2000 to 2099, not {_short(ms)}"
        )
    return datetime.datetime.fromtimestamp(ms / 1000, datetime.UTC).isoformat(timespec="milliseconds")


def _text(body: dict[str, Any], name: str) -> str:
    """The string field ``name`` of a request's body."""
    value = body.get(name)
    if not isinstance(value, str):
        raise RequestError(HTTPStatus.BAD_REQUEST, f"{name} must be a string, not {_short(value)}")
    return value


def parse_body(raw: bytes) -> dict[str, Any]:
    """A POST's body: a JSON object of strings, numbers, booleans and nulls (finite numbers only).

    Raises:
      RequestError: 400, with a one-line message, for anything else (deep nesting included).
    """

    def finite(text: str) -> float:
        value = float(text)
        if not math.isfinite(value):
            raise ValueError(f"{text} is out of range")
        return value

    def constant(name: str) -> None:
        raise ValueError(f"{name} is not a number")

    try:
        body = json.loads(raw, parse_float=finite, parse_constant=constant)
    except RecursionError as err:
        raise RequestError(HTTPStatus.BAD_REQUEST, "the body is not JSON: nested too deeply") from err
    except ValueError as err:  # UnicodeDecodeError too.
        raise RequestError(HTTPStatus.BAD_REQUEST, f"the body is not JSON: {str(err).splitlines()[0]}") from err
    if not isinstance(body, dict):
        raise RequestError(HTTPStatus.BAD_REQUEST, "the body must be a JSON object")
    for name, value in body.items():
        if isinstance(value, dict | list):
            raise RequestError(
                HTTPStatus.BAD_REQUEST, f"{_short(name)} must be a string or a number, not a {type(value).__name__}"
            )
    return body


class Labelling:
    """The state shared by the trainer's thread and the page's request threads.

    Args:
      labels: the run's label file.
      labeller: the id written with each answer.
      instruction: the question the page asks.
      budget: the run's label budget.
      num_rounds: rounds of the run (for the page's progress line).
    """

    def __init__(self, labels: LabelFile, labeller: str, instruction: str, budget: int, num_rounds: int):
        self.labels, self.labeller, self.instruction = labels, labeller, instruction
        self.budget, self.num_rounds = budget, num_rounds
        self.used = 0  # labels used before the open session
        self.round = 0
        self.status = "starting"
        self.session: Session | None = None
        self.final: dict[str, Any] | None = None  # the run's result, once it has finished
        self.run_dir = ""  # where the run's files are (said when it ends)
        self.polled: float | None = None  # time.monotonic() of the page's last state request
        self.told = False  # a page has read that the run is over
        self.changed = threading.Condition()

    # -- the trainer's side ----------------------------------------------------------------
    def set_training(self, round_index: int, used: int) -> None:
        with self.changed:
            self.status, self.round, self.used, self.session = "training", round_index, used, None
            self.changed.notify_all()

    def open_session(self, session: Session, used: int) -> None:
        with self.changed:
            self.status, self.round, self.used, self.session = "labelling", session.round, used, session
            self.changed.notify_all()

    def add_clips(self, query: Query, clips: dict[str, tuple[bytes, str]]) -> None:
        with self.changed:
            query.clips = clips
            self.changed.notify_all()

    def wait(self, timeout: float) -> str:
        """Blocks until the page finishes the session, or ``timeout`` seconds (0: no limit); the close reason."""
        deadline = time.monotonic() + timeout if timeout > 0 else None
        with self.changed:
            while self.session.closed is None:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    self._close("timeout")
                    break
                self.changed.wait(left)
            return self.session.closed

    def set_done(self, final: dict[str, Any] | None, run_dir: str) -> None:
        """The run is over: ``done`` with its ``final`` result, or ``stopped`` (an error, an interrupt) without."""
        with self.changed:
            self.status, self.session = ("done" if final is not None else "stopped"), None
            self.final, self.run_dir = final, run_dir
            self.changed.notify_all()

    def farewell(self, timeout: float = _FAREWELL_S) -> bool:
        """Waits up to ``timeout`` s for a page that polls to read that the run is over; whether one did."""
        with self.changed:
            if self.polled is None or time.monotonic() - self.polled > 2 * timeout:
                return self.told  # No page is open (or it stopped polling long ago).
            return self.changed.wait_for(lambda: self.told, timeout)

    def _close(self, reason: str) -> None:
        session = self.session
        self.labels.append({"kind": "close", "round": session.round, "reason": reason, "written_at": now()})
        session.closed = reason
        self.changed.notify_all()

    # -- the page's side -------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        with self.changed:
            self.polled = time.monotonic()
            if self.status in ("done", "stopped"):
                self.told = True
                self.changed.notify_all()
            out = {
                "status": self.status,
                "round": self.round,
                "num_rounds": self.num_rounds,
                "instruction": self.instruction,
                "labeller": self.labeller,
                "budget": self.budget,
                "used": self.used,
                "session": None,
                "final": self.final,
                "run_dir": self.run_dir if self.status in ("done", "stopped") else None,
            }
            session = self.session
            if session is not None:
                out["used"] = self.used + session.answers.kept
                out["session"] = {
                    "round": session.round,
                    "fps": session.fps,
                    "frames": session.frames,
                    "closed": session.closed,
                    "complete": session.complete,
                    "last": session.answers.order[-1] if session.answers.order else None,
                    "queries": [
                        {
                            "id": q.id,
                            "index": q.index,
                            "ready": bool(q.clips),
                            "shown": q.shown,
                            "answer": session.answers.answers.get(q.id, {}).get("answer"),
                        }
                        for q in session.queries
                    ],
                }
            return out

    def _open(self) -> Session:
        if self.session is None:
            raise RequestError(HTTPStatus.CONFLICT, "no feedback session is open")
        if self.session.closed is not None:
            raise RequestError(HTTPStatus.CONFLICT, f"the session of round {self.session.round} is closed")
        return self.session

    def _query(self, session: Session, query_id: Any) -> Query:
        for q in session.queries:
            if q.id == query_id:
                return q
        raise RequestError(HTTPStatus.NOT_FOUND, f"unknown query id {_short(query_id)} in the open session")

    def clip(self, query_id: str, side: str) -> tuple[bytes, str]:
        with self.changed:
            session = self.session
            if session is None:
                raise RequestError(HTTPStatus.NOT_FOUND, "no feedback session is open")
            query = self._query(session, query_id)
            if side not in ("left", "right"):
                raise RequestError(HTTPStatus.NOT_FOUND, f"side must be left or right, not {_short(side)}")
            if not query.clips:
                raise RequestError(HTTPStatus.NOT_FOUND, f"the clips of {query_id} are not rendered yet")
            return query.clips[side]

    def shown(self, body: dict[str, Any]) -> None:
        """The page shows ``body["query"]``'s clips: from now on it may be answered."""
        query_id = _text(body, "query")
        with self.changed:
            session = self._open()
            query = self._query(session, query_id)
            if not query.clips:
                raise RequestError(HTTPStatus.CONFLICT, f"the clips of {query.id} are not rendered yet")
            query.shown = True
            self.changed.notify_all()

    def answer(self, body: dict[str, Any]) -> None:
        query_id, answer = _text(body, "query"), _text(body, "answer")
        if answer not in ANSWERS:
            raise RequestError(
                HTTPStatus.BAD_REQUEST, f"answer must be one of {', '.join(ANSWERS)}, not {_short(answer)}"
            )
        shown_at, answered_at = _iso("shown_at", body.get("shown_at")), _iso("answered_at", body.get("answered_at"))
        if shown_at is not None and answered_at is not None and body["answered_at"] < body["shown_at"]:
            raise RequestError(HTTPStatus.BAD_REQUEST, "answered_at is before shown_at")
        with self.changed:
            session = self._open()
            query = self._query(session, query_id)
            if query.id in session.answers.answers:
                raise RequestError(HTTPStatus.CONFLICT, f"query {query.id} is already answered (undo it first)")
            if session.complete:
                raise RequestError(HTTPStatus.CONFLICT, "the session's label budget is spent")
            if not query.shown:
                raise RequestError(HTTPStatus.CONFLICT, f"query {query.id} has not been shown on the page yet")
            label, mask = to_label(answer, query.left)
            record = {
                "kind": "answer",
                **query.record,
                "left": query.left,
                "answer": answer,
                "label": label,
                "mask": mask,
                "labeller": self.labeller,
                "shown_at": shown_at,
                "answered_at": answered_at,
                "written_at": now(),
            }
            self.labels.append(record)
            session.answers.apply(record)
            self.changed.notify_all()

    def undo(self, body: dict[str, Any]) -> None:
        query_id = _text(body, "query")
        with self.changed:
            session = self._open()
            query = self._query(session, query_id)
            if not session.answers.order or session.answers.order[-1] != query.id:
                raise RequestError(HTTPStatus.CONFLICT, f"{query.id} is not the session's last answer")
            record = {"kind": "undo", "round": session.round, "query": query.id, "labeller": self.labeller}
            record["written_at"] = now()
            self.labels.append(record)
            session.answers.apply(record)
            self.changed.notify_all()

    def finish(self, body: dict[str, Any]) -> None:
        del body  # Unused: nothing to say but "finish".
        with self.changed:
            session = self._open()
            if not session.complete:
                left = len(session.queries) - len(session.answers.answers)
                raise RequestError(HTTPStatus.CONFLICT, f"{left} queries are still unanswered")
            self._close("budget" if len(session.answers.answers) < len(session.queries) else "finished")
