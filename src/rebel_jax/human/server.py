"""The labelling page's HTTP server: the standard library's ``ThreadingHTTPServer``, on loopback by default.

Routes (JSON in and out):

- ``GET /``, ``GET /static/<file>``: the page (plain HTML, JS and CSS in ``static/``, no build step).
- ``GET /api/state``: what the page shows (training status, the open session's queries, answers so far).
- ``GET /clips/<query id>/<left|right>``: a clip's sheet of frames (see :mod:`rebel_jax.human.clips`).
- ``POST /api/answer`` ``{"query", "answer", "shown_at", "answered_at"}``: one answer (``left``,
  ``right``, ``equal``, ``skip``); the client times are milliseconds since the epoch.
- ``POST /api/undo`` ``{"query"}``: withdraws the session's last answer, which must be ``query``.
- ``POST /api/finish``: closes a session whose queries are all answered (or whose budget is spent).

Errors answer ``{"error": ...}`` with 400 (malformed request), 404 (unknown query or path) or 409
(the session is closed, the query is already answered, the undo is not of the last answer).
Every accepted answer is in ``labels.jsonl`` (fsync-ed) before the response is sent.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import pathlib
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from rebel_jax.human.labels import ANSWERS, LabelError, LabelFile, SessionAnswers, now, to_label

STATIC = pathlib.Path(__file__).parent / "static"
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css"}
_MAX_BODY = 64 * 1024


class RequestError(Exception):
    def __init__(self, status: HTTPStatus, message: str):
        super().__init__(message)
        self.status = status


@dataclasses.dataclass
class Query:
    """One pair as the page sees it (``record`` holds what goes into its answer's line)."""

    id: str
    index: int
    left: str  # "a" or "b": which segment is on the left
    record: dict[str, Any]  # segment indices, scripted answer, ... (not sent to the page)
    clips: dict[str, tuple[bytes, str]] = dataclasses.field(default_factory=dict)  # side -> (image, mime)


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


def _iso(ms: Any) -> str | None:
    if ms is None:
        return None
    if not isinstance(ms, int | float) or isinstance(ms, bool):
        raise RequestError(HTTPStatus.BAD_REQUEST, f"a time must be milliseconds since the epoch, not {ms!r}")
    return datetime.datetime.fromtimestamp(ms / 1000, datetime.UTC).isoformat(timespec="milliseconds")


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

    def set_done(self) -> None:
        with self.changed:
            self.status, self.session = "done", None
            self.changed.notify_all()

    def _close(self, reason: str) -> None:
        session = self.session
        self.labels.append({"kind": "close", "round": session.round, "reason": reason, "written_at": now()})
        session.closed = reason
        self.changed.notify_all()

    # -- the page's side -------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        with self.changed:
            out = {
                "status": self.status,
                "round": self.round,
                "num_rounds": self.num_rounds,
                "instruction": self.instruction,
                "labeller": self.labeller,
                "budget": self.budget,
                "used": self.used,
                "session": None,
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
        raise RequestError(HTTPStatus.NOT_FOUND, f"unknown query id {query_id!r} in the open session")

    def clip(self, query_id: str, side: str) -> tuple[bytes, str]:
        with self.changed:
            session = self.session
            if session is None:
                raise RequestError(HTTPStatus.NOT_FOUND, "no feedback session is open")
            query = self._query(session, query_id)
            if side not in ("left", "right"):
                raise RequestError(HTTPStatus.NOT_FOUND, f"side must be left or right, not {side!r}")
            if not query.clips:
                raise RequestError(HTTPStatus.NOT_FOUND, f"the clips of {query_id} are not rendered yet")
            return query.clips[side]

    def answer(self, body: dict[str, Any]) -> None:
        answer = body.get("answer")
        if answer not in ANSWERS:
            raise RequestError(HTTPStatus.BAD_REQUEST, f"answer must be one of {', '.join(ANSWERS)}, not {answer!r}")
        shown_at, answered_at = _iso(body.get("shown_at")), _iso(body.get("answered_at"))
        with self.changed:
            session = self._open()
            query = self._query(session, body.get("query"))
            if query.id in session.answers.answers:
                raise RequestError(HTTPStatus.CONFLICT, f"query {query.id} is already answered (undo it first)")
            if session.complete:
                raise RequestError(HTTPStatus.CONFLICT, "the session's label budget is spent")
            if not query.clips:
                raise RequestError(HTTPStatus.CONFLICT, f"query {query.id} has not been shown yet")
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
        with self.changed:
            session = self._open()
            query = self._query(session, body.get("query"))
            if not session.answers.order or session.answers.order[-1] != query.id:
                raise RequestError(HTTPStatus.CONFLICT, f"{query.id} is not the session's last answer")
            record = {"kind": "undo", "round": session.round, "query": query.id, "labeller": self.labeller}
            record["written_at"] = now()
            self.labels.append(record)
            session.answers.apply(record)
            self.changed.notify_all()

    def finish(self) -> None:
        with self.changed:
            session = self._open()
            if not session.complete:
                left = len(session.queries) - len(session.answers.answers)
                raise RequestError(HTTPStatus.CONFLICT, f"{left} queries are still unanswered")
            self._close("budget" if len(session.answers.answers) < len(session.queries) else "finished")


def _handler(labelling: Labelling) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "rebel_jax-human"

        def log_message(self, format, *args):  # noqa: A002 - the base class's name
            del format, args  # Unused: requests are not logged (the page polls).

        def _send(self, status: int, body: bytes, mime: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", mime)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, status: int, data: Any) -> None:
            self._send(status, json.dumps(data).encode(), "application/json")

        def _route(self, method: str) -> None:
            try:
                path = self.path.split("?", 1)[0]
                if method == "GET":
                    if path in ("/", "/index.html"):
                        return self._send(200, (STATIC / "index.html").read_bytes(), _TYPES[".html"])
                    if path.startswith("/static/"):
                        name = path.removeprefix("/static/")
                        file = STATIC / name
                        if "/" in name or name.startswith(".") or not file.is_file():
                            raise RequestError(HTTPStatus.NOT_FOUND, f"no file {path}")
                        return self._send(200, file.read_bytes(), _TYPES.get(file.suffix, "application/octet-stream"))
                    if path == "/api/state":
                        return self._json(200, labelling.state())
                    parts = path.strip("/").split("/")
                    if len(parts) == 3 and parts[0] == "clips":
                        image, mime = labelling.clip(parts[1], parts[2])
                        return self._send(200, image, mime)
                    raise RequestError(HTTPStatus.NOT_FOUND, f"no page {path}")
                actions = {"/api/answer": labelling.answer, "/api/undo": labelling.undo}
                if path == "/api/finish":
                    labelling.finish()
                    return self._json(200, labelling.state())
                if path not in actions:
                    raise RequestError(HTTPStatus.NOT_FOUND, f"no action {path}")
                actions[path](self._body())
                return self._json(200, labelling.state())
            except RequestError as err:
                return self._json(err.status, {"error": str(err)})
            except LabelError as err:
                return self._json(HTTPStatus.BAD_REQUEST, {"error": str(err)})

        def _body(self) -> dict[str, Any]:
            try:
                length = int(self.headers.get("Content-Length", "0"))
            except ValueError as err:
                raise RequestError(HTTPStatus.BAD_REQUEST, "bad Content-Length") from err
            if not 0 < length <= _MAX_BODY:
                raise RequestError(HTTPStatus.BAD_REQUEST, f"a JSON body of 1 to {_MAX_BODY} bytes is required")
            try:
                body = json.loads(self.rfile.read(length))
            except ValueError as err:
                raise RequestError(HTTPStatus.BAD_REQUEST, f"the body is not JSON: {err}") from err
            if not isinstance(body, dict):
                raise RequestError(HTTPStatus.BAD_REQUEST, "the body must be a JSON object")
            return body

        def do_GET(self):  # noqa: N802 - http.server's name
            self._route("GET")

        def do_POST(self):  # noqa: N802 - http.server's name
            self._route("POST")

    return Handler


class Server:
    """Serves ``labelling`` on ``host:port`` from a daemon thread (port 0: any free port)."""

    def __init__(self, labelling: Labelling, host: str = "127.0.0.1", port: int = 0):
        self.httpd = ThreadingHTTPServer((host, port), _handler(labelling))
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="labelling-page", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{port}/"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)
