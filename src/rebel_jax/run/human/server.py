"""The labelling page's HTTP server: the standard library's ``ThreadingHTTPServer``, on loopback by default.

Routes (JSON in and out):

- ``GET /``, ``GET /static/<file>``: the page (plain HTML, JS and CSS in ``static/``, no build step).
- ``GET /api/state``: what the page shows (training status, the open session's queries, answers so far).
- ``GET /clips/<query id>/<left|right>``: a clip's sheet of frames (see :mod:`rebel_jax.run.human.clips`).
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
import hmac
import ipaddress
import json
import pathlib
import re
import socket
import sys
import threading
import urllib.parse
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from rebel_jax.run.human.labelling import (  # noqa: F401 - re-exported: the sessions the server serves
    Labelling,
    Query,
    RequestError,
    Session,
    _short,
    parse_body,
)
from rebel_jax.run.human.labels import LabelError

STATIC = pathlib.Path(__file__).parent / "static"
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css"}
_MAX_BODY = 64 * 1024
_SECURITY_HEADERS = (
    ("Cache-Control", "no-store"),
    ("X-Content-Type-Options", "nosniff"),
    ("X-Frame-Options", "DENY"),  # No other site may frame the page (and make the labeller click in it).
    ("Referrer-Policy", "no-referrer"),
)


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
