"""The labelling page's HTTP server: the standard library's ``ThreadingHTTPServer``, on loopback by default.

Routes (JSON in and out):

- ``GET /``, ``GET /static/<file>``: the page (plain HTML, JS and CSS in ``static/``, no build step).
- ``GET /api/state``: what the page shows (training status, the open session's queries, answers so far).
- ``GET /clips/<query id>/<left|right>``: a clip's sheet of frames (see :mod:`rebel_jax.human.clips`).
- ``POST /api/shown`` ``{"query"}``: the page shows the query's clips; only a shown query can be answered.
- ``POST /api/answer`` ``{"query", "answer", "shown_at", "answered_at"}``: one answer (``left``,
  ``right``, ``equal``, ``skip``); the client times are milliseconds since the epoch.
- ``POST /api/undo`` ``{"query"}``: withdraws the session's last answer, which must be ``query``.
- ``POST /api/finish`` ``{}``: closes a session whose queries are all answered (or whose budget is spent).

Who may call them (:class:`Access`) follows Jupyter's server, cited below at
jupyter-server/jupyter_server@9a4d6eea2b16815a493b11fffe0b51b1fe55a81b:

- every ``/api/*`` and ``/clips/*`` request carries the run's token, as ``Authorization: token T`` or
  ``?token=T`` (the two ways of ``jupyter_server/auth/identity.py:468``); the page and its static files
  need none, and say so when the API refuses them;
- on a loopback bind, the ``Host`` header must name a loopback address or ``localhost`` (the check
  against DNS rebinding of ``jupyter_server/base/handlers.py:556``); a bind to another address turns
  the check off, as ``ServerApp.allow_remote_access`` defaults to on there (``jupyter_server/serverapp.py:1370``),
  and the token (never empty there) is the guard;
- a POST with an ``Origin`` header must come from the page's own origin (``Origin``'s host and port
  equal ``Host``, ``jupyter_server/base/handlers.py:437``), and must send ``Content-Type:
  application/json``: a cross-origin JSON POST needs a CORS preflight, and the server answers
  ``OPTIONS`` with 403 (no ``Access-Control-Allow-*`` header is ever sent).

Errors answer one JSON line ``{"error": ...}``: 400 (malformed request), 403 (refused: token, host,
origin, preflight), 404 (unknown query or path), 409 (the session is closed, the query is already
answered or not shown yet, the undo is not of the last answer), 415 (not JSON). A request the server
cannot read gets its status too; nothing a client sends prints a traceback or stops the server.
Every accepted answer is in ``labels.jsonl`` (fsync-ed) before the response is sent.
"""

from __future__ import annotations

import dataclasses
import datetime
import hmac
import ipaddress
import json
import math
import pathlib
import re
import socket
import sys
import threading
import time
import urllib.parse
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from rebel_jax.human.labels import ANSWERS, LabelError, LabelFile, SessionAnswers, now, to_label

STATIC = pathlib.Path(__file__).parent / "static"
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css"}
_MAX_BODY = 64 * 1024
_EARLIEST_MS, _LATEST_MS = 946_684_800_000, 4_102_444_800_000  # 2000-01-01 and 2100-01-01 UTC
_FAREWELL_S = 2.0  # At the end of a run, how long an open page is given to read that it is over.
_SECURITY_HEADERS = (
    ("Cache-Control", "no-store"),
    ("X-Content-Type-Options", "nosniff"),
    ("X-Frame-Options", "DENY"),  # No other site may frame the page (and make the labeller click in it).
    ("Referrer-Policy", "no-referrer"),
)


class RequestError(Exception):
    """A request the page's API refuses: its HTTP status and a one-line message."""

    def __init__(self, status: HTTPStatus, message: str):
        super().__init__(message)
        self.status = status


def _short(value: Any, limit: int = 60) -> str:
    """``repr(value)``, cut to ``limit`` characters (a client's value quoted in an error)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) can be reached only from this machine.

    A name counts when it is ``localhost`` or every address it resolves to is loopback (as
    ``jupyter_server/serverapp.py:1370`` decides whether to check the Host header).
    """
    name = host.strip().strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(name, None, 0, socket.SOCK_STREAM)
    except (OSError, UnicodeError):
        return False
    addresses = {info[4][0].split("%")[0] for info in infos}
    return bool(addresses) and all(ipaddress.ip_address(a).is_loopback for a in addresses)


def host_name(header: str) -> str:
    """The name in a ``Host`` header: without its port and an IPv6 address's brackets, lower case."""
    match = re.match(r"^(.*?)(:\d+)?$", header.strip().lower())  # As jupyter_server/base/handlers.py:565.
    name = match.group(1) if match else ""
    return name[1:-1] if name.startswith("[") and name.endswith("]") else name


@dataclasses.dataclass(frozen=True)
class Access:
    """Who may use the page's API.

    Attributes:
      token: what each ``/api/*`` and ``/clips/*`` request must carry; empty: no token (loopback only).
      check_host: only loopback names in the ``Host`` header (a loopback bind); False for another bind.
    """

    token: str
    check_host: bool

    def host_allowed(self, header: str | None) -> bool:
        """Whether a request with this ``Host`` header is served (every request, the page's files too)."""
        if not self.check_host:
            return True
        if not header:
            return False
        name = host_name(header)
        if name == "localhost":
            return True
        try:
            return ipaddress.ip_address(name).is_loopback
        except ValueError:
            return False

    def token_given(self, path: str, authorization: str | None) -> bool:
        """Whether the request's ``?token=`` or ``Authorization: token T`` header holds the token."""
        if not self.token:
            return True
        given = urllib.parse.parse_qs(urllib.parse.urlsplit(path).query).get("token", [""])[0]
        match = re.fullmatch(r"(?:token|bearer)\s+(\S+)", (authorization or "").strip(), re.IGNORECASE)
        if not given and match:
            given = match.group(1)
        return hmac.compare_digest(given.encode(), self.token.encode())

    @staticmethod
    def origin_allowed(origin: str | None, host: str | None) -> bool:
        """Whether a POST's ``Origin`` is the page's own (absent: a script, not a page; allowed)."""
        if origin is None:
            return True
        netloc = urllib.parse.urlsplit(origin.strip().lower()).netloc
        return bool(host) and netloc == host.strip().lower()


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


def _note(text: str) -> None:
    """One line on the trainer's console about the page's server (never a traceback)."""
    print(f"human feedback: {text}", file=sys.stderr, flush=True)


def _handler(labelling: Labelling, access: Access) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        server_version = "rebel_jax-human"
        timeout = 30  # seconds a client may take to send its request (a body it announced and never sent)

        def log_message(self, format, *args):  # noqa: A002 - the base class's name
            del format, args  # Unused: requests are not logged (the page polls; a URL may hold the token).

        def _send(self, status: int, body: bytes, mime: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", mime)
            self.send_header("Content-Length", str(len(body)))
            for name, value in _SECURITY_HEADERS:
                self.send_header(name, value)
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _json(self, status: int, data: Any) -> None:
            self._send(status, json.dumps(data).encode(), "application/json")

        def send_error(self, code, message=None, explain=None):
            """http.server's own refusals (a bad request line, headers too long, an unknown method): JSON too."""
            del explain  # Unused: the one-line message says it.
            self.close_connection = True
            self.request_version = "HTTP/1.0"  # Not 0.9 (http.server's guess for a garbled line): headers too.
            try:
                phrase = HTTPStatus(code).phrase
            except ValueError:
                phrase = "error"
            text = " ".join(str(message or phrase).split())
            self._json(code, {"error": f"{phrase.lower()}: {text}" if message else phrase.lower()})

        def _guard(self, method: str, path: str) -> None:
            """Refuses a request from a foreign Host, without the token, or a POST of a foreign page."""
            host = self.headers.get("Host")
            if not access.host_allowed(host):
                raise RequestError(
                    HTTPStatus.FORBIDDEN,
                    f"Host {_short(host)} is not this machine's loopback: open the page at 127.0.0.1 or localhost",
                )
            if not path.startswith(("/api/", "/clips/")):
                return
            if not access.token_given(self.path, self.headers.get("Authorization")):
                raise RequestError(
                    HTTPStatus.FORBIDDEN,
                    "this page needs the run's token: open the URL the trainer printed (?token=...)",
                )
            if method != "POST":
                return
            if not access.origin_allowed(self.headers.get("Origin"), host):
                raise RequestError(
                    HTTPStatus.FORBIDDEN, f"Origin {_short(self.headers.get('Origin'))} is not this page's"
                )
            mime = self.headers.get("Content-Type", "").split(";", 1)[0].strip().lower()
            if mime != "application/json":
                raise RequestError(
                    HTTPStatus.UNSUPPORTED_MEDIA_TYPE, f"Content-Type must be application/json, not {_short(mime)}"
                )

        def _route(self, method: str) -> None:
            path = urllib.parse.urlsplit(self.path).path
            self.body_read = False
            try:
                self._guard(method, path)
                if method == "GET":
                    return self._get(path)
                actions = {
                    "/api/shown": labelling.shown,
                    "/api/answer": labelling.answer,
                    "/api/undo": labelling.undo,
                    "/api/finish": labelling.finish,
                }
                if path not in actions:
                    raise RequestError(HTTPStatus.NOT_FOUND, f"no action {_short(path)}")
                actions[path](parse_body(self._body()))
                return self._json(200, labelling.state())
            except RequestError as err:
                self._discard_body()
                return self._json(err.status, {"error": str(err)})
            except LabelError as err:
                return self._json(HTTPStatus.BAD_REQUEST, {"error": " ".join(str(err).split())})
            except (ConnectionError, TimeoutError):
                self.close_connection = True  # The page went away, or stopped sending: nobody to answer.
            except Exception as err:  # A fault of the server's: one line on the console, the server goes on.
                _note(f"{method} {path} failed: {type(err).__name__}: {' '.join(str(err).split())}")
                return self._json(HTTPStatus.INTERNAL_SERVER_ERROR, {"error": f"internal error: {type(err).__name__}"})

        def _get(self, path: str) -> None:
            if path in ("/", "/index.html"):
                return self._send(200, (STATIC / "index.html").read_bytes(), _TYPES[".html"])
            if path.startswith("/static/"):
                name = path.removeprefix("/static/")
                file = STATIC / name
                if "/" in name or name.startswith(".") or not file.is_file():
                    raise RequestError(HTTPStatus.NOT_FOUND, f"no file {_short(path)}")
                return self._send(200, file.read_bytes(), _TYPES.get(file.suffix, "application/octet-stream"))
            if path == "/api/state":
                return self._json(200, labelling.state())
            parts = path.strip("/").split("/")
            if len(parts) == 3 and parts[0] == "clips":
                image, mime = labelling.clip(urllib.parse.unquote(parts[1]), parts[2])
                return self._send(200, image, mime)
            raise RequestError(HTTPStatus.NOT_FOUND, f"no page {_short(path)}")

        def _discard_body(self) -> None:
            """Reads a refused POST's body, so that closing the connection does not reset it before the reply."""
            if self.command != "POST" or self.body_read:
                return
            try:
                length = int(self.headers.get("Content-Length", "0"))
                if 0 < length <= _MAX_BODY:
                    self.rfile.read(length)
            except (ValueError, OSError):
                pass

        def _body(self) -> bytes:
            self.body_read = True
            try:
                length = int(self.headers.get("Content-Length", "0"))
            except ValueError as err:
                raise RequestError(HTTPStatus.BAD_REQUEST, "bad Content-Length") from err
            if not 0 < length <= _MAX_BODY:
                raise RequestError(HTTPStatus.BAD_REQUEST, f"a JSON body of 1 to {_MAX_BODY} bytes is required")
            return self.rfile.read(length)

        def do_GET(self):  # noqa: N802 - http.server's name
            self._route("GET")

        def do_POST(self):  # noqa: N802 - http.server's name
            self._route("POST")

        def do_OPTIONS(self):  # noqa: N802 - http.server's name
            # A CORS preflight: refused, so that no other origin may POST JSON here.
            self._json(HTTPStatus.FORBIDDEN, {"error": "cross-origin requests are not allowed"})

    return Handler


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    request_queue_size = 64  # socketserver's 5 resets connections when a few tabs and clients ask at once

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler]):
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, handler)

    def handle_error(self, request, client_address):
        """What escaped a request's handler: one line on the console (none for a client gone away)."""
        del request  # Unused.
        err = sys.exc_info()[1]
        if not isinstance(err, ConnectionError | TimeoutError):
            _note(f"a request from {client_address[0]} failed: {type(err).__name__}: {err}")


def machine_addresses() -> list[str]:
    """This machine's name and its IPv4 addresses but loopback (where a page bound to 0.0.0.0 is reached)."""
    name = socket.gethostname()
    found = []
    try:
        found += [info[4][0] for info in socket.getaddrinfo(name, None, socket.AF_INET, socket.SOCK_STREAM)]
    except OSError:
        pass
    try:  # The address of the interface with the default route (connecting a UDP socket sends nothing).
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))  # TEST-NET-1 (RFC 5737): routed like any outside address
            found.append(probe.getsockname()[0])
    except OSError:
        pass
    addresses = [a for a in dict.fromkeys(found) if not ipaddress.ip_address(a).is_loopback]
    return [name, *addresses]


class Server:
    """Serves ``labelling`` on ``host:port`` from a daemon thread (port 0: any free port).

    Args:
      labelling: the state the page shows and changes.
      host: the address to bind (loopback by default; another one exposes the page to that network).
      port: the port (0: any free one).
      token: what the API's requests must carry; empty: none (refused unless ``host`` is loopback).
    """

    def __init__(self, labelling: Labelling, host: str = "127.0.0.1", port: int = 0, token: str = ""):
        loopback = is_loopback(host)
        if not token and not loopback:
            raise ValueError(f"the labelling page on {host} (not loopback) needs a token: an empty one is refused")
        self.host, self.token, self.loopback = host, token, loopback
        self.access = Access(token=token, check_host=loopback)
        self.httpd = _HTTPServer((host, port), _handler(labelling, self.access))
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="labelling-page", daemon=True)
        self.thread.start()

    @property
    def port(self) -> int:
        return self.httpd.server_address[1]

    @property
    def wildcard(self) -> bool:
        """Bound to every interface (0.0.0.0 or ::)."""
        return self.host in ("0.0.0.0", "::", "")

    @property
    def url(self) -> str:
        """The page's address without the token (loopback for a wildcard bind)."""
        return self._url(
            ("::1" if self.host == "::" else "127.0.0.1") if self.wildcard else self.httpd.server_address[0]
        )

    def urls(self) -> list[str]:
        """Where to open the page, token included: the bound address; for a wildcard bind, this machine's
        name and addresses, then loopback (``jupyter_server/serverapp.py:2433`` names the host for 0.0.0.0)."""
        hosts = [*machine_addresses(), "::1" if self.host == "::" else "127.0.0.1"] if self.wildcard else None
        hosts = hosts or [self.httpd.server_address[0]]
        query = "?" + urllib.parse.urlencode({"token": self.token}) if self.token else ""
        return [self._url(host) + query for host in hosts]

    def _url(self, host: str) -> str:
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}/"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(timeout=5)
