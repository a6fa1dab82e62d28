"""The human teacher's sessions run by the host between jitted rounds, on the probe task.

A robot labeller answers on the page's HTTP API what the hidden scripted (oracle) teacher answers;
the run must then equal the scripted run, whose session is inside the jitted round. The label file
it leaves must replay to the same run, and a session cut short by a crash must resume asking only
what was not answered.
"""

from __future__ import annotations

import functools
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import threading
import time
import urllib.request

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.preference.feedback import SESSION_METRICS
from rebel_jax.run.cli import parse
from rebel_jax.run.human import HostTeacher, HumanOptions
from rebel_jax.train import Trainer, compiled, seed_keys

# REBEL on the probe task, rounds of 20 vector steps (40 env steps); sessions at the start of rounds
# 2 and 3, 4 queries each. The browser test runs the CLI with these flags, so that its programs are
# those compiled here (the persistent compilation cache is shared with its subprocess).
FLAGS = (
    "--preset tiny --algo rebel --rebel.lam -0.01 --task probe_point --num-envs 2 --episode-length 40"
    " --sac.hidden 16 --sac.batch-size 16 --sac.utd 0.5 --total-steps 160 --seed-steps 20 --steps-per-round 40"
    " --eval-every 40 --eval-episodes 1 --feedback.labels 8 --feedback.per-session 4 --feedback.interval 40"
    " --reward.hidden 32"
    " --reward.batch-size 16 --query.segment-length 8 --pretrain.steps 60 --pretrain.chunk-size 64"
    " --rebel.num-segments 8 --rebel.segment-length 8"
).split()
MICRO = parse([*FLAGS, "--teacher", "human"]).config
ROUNDS = MICRO.train.num_rounds
SESSIONS = (2, 3)
KEYS = seed_keys(0, 1)


def _scripted_answer(query) -> str:
    """The page answer that gives the hidden scripted label (a: left if a is on the left)."""
    scripted = query.record["scripted"]
    if scripted is None:
        return "skip"
    if scripted == 0.5:
        return "equal"
    preferred = "b" if scripted == 1.0 else "a"
    return "left" if query.left == preferred else "right"


class Robot(threading.Thread):
    """Answers every query shown on the page, through its HTTP API, as the scripted teacher would."""

    def __init__(self, host: HostTeacher, stop_after: int | None = None, skip: tuple[str, ...] = ()):
        super().__init__(daemon=True)
        self.host, self.stop_after, self.asked, self.done = host, stop_after, [], threading.Event()
        self.skip = skip  # Queries it skips instead.

    def post(self, path: str, body: dict) -> None:
        headers = {"Content-Type": "application/json", "Authorization": f"token {self.host.server.token}"}
        data = json.dumps(body).encode()
        request = urllib.request.Request(self.host.server.url + path, data=data, headers=headers, method="POST")
        with urllib.request.urlopen(request, timeout=10) as response:
            assert response.status == 200

    def run(self):
        labelling = self.host.labelling
        while not self.done.is_set():
            session = labelling.session
            pending = [q for q in session.queries if q.id not in session.answers.answers] if session else []
            if session is not None and session.closed is None and session.complete:
                self.post("api/finish", {})
            elif pending and pending[0].clips:
                if self.stop_after is not None and len(self.asked) == self.stop_after:
                    return  # The labeller's tab is closed; the trainer "crashes".
                self.asked.append(pending[0].id)
                self.post("api/shown", {"query": pending[0].id})  # As the page does once both clips are on screen.
                answer = "skip" if pending[0].id in self.skip else _scripted_answer(pending[0])
                self.post("api/answer", {"query": pending[0].id, "answer": answer})
            time.sleep(0.01)


@functools.cache
def _host_trainer():
    """One trainer for every host-teacher run here: its programs compile once."""
    trainer = Trainer(MICRO, host_teacher=True)
    return trainer, compiled(trainer)


def _host_run(tmp_path, mode, rounds=range(ROUNDS), options=None, state=None, robot_stop=None, resume=False):
    trainer, (init, round_fn, _) = _host_trainer()
    state = init(KEYS) if state is None else state
    options = options or HumanOptions(port=0, labeller="robot")
    host = HostTeacher(trainer, mode, tmp_path, options, resume=resume)
    robot = Robot(host, robot_stop) if mode == "human" else None
    if robot is not None:
        robot.start()
    metrics = []
    try:
        for r in rounds:
            state, session = host.before_round(state, r)
            state, m = round_fn(state, jnp.int32(r))
            metrics.append({**jax.device_get(m), **session})
    finally:
        if robot is not None:
            robot.done.set()
        host.close()
    return state, metrics, robot


@pytest.fixture(scope="module")
def scripted_run():
    trainer = Trainer(MICRO)
    init, round_fn, _ = compiled(trainer)
    state, metrics = init(KEYS), []
    for r in range(ROUNDS):
        state, m = round_fn(state, jnp.int32(r))
        metrics.append(jax.device_get(m))
    return state, metrics


@pytest.fixture(scope="module")
def human_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("human")
    state, metrics, robot = _host_run(run_dir, "human")
    return run_dir, state, metrics, robot


def _assert_same_run(state, metrics, other_state, other_metrics, exact: bool):
    check = np.testing.assert_array_equal if exact else lambda a, b: np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_array_equal(state.reward.data.labels, other_state.reward.data.labels)
    np.testing.assert_array_equal(state.reward.data.count, other_state.reward.data.count)
    jax.tree.map(check, state.reward.params, other_state.reward.params)
    jax.tree.map(check, state.agent.actor_params, other_state.agent.actor_params)
    np.testing.assert_array_equal(state.key, other_state.key)
    for m, o in zip(metrics, other_metrics, strict=True):
        for k in ("session", "session_labels", "session_skipped", "session_equal", "labels_used"):
            np.testing.assert_array_equal(m[k], o[k], err_msg=k)


def test_human_answers_enter_learn_as_the_scripted_teachers_do(human_run, scripted_run):
    run_dir, state, metrics, robot = human_run
    assert robot.asked == [f"r{r}-q{i}" for r in SESSIONS for i in range(4)]
    _assert_same_run(state, metrics, *scripted_run, exact=False)
    for r, m in enumerate(metrics):
        if r in SESSIONS:
            assert m["human_agreement"][0] == 1.0 and m["session_unanswered"][0] == 0
            assert all(np.isfinite(m[k]).all() for k in SESSION_METRICS)
        else:
            assert "human_agreement" not in m and np.isnan(m["session"]).all()
    assert int(state.reward.data.count[0]) == MICRO.feedback.labels


def test_label_file_holds_every_answer(human_run):
    run_dir, state, _, _ = human_run
    records = [json.loads(line) for line in (run_dir / "labels.jsonl").read_text().splitlines()]
    answers = [r for r in records if r["kind"] == "answer"]
    assert [r["query"] for r in answers] == [f"r{r}-q{i}" for r in SESSIONS for i in range(4)]
    assert [r["kind"] for r in records if r["kind"] != "answer"] == ["close", "close"]
    stored = np.asarray(state.reward.data.labels[0])
    np.testing.assert_array_equal(stored, [r["label"] for r in answers])  # The oracle never skips here.
    for r in answers:
        assert r["left"] in ("a", "b") and r["labeller"] == "robot" and r["label"] == r["scripted"]
        for seg in ("seg_a", "seg_b"):
            assert 0 <= r[seg]["env"] < 2 and r[seg]["length"] == 8 and 0 <= r[seg]["row"] < 80
    assert {r["left"] for r in answers} == {"a", "b"}  # The order is randomised.


def test_the_token_is_written_nowhere_in_the_run_directory(human_run):
    run_dir, _, _, robot = human_run
    token = robot.host.server.token
    assert len(token) == 48 and int(token, 16) >= 0  # 24 random bytes in hex, as Jupyter's.
    files = [f for f in run_dir.rglob("*") if f.is_file()]
    assert {f.name for f in files} >= {"labels.jsonl", "human_url.txt"}
    assert not [f for f in files if token.encode() in f.read_bytes()]
    assert (run_dir / "human_url.txt").read_text().strip() == robot.host.server.url


def test_replay_reruns_the_human_run(human_run, tmp_path):
    run_dir, state, metrics, _ = human_run
    options = HumanOptions(labels=run_dir / "labels.jsonl")
    replayed, replayed_metrics, _ = _host_run(tmp_path, "replay", options=options)
    _assert_same_run(replayed, replayed_metrics, state, metrics, exact=True)
    assert not (tmp_path / "labels.jsonl").exists()  # A replay writes no labels.


def test_replay_of_another_runs_labels_is_refused(human_run, tmp_path):
    run_dir, _, _, _ = human_run
    lines = (run_dir / "labels.jsonl").read_text().splitlines()
    record = json.loads(lines[0])
    record["seg_a"]["row"] += 1  # As if another seed had asked it.
    (tmp_path / "other.jsonl").write_text("\n".join([json.dumps(record), *lines[1:]]) + "\n")
    with pytest.raises(ValueError, match="belongs to another run"):
        _host_run(tmp_path, "replay", options=HumanOptions(labels=tmp_path / "other.jsonl"))


def test_crashed_session_resumes_asking_only_the_rest(human_run, tmp_path):
    run_dir, state, metrics, _ = human_run
    # The first run "crashes" after two answers of round 2's session (its tab closed, training stopped).
    _, (init, round_fn, _) = _host_trainer()
    start = init(KEYS)
    for r in range(2):
        start, _ = round_fn(start, jnp.int32(r))  # Rounds 0-1 have no session: the checkpoint of round 2.
    crashed = threading.Thread(target=_host_run, args=(tmp_path, "human", [2], None, start, 2), daemon=True)
    crashed.start()
    path = tmp_path / "labels.jsonl"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (path.exists() and path.read_text().count("\n") >= 2):
        time.sleep(0.05)
    with open(path, "ab") as f:
        f.write(b'{"kind": "answer", "query": "r2-q2"')  # Torn by the crash.
    # --resume: the journal is re-read; only r2-q2 and r2-q3 are asked, then round 3 as usual.
    resumed, resumed_metrics, robot = _host_run(tmp_path, "human", range(2, ROUNDS), state=start, resume=True)
    assert robot.asked == ["r2-q2", "r2-q3"] + [f"r3-q{i}" for i in range(4)]
    _assert_same_run(resumed, resumed_metrics, state, metrics[2:], exact=True)


def test_unanswered_sessions_time_out_and_replay(tmp_path):
    """No one answers: each session closes after --human.timeout, training goes on without labels."""
    options = HumanOptions(port=0, timeout=0.3)
    trainer, (init, round_fn, _) = _host_trainer()
    host = HostTeacher(trainer, "human", tmp_path, options, resume=False)
    state, metrics = init(KEYS), []
    try:
        for r in range(ROUNDS):
            state, session = host.before_round(state, r)
            state, m = round_fn(state, jnp.int32(r))
            metrics.append({**jax.device_get(m), **session})
    finally:
        host.close()
    records = [json.loads(line) for line in (tmp_path / "labels.jsonl").read_text().splitlines()]
    assert [(r["kind"], r["round"], r["reason"]) for r in records] == [("close", r, "timeout") for r in SESSIONS]
    assert int(state.reward.data.count[0]) == 0
    for r in SESSIONS:
        assert metrics[r]["session_labels"][0] == 0 and metrics[r]["session_unanswered"][0] == 4
        assert np.isnan(metrics[r]["reward_accuracy_all"][0])  # Nothing kept: the reward model was not trained.
    replayed, replayed_metrics, _ = _host_run(
        tmp_path / "replay", "replay", options=HumanOptions(labels=tmp_path / "labels.jsonl")
    )
    _assert_same_run(replayed, replayed_metrics, state, metrics, exact=True)


@pytest.mark.heavy  # its own trainer (~36 s on 2 cores); make test checks the budget in the round (preference_train)
def test_asked_budget_shows_only_the_pairs_it_counts_and_a_skip_spends_one(tmp_path):
    """``--budget asked`` with 6 labels of 4 per session: round 3's session shows 2 pairs (B-Pref's
    shrunken last batch). A skipped pair is spent: the session ends after those 2 answers, and the one
    kept label enters training."""
    cfg = parse([*FLAGS, "--teacher", "human", "--feedback.labels", "6", "--feedback.budget", "asked"]).config
    trainer = Trainer(cfg, host_teacher=True)
    init, round_fn, _ = compiled(trainer)
    host = HostTeacher(trainer, "human", tmp_path, HumanOptions(port=0, labeller="robot"), resume=False)
    robot = Robot(host, skip=("r3-q0",))
    robot.start()
    state, metrics = init(KEYS), []
    try:
        for r in range(cfg.train.num_rounds):
            state, session = host.before_round(state, r)
            state, m = round_fn(state, jnp.int32(r))
            metrics.append({**jax.device_get(m), **session})
    finally:
        robot.done.set()
        host.close()
    assert robot.asked == [f"r2-q{i}" for i in range(4)] + ["r3-q0", "r3-q1"]
    assert [metrics[r]["session_labels"][0] for r in SESSIONS] == [4, 1]
    assert [metrics[r]["session_skipped"][0] for r in SESSIONS] == [0, 1]
    assert metrics[3]["session_unanswered"][0] == 0 and int(state.reward.data.count[0]) == 5
    records = [json.loads(line) for line in (tmp_path / "labels.jsonl").read_text().splitlines()]
    assert [(r["round"], r["reason"]) for r in records if r["kind"] == "close"] == [(2, "finished"), (3, "finished")]


# -- a person's browser: the CLI run with --teacher human, labelled in headless Chromium --------------

ROOT = pathlib.Path(__file__).parents[1]
CHROMIUM = pathlib.Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
# Records, every animation frame, which query the page shows and whether its answers are enabled.
GATE_WATCH = """
window.__gate = [];
(function watch() {
  const button = document.getElementById("answer-left");
  const query = document.body ? document.body.dataset.query || "" : "";
  const enabled = Boolean(button && !button.disabled);
  const last = window.__gate[window.__gate.length - 1];
  if (!last || last.query !== query || last.enabled !== enabled) {
    window.__gate.push({query, enabled, t: performance.now()});
  }
  requestAnimationFrame(watch);
})();
"""
# What the browser does, query by query: (how, what); "key" presses a key, "click" a button.
SESSION_ROUND_2 = [
    ("r2-q0", [("key", "ArrowRight")]),
    ("r2-q1", [("click", "#answer-left")]),
    ("r2-q2", [("key", "ArrowDown"), ("click", "#undo")]),  # Skip, then undo it with the button ...
    ("r2-q2", [("key", "ArrowUp")]),  # ... and answer equal.
    ("r2-q3", [("click", "#answer-right"), ("key", "Backspace")]),  # Undo by key ...
    ("r2-q3", [("key", "ArrowLeft")]),
]
SESSION_ROUND_3 = [
    ("r3-q0", [("click", "#speed"), ("key", " "), ("key", "ArrowLeft")]),  # 0.5x, replay, then answer.
    ("r3-q1", [("click", "#answer-skip")]),
    ("r3-q2", [("key", "ArrowRight")]),
    ("r3-q3", [("click", "#answer-equal")]),
]
EXPECTED_JOURNAL = [
    ("answer", "r2-q0", "right"),
    ("answer", "r2-q1", "left"),
    ("answer", "r2-q2", "skip"),
    ("undo", "r2-q2", None),
    ("answer", "r2-q2", "equal"),
    ("answer", "r2-q3", "right"),
    ("undo", "r2-q3", None),
    ("answer", "r2-q3", "left"),
    ("close", None, None),
    ("answer", "r3-q0", "left"),
    ("answer", "r3-q1", "skip"),
    ("answer", "r3-q2", "right"),
    ("answer", "r3-q3", "equal"),
    ("close", None, None),
]


def _label_session(page, round_index: int, steps, finish: tuple[str, str]) -> None:
    page.wait_for_function(f"document.body.dataset.session === '{round_index}'", timeout=120_000)
    for query, actions in steps:
        page.wait_for_function(f"document.body.dataset.query === {json.dumps(query)}", timeout=60_000)
        page.wait_for_selector("#answer-left:enabled", timeout=30_000)
        for how, what in actions:
            page.wait_for_function("document.body.dataset.busy === '0'", timeout=30_000)  # The last action is in.
            if how == "key":
                page.keyboard.press("Space" if what == " " else what)
            else:
                page.click(what)
        page.wait_for_function(
            f"document.body.dataset.query !== {json.dumps(query)} || !document.querySelector('#finish').hidden"
            " || document.querySelector('#answer-left').disabled",
            timeout=30_000,
        )
    page.wait_for_selector("#finish-button:visible", timeout=30_000)
    how, what = finish
    page.keyboard.press(what) if how == "key" else page.click(what)
    page.wait_for_function(f"document.body.dataset.session !== '{round_index}'", timeout=60_000)


# make test-heavy: a whole CLI run driven through Chromium (about 45 s on 2 cores); make test drives the same sessions
# through the page's HTTP API (the tests above) and the page in Chromium (test_the_page_says_when_...).
@pytest.mark.heavy
@pytest.mark.browser
def test_a_person_labels_a_cli_run_in_the_browser(human_run, tmp_path):
    """The README's ``--teacher human`` command, labelled by keys and clicks in Debian's Chromium."""
    del human_run  # Its programs are the CLI's: compiled once, loaded here from the persistent cache.
    if not CHROMIUM.exists():
        pytest.skip(f"Debian's Chromium is not at {CHROMIUM}: apt-get install chromium chromium-driver")
    from playwright.sync_api import sync_playwright

    run_dir = tmp_path / "run"
    env = dict(
        os.environ,
        PYTHONPATH=str(ROOT / "src"),
        JAX_COMPILATION_CACHE_DIR=str(jax.config.jax_compilation_cache_dir),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=str(jax.config.jax_persistent_cache_min_compile_time_secs),
    )
    cmd = [sys.executable, "-m", "rebel_jax.train", *FLAGS, "--teacher", "human", "--human.port", "0"]
    cmd += ["--human.labeller", "browser-test", "--run-dir", str(run_dir), "--no-progress", "--no-tensorboard"]
    log = open(tmp_path / "train.log", "w")  # noqa: SIM115 - closed below

    def log_text() -> str:
        return (tmp_path / "train.log").read_text()

    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        # The URL with its token, as a person copies it from the console.
        deadline, found = time.monotonic() + 300, None
        while found is None:
            assert proc.poll() is None, (tmp_path / "train.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "the page never started"
            time.sleep(0.1)
            found = re.search(r"label the queries at (http://127\.0\.0\.1:\d+/)\?token=([0-9a-f]+)\n", log_text())
        url, token = found.group(1) + "?token=" + found.group(2), found.group(2)
        assert (run_dir / "human_url.txt").read_text() == found.group(1) + "\n"  # The file has no token.
        with sync_playwright() as pw:
            context = pw.chromium.launch_persistent_context(
                str(tmp_path / "profile"),  # A fresh, empty profile.
                executable_path=str(CHROMIUM),
                headless=True,
                args=CHROMIUM_FLAGS,
                viewport={"width": 900, "height": 820},
            )
            page = context.pages[0] if context.pages else context.new_page()
            page.add_init_script(GATE_WATCH)
            page.goto(url.split("?")[0])  # Without its token the page is refused, and says what to open.
            page.wait_for_function("document.body.dataset.contact === 'refused'", timeout=60_000)
            assert page.is_visible("#login") and "needs the run's token" in page.text_content("#alert")
            page.goto(url)
            page.wait_for_function("document.body.dataset.query === 'r2-q0'", timeout=120_000)
            assert (
                page.text_content("#instruction")
                == "Which dot gets closer to the target in the centre, and stays there?"
            )
            assert "query 1 of 4" in page.text_content("#query-progress")
            assert "paused" in page.text_content("#training")
            page.wait_for_selector("#answer-left:enabled", timeout=30_000)
            screenshot = tmp_path / "page.png"
            page.screenshot(path=str(screenshot))
            if os.environ.get("REBEL_JAX_SCREENSHOT"):
                shutil.copy(screenshot, os.environ["REBEL_JAX_SCREENSHOT"])
            _label_session(page, 2, SESSION_ROUND_2, ("key", "Enter"))
            _label_session(page, 3, SESSION_ROUND_3, ("click", "#finish-button"))
            gate = page.evaluate("window.__gate")
            # The run ends while the page is open: it says so, with the final return and where the files are.
            page.wait_for_selector("#finished:visible", timeout=300_000)
            finished = page.text_content("#finished-text")
            assert finished.startswith("Run finished: final evaluation return"), finished
            assert str(run_dir.resolve()) in page.text_content("#finished-files")
            context.close()
        assert proc.wait(timeout=300) == 0, (tmp_path / "train.log").read_text()[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()

    # Every answer, undo and close is in the journal, in order.
    records = [json.loads(line) for line in (run_dir / "labels.jsonl").read_text().splitlines()]
    assert [(r["kind"], r.get("query"), r.get("answer")) for r in records] == EXPECTED_JOURNAL
    answers = [r for r in records if r["kind"] == "answer"]
    assert all(r["labeller"] == "browser-test" and r["shown_at"] <= r["answered_at"] for r in answers)
    # The answers were enabled only once both clips had played through: 8 frames at 10 fps (0.5x: 1.6 s).
    duration = 1000 * MICRO.query.segment_length / 10
    shown = {}
    for event in gate:
        if event["query"] and not event["enabled"] and event["query"] not in shown:
            shown[event["query"]] = event["t"]
        if event["query"] and event["enabled"] and event["query"] in shown:
            assert event["t"] - shown.pop(event["query"]) >= duration - 40, event
    # Training went on with those labels: 4 kept in round 2 (one equal), 3 in round 3 (one skip, one equal).
    metrics = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [m["round"] for m in metrics] == list(range(ROUNDS))
    by_round = {m["round"]: m for m in metrics}
    assert [by_round[r]["session_labels"] for r in SESSIONS] == [[4.0], [3.0]]
    assert [by_round[r]["session_skipped"] for r in SESSIONS] == [[0.0], [1.0]]
    assert [by_round[r]["session_equal"] for r in SESSIONS] == [[1.0], [1.0]]
    assert by_round[3]["labels_used"] == [7.0]
    assert all(0.0 <= by_round[r]["human_agreement"][0] <= 1.0 for r in SESSIONS)
    assert (run_dir / "final.json").exists()
    final = json.loads((run_dir / "final.json").read_text())
    # One seed: its return alone (final.json's sample std is null); several: the mean +- their sample std.
    spread = "" if final["std"] is None else f" ± {final['std']:.1f}"
    shown = re.match(rf"Run finished: final evaluation return (-?[0-9.]+){re.escape(spread)}\. Thank you!$", finished)
    assert shown and abs(float(shown.group(1)) - final["mean"]) <= 0.05 + 1e-9, finished
    # The token is in the console only: in no file of the run (metrics, labels, meta, config, checkpoints, ...).
    files = [f for f in run_dir.rglob("*") if f.is_file()]
    assert {"metrics.jsonl", "meta.json", "labels.jsonl", "final.json"} <= {f.name for f in files}
    assert not [f for f in files if token.encode() in f.read_bytes()]
    assert "Traceback" not in log_text()


@pytest.mark.browser
def test_the_page_says_when_the_trainer_is_away_and_when_the_run_is_over(tmp_path):
    """The page alone (no trainer): the token form, answers disabled while the trainer does not answer,
    answers again once it is back (the same --human.token), and the run's end with its return and files."""
    if not CHROMIUM.exists():
        pytest.skip(f"Debian's Chromium is not at {CHROMIUM}: apt-get install chromium chromium-driver")
    from playwright.sync_api import sync_playwright

    from rebel_jax.run.human.clips import sheet
    from rebel_jax.run.human.labels import LabelFile, SessionAnswers
    from rebel_jax.run.human.server import Labelling, Query, Server, Session

    token = "page-test-token"
    labelling = Labelling(LabelFile(tmp_path / "labels.jsonl"), "tester", "Which is better?", 10, 5)
    server = Server(labelling, "127.0.0.1", 0, token=token)
    port = server.port
    frames = np.zeros((3, 16, 16, 3), np.uint8)  # 3 frames at 10 fps: answers unlock after 0.3 s.
    queries = [Query(f"r2-q{i}", i, "a", {"round": 2, "query": f"r2-q{i}", "index": i}) for i in range(2)]
    labelling.open_session(Session(2, queries, SessionAnswers(), 10, fps=10.0, frames=3), used=0)
    for q in queries:
        labelling.add_clips(q, {side: (sheet(frames, "PNG"), "image/png") for side in ("left", "right")})
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_FLAGS)
            page = browser.new_page()
            page.goto(server.url)
            page.wait_for_function("document.body.dataset.contact === 'refused'", timeout=30_000)
            page.fill("#token", token)
            page.press("#token", "Enter")  # The form opens /?token=...
            page.wait_for_function("document.body.dataset.query === 'r2-q0'", timeout=30_000)
            page.wait_for_selector("#answer-left:enabled", timeout=30_000)
            assert queries[0].shown  # The page reported it before its answers unlocked.
            page.keyboard.press("ArrowLeft")
            page.wait_for_function("document.body.dataset.query === 'r2-q1'", timeout=30_000)
            page.wait_for_selector("#answer-left:enabled", timeout=30_000)
            server.close()  # The trainer goes away (killed, or its machine unreachable).
            page.wait_for_function("document.body.dataset.contact === 'lost'", timeout=30_000)
            assert "Trainer not answering (last contact" in page.text_content("#alert")
            assert page.text_content("#training") == "trainer not answering"
            assert page.is_disabled("#answer-left") and page.is_disabled("#answer-right")
            page.keyboard.press("ArrowRight")  # Does nothing.
            queries[1].shown = False  # The trainer started again: it has not seen the query shown.
            server = Server(labelling, "127.0.0.1", port, token=token)
            page.wait_for_function("document.body.dataset.contact === 'ok'", timeout=30_000)
            page.wait_for_selector("#answer-right:enabled", timeout=30_000)
            assert queries[1].shown and page.is_hidden("#alert")  # Reported again.
            page.keyboard.press("ArrowRight")
            page.wait_for_selector("#finish-button:visible", timeout=30_000)
            labelling.set_done({"status": "completed", "mean": 12.34, "std": 0.5}, str(tmp_path))
            page.wait_for_selector("#finished:visible", timeout=30_000)
            assert page.text_content("#finished-text") == "Run finished: final evaluation return 12.3 ± 0.5. Thank you!"
            assert page.text_content("#finished-files") == f"Its files are in {tmp_path}"
            assert labelling.farewell(timeout=5)
            server.close()
            page.wait_for_selector("#finished-exit:visible", timeout=30_000)
            assert page.is_hidden("#alert")  # A finished run is not "not answering".
            browser.close()
    finally:
        server.close()
    answers = [json.loads(line) for line in (tmp_path / "labels.jsonl").read_text().splitlines()]
    assert [(r["query"], r["answer"]) for r in answers] == [("r2-q0", "left"), ("r2-q1", "right")]
