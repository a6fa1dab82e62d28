"""The human teacher without JAX: the answer -> label table, labels.jsonl (append, torn line, resume),
the page's HTTP API (answers, undo, budget, bad requests), who may call it (token, Host, Origin,
Content-Type, shown queries), and the command line's checks."""

from __future__ import annotations

import json
import math
import pathlib
import socket
import threading
import urllib.error
import urllib.parse
import urllib.request

import pytest

from rebel_jax.run.human.labels import LabelError, LabelFile, SessionAnswers, query_id, to_label
from rebel_jax.run.human.server import Access, Labelling, Query, Server, Session, host_name, is_loopback
from rebel_jax.run.human.session import hide_token, page_lines, redact_token

TOKEN = "0123abcd" * 6  # what the page fixture's server asks for

# Written out by hand: (answer, segment shown on the left) -> (P(b preferred), mask).
TABLE = [
    ("left", "a", 0.0, 1.0),
    ("left", "b", 1.0, 1.0),
    ("right", "a", 1.0, 1.0),
    ("right", "b", 0.0, 1.0),
    ("equal", "a", 0.5, 1.0),
    ("equal", "b", 0.5, 1.0),
    ("skip", "a", 0.0, 0.0),
    ("skip", "b", 0.0, 0.0),
]


@pytest.mark.parametrize(("answer", "left", "label", "mask"), TABLE)
def test_answer_to_label(answer, left, label, mask):
    assert to_label(answer, left) == (label, mask)


@pytest.mark.parametrize(("answer", "left"), [("up", "a"), ("", "a"), (None, "b"), ("left", "c"), ("right", None)])
def test_bad_answers_are_rejected(answer, left):
    with pytest.raises(LabelError, match="invalid"):
        to_label(answer, left)


def _answer(round_index: int, index: int, answer: str, left: str = "a") -> dict:
    label, mask = to_label(answer, left)
    return {
        "kind": "answer",
        "round": round_index,
        "query": query_id(round_index, index),
        "left": left,
        "answer": answer,
        "label": label,
        "mask": mask,
    }


def test_label_file_round_trip_and_resume(tmp_path):
    path = tmp_path / "labels.jsonl"
    labels = LabelFile(path)
    written = [_answer(1, 0, "left"), _answer(1, 1, "skip"), {"kind": "undo", "round": 1, "query": "r1-q1"}]
    written += [_answer(1, 1, "equal", "b"), {"kind": "close", "round": 1, "reason": "finished"}]
    for record in written:
        labels.append(record)
    lines = path.read_text().splitlines()
    assert [json.loads(line) for line in lines] == written  # One line per record, in order.
    again = LabelFile(path)  # What --resume reads.
    assert again.records == written
    session = again.session(1)
    assert session.order == ["r1-q0", "r1-q1"]
    assert session.answers["r1-q1"]["answer"] == "equal"  # The undone skip is gone.
    assert session.kept == 2 and session.closed["reason"] == "finished"
    assert again.session(2).answers == {}


def test_torn_last_line_is_moved_aside_and_the_file_repaired(tmp_path, capsys):
    path = tmp_path / "labels.jsonl"
    labels = LabelFile(path)
    labels.append(_answer(3, 0, "right"))
    labels.append(_answer(3, 1, "left", "b"))
    whole = path.read_bytes()
    torn = json.dumps(_answer(3, 2, "skip")).encode()[:17]  # A crash in the middle of a write.
    path.write_bytes(whole + torn)
    again = LabelFile(path)
    assert [r["query"] for r in again.records] == ["r3-q0", "r3-q1"]
    assert path.read_bytes() == whole  # Cut back to the last whole line ...
    assert (tmp_path / "labels.jsonl.torn").read_bytes() == torn + b"\n"  # ... the torn bytes kept aside.
    assert "torn last line" in capsys.readouterr().err
    again.append(_answer(3, 2, "equal"))
    assert [r["query"] for r in LabelFile(path).records] == ["r3-q0", "r3-q1", "r3-q2"]


def test_a_whole_last_line_without_its_newline_is_kept(tmp_path):
    path = tmp_path / "labels.jsonl"
    path.write_text(json.dumps(_answer(1, 0, "left")) + "\n" + json.dumps(_answer(1, 1, "right")))
    labels = LabelFile(path)
    assert [r["query"] for r in labels.records] == ["r1-q0", "r1-q1"]
    assert path.read_text().endswith("}\n")
    labels.append(_answer(1, 2, "skip"))
    assert len(LabelFile(path).records) == 3


def test_a_damaged_middle_line_is_an_error(tmp_path):
    path = tmp_path / "labels.jsonl"
    path.write_text(json.dumps(_answer(1, 0, "left")) + "\n{oops\n" + json.dumps(_answer(1, 1, "left")) + "\n")
    with pytest.raises(LabelError, match=r"labels.jsonl:2"):
        LabelFile(path)


def test_replay_file_is_read_only_and_must_exist(tmp_path):
    with pytest.raises(LabelError, match="does not exist"):
        LabelFile(tmp_path / "missing.jsonl", writable=False)
    path = tmp_path / "labels.jsonl"
    LabelFile(path).append(_answer(1, 0, "left"))
    with pytest.raises(LabelError, match="read-only"):
        LabelFile(path, writable=False).append(_answer(1, 1, "left"))


def test_journal_rules():
    session = SessionAnswers()
    session.apply(_answer(1, 0, "left"))
    with pytest.raises(LabelError, match="answered twice"):
        session.apply(_answer(1, 0, "right"))
    session.apply(_answer(1, 1, "skip"))
    with pytest.raises(LabelError, match="not the session's last answer"):
        session.apply({"kind": "undo", "round": 1, "query": "r1-q0"})
    assert session.kept == 1  # The skip does not count against the budget.


# -- the page's API, on a hand-made session (no trainer) -----------------------------------------


def _call(url: str, path: str, body=None, raw: bytes | None = None, token: str = TOKEN) -> tuple[int, dict]:
    """The page's own request: the token in its header, JSON for a POST."""
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    request = urllib.request.Request(url + path.lstrip("/"), data=data, method="GET" if data is None else "POST")
    if token:
        request.add_header("Authorization", f"token {token}")
    if data is not None:
        request.add_header("Content-Type", "application/json")
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read())


def _exchange(url: str, request: bytes) -> tuple[bytes, bytes]:
    """Sends ``request`` as typed (as curl would, or worse); the response's head and body."""
    host, port = urllib.parse.urlsplit(url).netloc.rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=10) as conn:
        conn.sendall(request)
        conn.shutdown(socket.SHUT_WR)
        data = b""
        while chunk := conn.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    return head, body


def _raw(url: str, request: bytes) -> tuple[int, dict]:
    """The status and the JSON reply (every reply of the API is JSON, refusals included) of ``request``."""
    head, body = _exchange(url, request)
    assert b"content-type: application/json" in head.lower(), head
    return int(head.split(b" ", 2)[1]), json.loads(body)


def _post(url: str, path: str, body: bytes, headers: dict[str, str]) -> tuple[int, dict]:
    """A hand-made POST: exactly these headers (Host, Content-Length added unless given)."""
    netloc = urllib.parse.urlsplit(url).netloc
    lines = [f"POST {path} HTTP/1.1"]
    given = {k.lower() for k in headers}
    if "host" not in given:
        lines.append(f"Host: {netloc}")
    if "content-length" not in given:
        lines.append(f"Content-Length: {len(body)}")
    lines += [f"{k}: {v}" for k, v in headers.items()]
    return _raw(url, ("\r\n".join(lines) + "\r\n\r\n").encode() + body)


def _show(url: str, *ids: str) -> None:
    """The page reports each query shown (what it does once both clips are on screen)."""
    for query in ids:
        assert _call(url, "/api/shown", {"query": query})[0] == 200


@pytest.fixture
def page(tmp_path):
    labels = LabelFile(tmp_path / "labels.jsonl")
    labelling = Labelling(labels, "tester", "Which is better?", budget=10, num_rounds=5)
    server = Server(labelling, "127.0.0.1", 0, token=TOKEN)
    yield labelling, server.url, tmp_path / "labels.jsonl"
    server.close()


def _open(labelling: Labelling, remaining: int, lefts=("a", "b", "a")) -> Session:
    queries = [
        Query(query_id(2, i), i, left, {"round": 2, "query": query_id(2, i), "index": i})
        for i, left in enumerate(lefts)
    ]
    session = Session(2, queries, SessionAnswers(), remaining, fps=10.0, frames=5)
    labelling.open_session(session, used=10 - remaining)
    for q in queries:
        labelling.add_clips(q, {"left": (b"L" + q.id.encode(), "image/png"), "right": (b"R", "image/png")})
    return session


def test_page_answers_undo_and_finish(page):
    labelling, url, path = page
    status, state = _call(url, "/api/state")
    assert status == 200 and state["status"] == "starting" and state["session"] is None
    session = _open(labelling, remaining=10)
    with urllib.request.urlopen(url + f"clips/r2-q1/left?token={TOKEN}", timeout=10) as response:
        assert response.read() == b"Lr2-q1"
    _show(url, "r2-q0", "r2-q1", "r2-q2")
    status, state = _call(url, "/api/answer", {"query": "r2-q0", "answer": "right", "shown_at": 1.7e12})
    assert status == 200 and state["session"]["queries"][0]["answer"] == "right"
    assert _call(url, "/api/answer", {"query": "r2-q1", "answer": "skip"})[0] == 200
    status, state = _call(url, "/api/undo", {"query": "r2-q1"})
    assert status == 200 and state["session"]["last"] == "r2-q0"
    assert _call(url, "/api/answer", {"query": "r2-q1", "answer": "left"})[0] == 200
    assert _call(url, "/api/finish", {})[0] == 409  # r2-q2 is unanswered.
    assert _call(url, "/api/answer", {"query": "r2-q2", "answer": "equal"})[0] == 200
    assert _call(url, "/api/finish", {})[0] == 200
    assert labelling.wait(timeout=5) == "finished"
    records = [json.loads(line) for line in path.read_text().splitlines()]
    assert [(r["kind"], r.get("query"), r.get("answer")) for r in records] == [
        ("answer", "r2-q0", "right"),
        ("answer", "r2-q1", "skip"),
        ("undo", "r2-q1", None),
        ("answer", "r2-q1", "left"),
        ("answer", "r2-q2", "equal"),
        ("close", None, None),
    ]
    # q0 showed a on the left: "right" prefers b. q1 showed b on the left: "left" prefers b.
    assert [(r["label"], r["mask"]) for r in records if r["kind"] == "answer"] == [
        (1.0, 1.0),
        (0.0, 0.0),
        (1.0, 1.0),
    ] + [(0.5, 1.0)]
    assert records[0]["labeller"] == "tester" and records[0]["shown_at"].startswith("2023-")
    assert session.answers.kept == 3
    # The session is closed now: no more answers or undos.
    assert _call(url, "/api/answer", {"query": "r2-q0", "answer": "left"})[0] == 409
    assert _call(url, "/api/undo", {"query": "r2-q2"})[0] == 409


def test_page_rejects_bad_requests(page):
    labelling, url, path = page
    assert _call(url, "/api/answer", {"query": "r2-q0", "answer": "left"})[0] == 409  # No session yet.
    _open(labelling, remaining=10)
    _show(url, "r2-q0")
    bad = [
        ({"query": "r9-q9", "answer": "left"}, 404, "unknown query id"),
        ({"query": "r2-q0", "answer": "sideways"}, 400, "answer must be one of"),
        ({"query": "r2-q0", "answer": "left", "shown_at": "yesterday"}, 400, "milliseconds"),
    ]
    for body, status, message in bad:
        got, reply = _call(url, "/api/answer", body)
        assert got == status and message in reply["error"], (body, reply)
    for raw, message in [(b"{not json", "not JSON"), (b"[1, 2]", "JSON object")]:
        got, reply = _call(url, "/api/answer", raw=raw)
        assert got == 400 and message in reply["error"]
    assert _call(url, "/api/undo", {"query": "r2-q0"})[0] == 409  # Nothing to undo.
    assert _call(url, "/api/nothing", {})[0] == 404
    assert _call(url, "/static/../labels.py")[0] == 404
    assert path.read_text() == ""  # Nothing was written by the bad requests.


def test_budget_counts_answers_not_skips(page):
    labelling, url, _ = page
    session = _open(labelling, remaining=1, lefts=("a", "a", "b"))
    _show(url, "r2-q0", "r2-q1", "r2-q2")
    assert _call(url, "/api/answer", {"query": "r2-q0", "answer": "skip"})[0] == 200
    status, state = _call(url, "/api/state")
    assert state["used"] == 9 and not state["session"]["complete"]  # A skip costs nothing.
    status, state = _call(url, "/api/answer", {"query": "r2-q1", "answer": "left"})
    assert state["used"] == 10 and state["session"]["complete"]  # The budget is spent: nothing more is asked.
    got, reply = _call(url, "/api/answer", {"query": "r2-q2", "answer": "left"})
    assert got == 409 and "budget" in reply["error"]
    assert _call(url, "/api/finish", {})[0] == 200
    assert session.closed == "budget"


def test_session_timeout_closes_it(page):
    labelling, _, path = page
    _open(labelling, remaining=10)
    assert labelling.wait(timeout=0.2) == "timeout"
    assert json.loads(path.read_text().splitlines()[-1])["reason"] == "timeout"


# -- who may call the API: token, Host, Origin, Content-Type, shown queries -------------------------


def _nothing_written(path: pathlib.Path) -> bool:
    return path.read_text() == ""


def test_the_two_requests_of_a_foreign_page_are_refused(page):
    """A cross-site text/plain POST and a DNS-rebound one (curl's requests): refused, nothing written."""
    labelling, url, path = page
    _open(labelling, remaining=10)
    _show(url, "r2-q0", "r2-q1")  # Shown: only who asks is wrong.
    cross_site = {"Content-Type": "text/plain", "Origin": "http://evil.example"}
    got, reply = _post(url, "/api/answer", b'{"query":"r2-q0","answer":"left"}', cross_site)
    assert got == 403 and "token" in reply["error"]
    rebound = {"Host": f"attacker.example:{urllib.parse.urlsplit(url).port}", "Content-Type": "text/plain"}
    got, reply = _post(url, "/api/answer", b'{"query":"r2-q1","answer":"right"}', rebound)
    assert got == 403 and "Host" in reply["error"]
    # With the token (as if the attacker had it), each check still refuses on its own.
    auth = {"Authorization": f"token {TOKEN}"}
    body = b'{"query":"r2-q0","answer":"left"}'
    assert _post(url, "/api/answer", body, {**auth, **cross_site})[0] == 403  # the Origin
    assert _post(url, "/api/answer", body, {**auth, "Content-Type": "text/plain"})[0] == 415
    assert _post(url, "/api/answer", body, {**auth, **rebound, "Content-Type": "application/json"})[0] == 403
    assert _nothing_written(path) and labelling.session.answers.answers == {}


@pytest.mark.parametrize(
    ("method", "path"),
    [("GET", "/api/state"), ("GET", "/clips/r2-q0/left"), ("POST", "/api/answer"), ("POST", "/api/finish")],
)
@pytest.mark.parametrize("token", ["", "wrong", TOKEN[:-1], TOKEN + "0"])
def test_the_api_needs_the_token(page, method, path, token):
    labelling, url, path_labels = page
    _open(labelling, remaining=10)
    _show(url, "r2-q0")
    if method == "GET":
        got, reply = _call(url, path, token=token)
    else:
        got, reply = _call(url, path, {"query": "r2-q0", "answer": "left"}, token=token)
    assert got == 403 and "token" in reply["error"] and "\n" not in reply["error"]
    assert _nothing_written(path_labels)


def test_the_token_may_be_in_the_url_and_the_page_needs_none(page):
    labelling, url, _ = page
    assert _call(url, f"/api/state?token={TOKEN}", token="")[0] == 200  # Jupyter's two ways: ?token= ...
    assert _call(url, "/api/state")[0] == 200  # ... and Authorization: token T.
    for file in ("", "static/app.js", "static/style.css"):  # The page itself, which then asks for the token.
        with urllib.request.urlopen(url + file, timeout=10) as response:
            assert response.status == 200 and response.headers["X-Frame-Options"] == "DENY"


@pytest.mark.parametrize(
    ("host", "allowed"),
    [
        ("127.0.0.1:{port}", True),
        ("localhost:{port}", True),
        ("LOCALHOST", True),
        ("localhost:9000", True),  # An SSH tunnel's local port.
        ("127.0.0.2:{port}", True),
        ("[::1]:{port}", True),
        ("attacker.example:{port}", False),
        ("attacker.example", False),
        ("127.0.0.1.attacker.example:{port}", False),
        ("10.0.0.5:{port}", False),
        ("", False),
    ],
)
def test_host_header_on_a_loopback_bind(page, host, allowed):
    labelling, url, path = page
    port = urllib.parse.urlsplit(url).port
    header = f"Host: {host.format(port=port)}\r\n" if host else ""
    request = f"GET /api/state HTTP/1.1\r\n{header}Authorization: token {TOKEN}\r\n\r\n".encode()
    status, reply = _raw(url, request)
    assert status == (200 if allowed else 403), reply
    page_request = f"GET / HTTP/1.1\r\n{header}\r\n".encode()
    if not allowed:  # The page's files too: a rebound name reads nothing.
        assert _raw(url, page_request)[0] == 403


def test_host_names_and_loopback():
    assert [host_name(h) for h in ("LocalHost:80", "[::1]:8765", "127.0.0.1", "a.b:1:2")] == [
        "localhost",
        "::1",
        "127.0.0.1",
        "a.b:1",
    ]
    assert all(is_loopback(h) for h in ("127.0.0.1", "::1", "[::1]", "localhost", "127.1.2.3"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "::", "10.0.0.5", "192.168.1.1"))
    remote = Access(token=TOKEN, check_host=False)  # Bound to another address: any Host, the token guards.
    assert remote.host_allowed("gpu-box.lab:8765") and remote.host_allowed(None)
    assert not remote.token_given("/api/state", None) and remote.token_given("/api/state", f"Bearer {TOKEN}")
    with pytest.raises(ValueError, match="needs a token"):
        Server(Labelling(None, "x", "q", 1, 1), "0.0.0.0", 0, token="")  # Refused before binding.


@pytest.mark.parametrize(
    ("origin", "status"),
    [
        (None, 200),  # A script (curl, Python) sends none.
        ("http://127.0.0.1:{port}", 200),
        ("http://evil.example", 403),
        ("http://127.0.0.1:1", 403),
        ("http://localhost:{port}", 403),  # Another origin than the page's (Host: 127.0.0.1:port).
        ("null", 403),
    ],
)
def test_origin_of_a_post(page, origin, status):
    labelling, url, path = page
    _open(labelling, remaining=10)
    _show(url, "r2-q0")
    port = urllib.parse.urlsplit(url).port
    headers = {"Authorization": f"token {TOKEN}", "Content-Type": "application/json"}
    if origin is not None:
        headers["Origin"] = origin.format(port=port)
    got, reply = _post(url, "/api/answer", b'{"query": "r2-q0", "answer": "left"}', headers)
    assert got == status, reply
    assert _nothing_written(path) == (status != 200)


@pytest.mark.parametrize(
    ("content_type", "status"),
    [
        ("text/plain", 415),
        ("application/x-www-form-urlencoded", 415),
        ("multipart/form-data; boundary=x", 415),
        (None, 415),
        ("application/json; charset=utf-8", 200),
        ("Application/JSON", 200),
    ],
)
def test_content_type_of_a_post(page, content_type, status):
    labelling, url, path = page
    _open(labelling, remaining=10)
    _show(url, "r2-q0")
    headers = {"Authorization": f"token {TOKEN}"}
    if content_type is not None:
        headers["Content-Type"] = content_type
    got, reply = _post(url, "/api/answer", b'{"query": "r2-q0", "answer": "left"}', headers)
    assert got == status, reply
    assert _nothing_written(path) == (status != 200)


def test_a_preflight_is_refused(page):
    _, url, _ = page
    request = (
        b"OPTIONS /api/answer HTTP/1.1\r\nHost: 127.0.0.1\r\nOrigin: http://evil.example\r\n"
        b"Access-Control-Request-Method: POST\r\nAccess-Control-Request-Headers: content-type\r\n\r\n"
    )
    head, body = _exchange(url, request)
    assert head.split(b" ", 2)[1] == b"403" and b"access-control-allow" not in head.lower()
    assert "cross-origin" in json.loads(body)["error"]


def test_an_answer_counts_only_for_a_query_shown(page):
    labelling, url, path = page
    session = _open(labelling, remaining=10)
    got, reply = _call(url, "/api/answer", {"query": "r2-q1", "answer": "left"})
    assert got == 409 and "not been shown" in reply["error"]
    session.queries[2].clips = {}  # Not rendered yet: it cannot have been shown.
    got, reply = _call(url, "/api/shown", {"query": "r2-q2"})
    assert got == 409 and "not rendered" in reply["error"]
    assert _call(url, "/api/shown", {"query": "r9-q9"})[0] == 404
    assert _nothing_written(path)
    _show(url, "r2-q1")
    assert _call(url, "/api/answer", {"query": "r2-q1", "answer": "left"})[0] == 200


def _nested(depth: int) -> bytes:
    return b'{"query": ' + b"[" * depth + b"]" * depth + b"}"


MALFORMED = [
    (b'{"query": "r2-q0", "answer": "left", "shown_at": 1e300}', "shown_at"),
    (b'{"query": "r2-q0", "answer": "left", "shown_at": NaN}', "not a number"),
    (b'{"query": "r2-q0", "answer": "left", "shown_at": -Infinity}', "not a number"),
    (b'{"query": "r2-q0", "answer": "left", "shown_at": 1e400}', "out of range"),
    (b'{"query": "r2-q0", "answer": "left", "shown_at": -1e15}', "shown_at"),
    (b'{"query": "r2-q0", "answer": "left", "answered_at": 1e13}', "answered_at"),
    (b'{"query": "r2-q0", "answer": "left", "shown_at": true}', "shown_at"),
    (b'{"query": "r2-q0", "answer": "left", "shown_at": 1.8e12, "answered_at": 1.7e12}', "before"),
    (b'{"query": "r2-q0", "answer": "left", "shown_at": 1' + b"0" * 5000 + b"}", "not JSON"),
    (_nested(20_000), "nested too deeply"),
    (b"[" * 20_000 + b"]" * 20_000, "nested too deeply"),
    (_nested(3), "string or a number"),
    (b'{"query": ["r2-q0"], "answer": "left"}', "string or a number"),
    (b'{"query": 7, "answer": "left"}', "query must be a string"),
    (b'{"query": "r2-q0", "answer": null}', "answer must be a string"),
    (b'{"query": "r2-q0", "answer": "left"', "not JSON"),
    (b'\xff\xfe{"query": "r2-q0"}', "not JSON"),
    (b'"r2-q0"', "JSON object"),
]


@pytest.mark.parametrize(("body", "message"), MALFORMED)
def test_malformed_bodies_get_400_and_no_traceback(page, capfd, body, message):
    labelling, url, path = page
    _open(labelling, remaining=10)
    _show(url, "r2-q0")
    headers = {"Authorization": f"token {TOKEN}", "Content-Type": "application/json"}
    got, reply = _post(url, "/api/answer", body, headers)
    assert got == 400 and message in reply["error"] and "\n" not in reply["error"], reply
    assert _nothing_written(path)
    assert _call(url, "/api/state")[0] == 200  # The server is up.
    assert "Traceback" not in capfd.readouterr().err


@pytest.mark.parametrize(
    ("request_bytes", "status"),
    [
        (b"GARBAGE\r\n\r\n", 400),
        (b"GET / HTTP/9.9\r\n\r\n", 505),
        (b"GET /" + b"a" * 70_000 + b" HTTP/1.1\r\n\r\n", 414),
        (b"GET / HTTP/1.1\r\nX: " + b"a" * 70_000 + b"\r\n\r\n", 431),
        (b"DELETE /api/answer HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", 501),
        (
            b"POST /api/answer HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: token "
            + TOKEN.encode()
            + b"\r\nContent-Type: application/json\r\nContent-Length: -5\r\n\r\n",
            400,
        ),
        (
            b"POST /api/answer HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: token "
            + TOKEN.encode()
            + b"\r\nContent-Type: application/json\r\nContent-Length: many\r\n\r\n",
            400,
        ),
        (
            b"POST /api/answer HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: token "
            + TOKEN.encode()
            + b"\r\nContent-Type: application/json\r\nContent-Length: 999999999\r\n\r\n",
            400,
        ),
        (
            b"POST /api/answer HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: token "
            + TOKEN.encode()
            + b"\r\nContent-Type: application/json\r\n\r\n",
            400,
        ),  # No body.
    ],
)
def test_malformed_requests_get_a_json_status(page, capfd, request_bytes, status):
    labelling, url, path = page
    _open(labelling, remaining=10)
    got, reply = _raw(url, request_bytes)
    assert got == status and reply["error"] and "\n" not in reply["error"], reply
    assert _call(url, "/api/state")[0] == 200
    assert _nothing_written(path)
    assert "Traceback" not in capfd.readouterr().err


def test_one_of_twenty_simultaneous_answers_is_accepted(page):
    labelling, url, path = page
    _open(labelling, remaining=10)
    _show(url, "r2-q0")
    barrier, statuses = threading.Barrier(20), []

    def answer(i):
        barrier.wait()
        statuses.append(_call(url, "/api/answer", {"query": "r2-q0", "answer": ("left", "right")[i % 2]})[0])

    threads = [threading.Thread(target=answer, args=(i,)) for i in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert sorted(statuses) == [200] + [409] * 19
    assert [json.loads(line)["query"] for line in path.read_text().splitlines()] == ["r2-q0"]


def test_two_tabs_see_one_session(page):
    """Both tabs show the query; one answers; the other's answer is refused and its state moves on."""
    labelling, url, path = page
    _open(labelling, remaining=10)
    _show(url, "r2-q0")  # tab 1
    _show(url, "r2-q0")  # tab 2: reporting it again is harmless
    assert _call(url, "/api/answer", {"query": "r2-q0", "answer": "left"})[0] == 200
    got, reply = _call(url, "/api/answer", {"query": "r2-q0", "answer": "right"})
    assert got == 409 and "already answered" in reply["error"]
    assert _call(url, "/api/state")[1]["session"]["queries"][0]["answer"] == "left"
    assert len(path.read_text().splitlines()) == 1


def test_the_page_is_told_that_the_run_is_over(page, tmp_path):
    labelling, url, _ = page
    assert not labelling.farewell(timeout=0.1)  # No page has polled: nobody to wait for.
    assert _call(url, "/api/state")[0] == 200
    final = {"status": "completed", "mean": 12.5, "std": 0.5}
    labelling.set_done(final, str(tmp_path))
    waiting = threading.Thread(target=lambda: _call(url, "/api/state"))
    waiting.start()
    assert labelling.farewell(timeout=10)  # The page's next poll reads it.
    waiting.join()
    state = _call(url, "/api/state")[1]
    assert state["status"] == "done" and state["final"] == final and state["run_dir"] == str(tmp_path)
    labelling.set_done(None, str(tmp_path))
    assert _call(url, "/api/state")[1]["status"] == "stopped"


def test_console_lines_and_urls():
    urls = [f"http://gpu-box:8765/?token={TOKEN}", f"http://10.0.0.5:8765/?token={TOKEN}"]
    lines = page_lines(urls, given=False, loopback=False)
    assert lines[1:] == [f"    {u}" for u in urls]
    given = page_lines(urls[:1], given=True, loopback=True)
    assert given[0] == "human feedback: label the queries at http://gpu-box:8765/?token=..."
    assert not any(TOKEN in line for line in given)
    assert "no token" in page_lines(["http://127.0.0.1:8765/"], given=True, loopback=True)[-1]
    assert hide_token("http://a:1/") == "http://a:1/"
    argv = ["--human.token", "s3cret", "--seed", "1", "--human.token=s3cret2", "--human.port", "0"]
    assert redact_token(argv) == ["--human.token", "...", "--seed", "1", "--human.token=...", "--human.port", "0"]


def test_the_server_prints_its_token_and_its_urls(tmp_path):
    labelling = Labelling(LabelFile(tmp_path / "labels.jsonl"), "x", "q", 1, 1)
    server = Server(labelling, "127.0.0.1", 0, token=TOKEN)
    try:
        assert server.urls() == [f"http://127.0.0.1:{server.port}/?token={TOKEN}"]
        assert server.url == f"http://127.0.0.1:{server.port}/" and math.isfinite(server.port)
    finally:
        server.close()


# -- the command line's checks ---------------------------------------------------------------------

TINY = ["--preset", "tiny", "--task", "probe_point", "--algo", "pebble"]


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--teacher", "human", "--seeds", "2"], "labels one run"),
        (["--teacher", "human", "--algo", "sac"], "allowed only with a preference method"),
        (["--teacher", "replay"], "needs an existing file"),
        (["--teacher", "human", "--human.labels", "x.jsonl"], "only for --teacher replay"),
        (["--teacher", "human", "--human.port", "70000"], "human.port"),
        (["--teacher", "human", "--human.timeout", "-1"], "human.timeout"),
        (["--teacher", "human", "--human.host", "0.0.0.0", "--human.token", ""], "human.token=''"),
    ],
)
def test_cli_rejects_bad_human_flags(flags, message, capsys):
    from rebel_jax.run.cli import parse

    with pytest.raises(SystemExit):
        parse(TINY + flags)
    assert message in capsys.readouterr().err


def test_cli_human_teacher_compares_with_the_oracle(tmp_path: pathlib.Path):
    from rebel_jax.preference import teachers
    from rebel_jax.run.cli import parse

    args = parse(TINY + ["--teacher", "human", "--human.port", "0", "--human.timeout", "30"])
    assert args.host_teacher == "human" and args.human.port == 0 and args.human.timeout == 30
    assert args.config.teacher == teachers.PRESETS["oracle"]
    path = tmp_path / "labels.jsonl"
    path.touch()
    args = parse(TINY + ["--teacher", "replay", "--human.labels", str(path)])
    assert args.host_teacher == "replay" and args.human.labels == path
