"""The human and replay teachers: feedback sessions run by the host between jitted rounds.

For a round that starts on the feedback schedule, :meth:`HostTeacher.before_round`

1. runs the jitted ``Trainer.session_queries`` (the session's keys and ``select``), exactly as
   the scripted round would, and the scripted teacher's ``teach`` on them (its answers are
   recorded beside the person's, for the agreement metric; the page never sees them);
2. gets an answer per query: from ``labels.jsonl`` where the journal already has it (``--resume``,
   ``--teacher replay``), else from the page, clips rendered from the buffer's stored positions (and, for a
   Meta-World task, the stored scenes: the mocap, the moved body and the goal site);
3. runs the jitted ``Trainer.session_learn`` with the labels as data.

The trainer's round itself (built with ``host_teacher=True``) then runs without a session.
One run, one column: the person labels one seed's queries.
"""

from __future__ import annotations

import dataclasses
import functools
import getpass
import math
import pathlib
import random
import secrets
import threading
from typing import Annotated

import jax
import jax.numpy as jnp
import numpy as np

from rebel_jax.core.ranges import Range
from rebel_jax.preference.budget import offered_pairs, remaining_budget, within_budget
from rebel_jax.run.human import clips as clips_lib
from rebel_jax.run.human.labels import LabelError, LabelFile, SessionAnswers, now, query_id
from rebel_jax.run.human.server import Labelling, Query, Server, Session


@dataclasses.dataclass(frozen=True)
class HumanOptions:
    """The human teacher (``--teacher human``) and the replay of its labels (``--teacher replay``)."""

    host: str = "127.0.0.1"
    """Address the labelling page binds to (loopback by default; 0.0.0.0 exposes it to the network)."""
    port: Annotated[int, Range(0, 65535, note="0: any free port")] = 8765
    """Port of the labelling page (0: any free port; the URL is printed, and without its token written to
    RUN_DIR/human_url.txt)."""
    token: str | None = None
    """Token the page's requests must carry (default: a random one per run, printed in the page's URL and
    written nowhere); '' for none, allowed only on a loopback --human.host."""
    timeout: Annotated[float, Range(0, min(threading.TIMEOUT_MAX, 1e9), note="seconds; 0: no limit")] = 0.0
    """Seconds a session waits for answers before training goes on without the missing ones; 0: no limit."""
    labeller: str = ""
    """Labeller id written with each answer; default: the login name."""
    labels: pathlib.Path | None = None
    """``--teacher replay`` only: the ``labels.jsonl`` of an earlier human run to take every answer from."""
    clip_size: Annotated[int, Range(16, 4096)] = 256
    """Width and height of the clips, in pixels."""


@functools.cache
def _compiled(trainer):
    """Jitted, column-vmapped ``session_queries``, ``teach`` and ``session_learn`` (once per trainer)."""
    queries = jax.jit(jax.vmap(trainer.session_queries, in_axes=(0, None)))
    teach = jax.jit(jax.vmap(trainer.teach, in_axes=(0, 0, 0, 0, None)))
    learn = jax.jit(jax.vmap(trainer.session_learn, in_axes=(0, 0, 0, 0, None, 0)))
    return queries, teach, learn


def describe(seg, index: int) -> dict:
    """A segment's place in the buffer (column 0): env and first row, and its stored length."""
    rows = np.asarray(seg.row[0, index])
    return {"env": int(np.asarray(seg.env[0, index, 0])), "row": int(rows[0]), "length": int(rows.shape[0])}


class HostTeacher:
    """Runs the feedback sessions of a ``--teacher human`` or ``--teacher replay`` run.

    Args:
      trainer: a ``Trainer`` built with ``host_teacher=True``.
      mode: ``"human"`` or ``"replay"``.
      run_dir: the run's directory (``labels.jsonl``, ``human_url.txt``).
      options: the page's and the replay's settings.
      resume: the run continues: the label file may exist (its answers are reused).
    """

    def __init__(self, trainer, mode: str, run_dir: pathlib.Path, options: HumanOptions, resume: bool):
        if mode not in ("human", "replay"):
            raise ValueError(f"mode={mode!r} is invalid: allowed human, replay")
        self.trainer, self.mode, self.options, self.run_dir = trainer, mode, options, pathlib.Path(run_dir)
        self.final = None  # the run's result, for the page's last word (see finish)
        cfg = trainer.cfg
        self.seed = cfg.train.seed
        self.crop, self.horizon = trainer.crop, trainer.horizon
        self._queries, self._teach, self._learn = _compiled(trainer)
        self.server = self.labelling = self.renderer = None
        if mode == "replay":
            if options.labels is None:
                raise LabelError("--teacher replay needs --human.labels FILE (the labels.jsonl of a human run)")
            self.labels = LabelFile(options.labels, writable=False)
            return
        path = run_dir / "labels.jsonl"
        if path.exists() and path.stat().st_size and not resume:
            raise LabelError(f"{path} exists: continue that run with --resume, or choose another --run-dir")
        self.labels = LabelFile(path)
        self.renderer = clips_lib.make_renderer(cfg.env.task, options.clip_size)  # Fails now, not at session 1.
        instruction = clips_lib.INSTRUCTIONS.get(cfg.env.task, "Which clip shows the better behaviour?")
        labeller = options.labeller or getpass.getuser()
        self.labelling = Labelling(self.labels, labeller, instruction, cfg.feedback.labels, cfg.train.num_rounds)
        # As Jupyter's ServerApp.token (jupyter-server/jupyter_server@9a4d6eea2b16815a493b11fffe0b51b1fe55a81b:
        # jupyter_server/auth/identity.py:224): 24 random bytes in hex, made anew for each start of the run.
        token = secrets.token_hex(24) if options.token is None else options.token
        self.server = Server(self.labelling, options.host, options.port, token)
        (run_dir / "human_url.txt").write_text(self.server.url + "\n")  # No token: it stays in memory.
        for line in page_lines(self.server.urls(), given=options.token is not None, loopback=self.server.loopback):
            print(line, flush=True)

    def before_round(self, state, round_index: int):
        """Runs round ``round_index``'s feedback session if it has one; returns the state and its metrics."""
        due, first = self.trainer.session_due(round_index)
        used = int(np.asarray(state.reward.data.count)[0])
        if not due:
            if self.labelling is not None:
                self.labelling.set_training(round_index, used)
            return state, {}
        first = jnp.asarray(first)
        index = int(self.trainer.session_index(round_index))
        state, asked = self._queries(state, first)
        scripted, scripted_mask, _ = self._teach(state, asked.key_teach, asked.seg_a, asked.seg_b, jnp.int32(index))
        scripted, scripted_mask = np.asarray(scripted)[0], np.asarray(scripted_mask)[0]
        num = scripted.shape[0]
        records = []
        for i in range(num):
            records.append(
                {
                    "round": round_index,
                    "query": query_id(round_index, i),
                    "index": i,
                    "seg_a": describe(asked.seg_a, i),
                    "seg_b": describe(asked.seg_b, i),
                    "scripted": float(scripted[i]) if scripted_mask[i] > 0 else None,
                }
            )
        remaining = int(remaining_budget(self.trainer.cfg.feedback, used, index))
        offered = records[: offered_pairs(self.trainer.cfg.feedback, remaining, num)]
        answers = self._answers(state, round_index, offered, remaining, asked)
        labels, mask = np.zeros(num, np.float32), np.zeros(num, np.float32)
        for i, rec in enumerate(records):
            answer = answers.answers.get(rec["query"])
            if answer is not None:
                labels[i], mask[i] = answer["label"], answer["mask"]
        mask = np.asarray(within_budget(self.trainer.cfg.feedback, mask, used, index))  # As Trainer.teach.
        equal = (labels == 0.5) & (mask > 0)
        asked_count = sum(1 for rec in records if rec["query"] in answers.answers)
        info = {
            "num_skipped": jnp.asarray([asked_count - int(mask.sum())], jnp.int32),
            "num_equal": jnp.asarray([int(equal.sum())], jnp.int32),
        }
        state, metrics = self._learn(state, asked, jnp.asarray(labels)[None], jnp.asarray(mask)[None], first, info)
        metrics = jax.device_get(metrics)
        both = (mask > 0) & (scripted_mask > 0)
        agree = np.where(both, labels == scripted, False).sum() / max(both.sum(), 1)
        metrics["human_agreement"] = np.asarray([agree if both.any() else np.nan], np.float32)
        metrics["session_unanswered"] = np.asarray([len(offered) - asked_count], np.float32)
        if self.labelling is not None:
            self.labelling.set_training(round_index, int(np.asarray(state.reward.data.count)[0]))
        return state, metrics

    def _answers(self, state, round_index: int, records: list[dict], remaining: int, asked) -> SessionAnswers:
        journal = self.labels.session(round_index)
        for rec in records:
            old = journal.answers.get(rec["query"])
            if old is not None and (old.get("seg_a"), old.get("seg_b")) != (rec["seg_a"], rec["seg_b"]):
                raise LabelError(
                    f"{self.labels.path}: the answer to {rec['query']} was given for segments {old.get('seg_a')} / "
                    f"{old.get('seg_b')}, but this run asks {rec['seg_a']} / {rec['seg_b']}: the label file belongs "
                    "to another run (seed, config or code)"
                )
        if self.mode == "replay":
            missing = [rec["query"] for rec in records if rec["query"] not in journal.answers]
            if missing and journal.closed is None and journal.kept < remaining:
                raise LabelError(
                    f"{self.labels.path} has no answer to {', '.join(missing)} and does not close round "
                    f"{round_index}'s session: it is not the label file of this run, or that run stopped there"
                )
            return journal
        if journal.closed is not None:
            return journal
        if remaining <= 0 or journal.kept >= remaining or len(journal.answers) == len(records):
            reason = "budget" if remaining <= 0 or journal.kept >= remaining else "finished"
            self.labels.append({"kind": "close", "round": round_index, "reason": reason, "written_at": now()})
            return journal
        return self._ask(state, round_index, records, remaining, asked, journal)

    def _ask(self, state, round_index, records, remaining, asked, journal) -> SessionAnswers:
        positions = {"a": self._positions(state, asked.seg_a), "b": self._positions(state, asked.seg_b)}
        scenes = {"a": self._scenes(state, asked.seg_a), "b": self._scenes(state, asked.seg_b)}
        queries = []
        for rec in records:
            left = "b" if random.Random(f"{self.seed}:{rec['query']}").random() < 0.5 else "a"
            queries.append(Query(rec["query"], rec["index"], left, rec))
        session = Session(round_index, queries, journal, remaining, self.renderer.fps, self.horizon)
        self.labelling.open_session(session, self.trainer.cfg.feedback.labels - remaining)
        print(f"human feedback: round {round_index}'s session is waiting at {self._shown_url()}", flush=True)
        image_format = self.renderer.image_format
        mime = f"image/{image_format.lower()}"
        for query in queries:  # The page can start on the first query while the others render.
            sides = {"left": query.left, "right": "b" if query.left == "a" else "a"}
            sheets = {
                side: (clips_lib.sheet(self._frames(positions[seg], scenes[seg], query.index), image_format), mime)
                for side, seg in sides.items()
            }
            self.labelling.add_clips(query, sheets)
        reason = self.labelling.wait(self.options.timeout)
        print(f"human feedback: round {round_index}'s session closed ({reason})", flush=True)
        return session.answers

    def _frames(self, positions: np.ndarray, scenes: np.ndarray | None, index: int) -> np.ndarray:
        """The frames of segment ``index``: drawn from its positions, and its scenes where the buffer stores them."""
        if scenes is None:
            return self.renderer.frames(positions[index])
        return self.renderer.frames(positions[index], scenes[index])

    def _central(self, field, seg) -> np.ndarray:
        """(N, H, ...) ``field``'s rows (column 0) at the central steps of column 0's segments."""
        row = np.asarray(seg.row[0, :, self.crop : self.crop + self.horizon])
        env = np.asarray(seg.env[0, :, self.crop : self.crop + self.horizon])
        return np.asarray(field[0][row, env])

    def _positions(self, state, seg) -> np.ndarray:
        """(N, H, nq) stored positions of the central steps of column 0's segments."""
        return self._central(state.buffer.qpos, seg)

    def _scenes(self, state, seg) -> np.ndarray | None:
        """(N, H, k) stored scenes (a Meta-World task's mocap, moved body and goal site) of the central steps of column
        0's segments, or None where the buffer stores none."""
        return None if state.buffer.scene is None else self._central(state.buffer.scene, seg)

    def _shown_url(self) -> str:
        """The page's first URL as the console shows it (a token given on the command line is not repeated)."""
        return hide_token(self.server.urls()[0]) if self.options.token else self.server.urls()[0]

    def finish(self, result: dict) -> None:
        """The run has finished with ``result`` (``final.json``'s): the page says so when the host closes."""
        mean, std = (result.get(k) for k in ("mean", "std"))
        self.final = {
            "status": result.get("status"),
            "mean": mean if isinstance(mean, float) and math.isfinite(mean) else None,
            "std": std if isinstance(std, float) and math.isfinite(std) else None,
        }

    def close(self) -> None:
        if self.labelling is not None:
            self.labelling.set_done(self.final, str(self.run_dir.resolve()))
            self.labelling.farewell()  # An open page reads that the run is over before the server goes.
        if self.server is not None:
            self.server.close()
        if self.renderer is not None and hasattr(self.renderer, "close"):
            self.renderer.close()


def hide_token(url: str) -> str:
    """``url`` with its token's value replaced by ``...`` (as Jupyter prints a token it did not generate)."""
    return url.split("?token=", 1)[0] + "?token=..." if "?token=" in url else url


def page_lines(urls: list[str], given: bool, loopback: bool) -> list[str]:
    """What the console says about the page: its URLs, token included unless the user gave it (then ``...``,
    as ``jupyter_server/serverapp.py:2381`` hides a configured token), and a warning for no token."""
    shown = [hide_token(url) for url in urls] if given else urls
    lines = [f"human feedback: label the queries at {shown[0]}"]
    if len(shown) > 1:
        lines = ["human feedback: label the queries at one of (the page listens on every interface):"]
        lines += [f"    {url}" for url in shown]
    if given and any("?token=" in url for url in urls):
        lines.append("    (?token=...: the token you gave with --human.token)")
    if not any("?token=" in url for url in urls):
        where = "any program on this machine" if loopback else "anyone who reaches this machine"
        lines.append(f"warning: the labelling page has no token (--human.token ''): {where} can label")
    return lines


def redact_token(argv: list[str]) -> list[str]:
    """``argv`` with the value of ``--human.token`` replaced by ``...`` (so that no run file records it)."""
    out, hide = [], False
    for arg in argv:
        if hide:
            out.append("...")
        elif arg.startswith("--human.token="):
            out.append("--human.token=...")
        else:
            out.append(arg)
        hide = not hide and arg == "--human.token"
    return out
