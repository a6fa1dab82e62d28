"""The human teacher without JAX: the answer -> label table, labels.jsonl (append, torn line, resume),
the page's HTTP API (answers, undo, budget, bad requests) and the command line's checks."""

from __future__ import annotations

import json
import pathlib
import urllib.error
import urllib.request

import pytest

from rebel_jax.human.labels import LabelError, LabelFile, SessionAnswers, query_id, to_label
from rebel_jax.human.server import Labelling, Query, Server, Session

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


def _call(url: str, path: str, body=None, raw: bytes | None = None) -> tuple[int, dict]:
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    request = urllib.request.Request(url + path.lstrip("/"), data=data, method="GET" if data is None else "POST")
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read())


@pytest.fixture
def page(tmp_path):
    labels = LabelFile(tmp_path / "labels.jsonl")
    labelling = Labelling(labels, "tester", "Which is better?", budget=10, num_rounds=5)
    server = Server(labelling, "127.0.0.1", 0)
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
    with urllib.request.urlopen(url + "clips/r2-q1/left", timeout=10) as response:
        assert response.read() == b"Lr2-q1"
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


# -- the command line's checks ---------------------------------------------------------------------

TINY = ["--preset", "tiny", "--task", "probe_point", "--algo", "pebble"]


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--teacher", "human", "--seeds", "2"], "labels one run"),
        (["--teacher", "human", "--algo", "sac"], "preference algo"),
        (["--teacher", "replay"], "needs an existing file"),
        (["--teacher", "human", "--human.labels", "x.jsonl"], "only for --teacher replay"),
        (["--teacher", "human", "--human.port", "70000"], "human.port"),
        (["--teacher", "human", "--human.timeout", "-1"], "human.timeout"),
    ],
)
def test_cli_rejects_bad_human_flags(flags, message, capsys):
    from rebel_jax.cli import parse

    with pytest.raises(SystemExit):
        parse(TINY + flags)
    assert message in capsys.readouterr().err


def test_cli_human_teacher_compares_with_the_oracle(tmp_path: pathlib.Path):
    from rebel_jax import teachers
    from rebel_jax.cli import parse

    args = parse(TINY + ["--teacher", "human", "--human.port", "0", "--human.timeout", "30"])
    assert args.host_teacher == "human" and args.human.port == 0 and args.human.timeout == 30
    assert args.config.teacher == teachers.PRESETS["oracle"]
    path = tmp_path / "labels.jsonl"
    path.touch()
    args = parse(TINY + ["--teacher", "replay", "--human.labels", str(path)])
    assert args.host_teacher == "replay" and args.human.labels == path
