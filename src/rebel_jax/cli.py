"""``python -m rebel_jax.train``: the host loop over jitted rounds, and its command line.

    python -m rebel_jax.train --preset paper --algo sac --task walker_walk --seeds 5
    python -m rebel_jax.train --preset paper --algo pebble --labels 100 --teacher noisy

``--preset`` (``paper`` or ``tiny``) picks the defaults and ``--teacher`` (a B-Pref teacher:
oracle, noisy, mistake, skip, equal, myopic) the teacher; every other flag overrides one
field of :class:`rebel_jax.config.Config` (``--help`` lists them with their docs).
``--teacher human`` asks a person on a web page between rounds, ``--teacher replay`` takes a
human run's answers from its ``labels.jsonl`` (:mod:`rebel_jax.human`).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import pathlib
import subprocess
import sys
import time
from typing import Annotated

import jax
import jax.numpy as jnp
import numpy as np
import tyro

from rebel_jax import sweep, teachers
from rebel_jax.checkpoint import Checkpointer
from rebel_jax.config import PRESETS, Config, ConfigError
from rebel_jax.human import HOST_TEACHERS, HostTeacher, HumanError, HumanOptions
from rebel_jax.logging import RunLogger
from rebel_jax.train import Trainer, compiled, seed_keys


@dataclasses.dataclass(frozen=True)
class Args:
    """Train one configuration on several seeds."""

    config: Annotated[Config, tyro.conf.arg(name="")]
    seeds: int = 1
    """Seeds run together (vmapped; sharded over all devices when there are several)."""
    run_dir: pathlib.Path | None = None
    """The run's directory; default ``runs/<algo>_<task>_<time>``."""
    resume: bool = False
    """Continue from the latest checkpoint in ``run_dir``."""
    checkpoint_every: int = 1
    """Rounds between checkpoints; 0 disables them."""
    time_limit: float = 0.0
    """Seconds of wall time: stop after the last round that ends within it (checkpointing that
    round) and continue later with ``--resume``. For calls with a wall-clock limit; 0: none."""
    progress: bool = True
    """Show a progress bar."""
    tensorboard: bool = True
    """Write TensorBoard event files."""
    distributed: bool = False
    """Call ``jax.distributed.initialize()`` first (multi-host runs)."""
    lam_grid: tuple[float, ...] = ()
    """``--algo rebel`` only: run every seed with each of these lambdas in one vmapped program
    (columns are lambda-major: lambda 0 seed 0, lambda 0 seed 1, ...; seed i uses the same key
    for every lambda). Empty: ``rebel.lam`` only."""

    teacher_grid: tuple[str, ...] = ()
    """Preference methods only: run every seed (and lambda) with each of these B-Pref teachers
    in one vmapped program (columns: lambda, then teacher, then seed). Empty: ``--teacher``."""
    human: HumanOptions = HumanOptions()
    """``--teacher human`` (the labelling page) and ``--teacher replay`` (its saved answers)."""
    host_teacher: tyro.conf.Suppress[str] = ""
    """``human`` or ``replay`` (set from ``--teacher``), or empty for a scripted teacher."""

    @property
    def lams(self) -> tuple[float, ...]:
        return self.lam_grid or (self.config.rebel.lam,)

    @property
    def teachers(self) -> tuple[str | None, ...]:
        return self.teacher_grid or (None,)

    def grid(self) -> list[tuple[float, str | None]]:
        """(lambda, teacher preset or None for ``config.teacher``) of each column, seeds innermost."""
        return [(lam, t) for lam in self.lams for t in self.teachers for _ in range(self.seeds)]

    @property
    def columns(self) -> int:
        """Runs vmapped together: seeds x lambdas x teachers."""
        return self.seeds * len(self.lams) * len(self.teachers)


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        return out.stdout.strip() if out.returncode == 0 else None
    except OSError:
        return None


def _write_meta(run_dir: pathlib.Path, args: Args) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(dataclasses.asdict(args.config), indent=1))
    meta = {
        "jax": jax.__version__,
        "devices": [d.device_kind for d in jax.devices()],
        "backend": jax.default_backend(),
        "git_commit": _git_commit(),
        "command": " ".join(sys.argv),
        "seeds": args.seeds,
        "columns": args.columns,
        "lams": [lam for lam, _ in args.grid()] if args.config.algo == "rebel" else None,
        "teachers": [t for _, t in args.grid()] if args.teacher_grid else None,
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
    }
    (run_dir / "meta.json").write_text(json.dumps(meta, indent=1))


def _drop_rounds_after(metrics: pathlib.Path, rounds: int) -> None:
    """Keeps the first ``rounds`` rounds of a resumed run's log: later ones are run (and logged) again."""
    if metrics.exists():
        lines = metrics.read_text().splitlines(keepends=True)
        metrics.write_text("".join(line for line in lines if json.loads(line)["round"] < rounds))


def run(args: Args) -> dict:
    """Trains ``args.config`` on ``args.seeds`` seeds; returns the final per-seed evaluation."""
    cfg = args.config
    run_dir = args.run_dir or pathlib.Path("runs") / f"{cfg.algo}_{cfg.env.task}_{time.strftime('%Y%m%d-%H%M%S')}"
    trainer = Trainer(cfg, host_teacher=bool(args.host_teacher))
    # The human teacher's page and renderer start first: a machine that cannot render fails now.
    host = HostTeacher(trainer, args.host_teacher, run_dir, args.human, args.resume) if args.host_teacher else None
    init, round_fn, evaluate = compiled(trainer)
    sharding = sweep.seed_sharding(args.columns)
    keys = jnp.tile(seed_keys(cfg.train.seed, args.seeds), (args.columns // args.seeds, 1))
    keys = sweep.shard_seeds(keys, sharding)
    state = init(keys)
    grid = args.grid()
    if cfg.algo == "rebel":
        state = state.replace(lam=jnp.asarray([lam for lam, _ in grid], jnp.float32))
    if args.teacher_grid:
        knobs = [teachers.knobs(teachers.PRESETS[t]) for _, t in grid]
        state = state.replace(teacher=jax.tree.map(lambda *xs: jnp.stack(xs), *knobs))
    state = sweep.shard_seeds(state, sharding)
    ckpt = Checkpointer(run_dir / "checkpoints") if args.checkpoint_every else None
    start = 0
    if args.resume:
        if ckpt is None or ckpt.latest() is None:
            raise FileNotFoundError(f"--resume: no checkpoint under {run_dir / 'checkpoints'}")
        start, state = ckpt.restore(state)
        _drop_rounds_after(run_dir / "metrics.jsonl", start)
    else:
        _write_meta(run_dir, args)
    per_round = cfg.train.steps_per_round
    logger = RunLogger(run_dir, cfg.train.total_steps, start * per_round, args.progress, args.tensorboard)
    started, slowest = time.perf_counter(), 0.0
    try:
        for r in range(start, cfg.train.num_rounds):
            if args.time_limit and r > start and time.perf_counter() - started + 1.2 * slowest > args.time_limit:
                if ckpt is not None and ckpt.latest() != r:
                    ckpt.save(r, state)
                print(f"--time-limit {args.time_limit:g} s: stopped after round {r - 1}; continue with --resume")
                return {"stopped_at_round": r}
            session = {}
            if host is not None:  # The human or replay teacher's session, between rounds.
                state, session = host.before_round(state, r)
            t0 = time.perf_counter()
            state, metrics = round_fn(state, jnp.int32(r))
            metrics = {**jax.device_get(metrics), **session}
            seconds = time.perf_counter() - t0
            slowest = max(slowest, seconds) if r > start else 0.0
            env_steps = (r + 1) * per_round
            if env_steps % cfg.train.eval_every and r + 1 < cfg.train.num_rounds:
                metrics.pop("eval_return")
            extra = {"round": r, "seconds": seconds, "env_steps_per_s": per_round * args.columns / seconds}
            logger.write(env_steps, metrics, extra)
            if ckpt is not None and ((r + 1) % args.checkpoint_every == 0 or r + 1 == cfg.train.num_rounds):
                ckpt.save(r + 1, state)
        final = np.asarray(evaluate(state.sac.actor_params, keys))
        result = {"final_eval_return": final.tolist(), "mean": float(final.mean()), "std": float(final.std())}
        (run_dir / "final.json").write_text(json.dumps(result, indent=1))
    finally:
        if host is not None:
            host.close()
        logger.close()
        if ckpt is not None:
            ckpt.close()
    for i in range(0, args.columns, args.seeds):
        part = final[i : i + args.seeds]
        lam, teacher = grid[i]
        which = ([f"lambda {lam:g}"] if cfg.algo == "rebel" else []) + ([f"teacher {teacher}"] if teacher else [])
        which = f" ({', '.join(which)})" if which else ""
        print(f"final evaluation return over {args.seeds} seed(s){which}: {part.mean():.1f} +- {part.std():.1f}")
    print(f"run directory: {run_dir}")
    return result


def parse(argv: list[str] | None = None) -> Args:
    """Reads ``--preset`` and ``--teacher`` first, then every other flag as an override of them."""
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--preset", choices=sorted(PRESETS), default="paper")
    pre.add_argument("--teacher", choices=[*teachers.PRESETS, *HOST_TEACHERS], default="oracle")
    known, rest = pre.parse_known_args(argv)
    host_teacher = known.teacher if known.teacher in HOST_TEACHERS else ""
    scripted = "oracle" if host_teacher else known.teacher  # The human's answers are compared with the oracle's.
    description = (
        f"{__doc__}\nPreset: --preset {{{','.join(sorted(PRESETS))}}} (default paper)."
        f"\nTeacher: --teacher {{{','.join(teachers.PRESETS)}}} (default oracle); --teacher.* flags override it;"
        " --teacher human asks a person on a web page (--human.*), --teacher replay --human.labels FILE"
        " re-runs a human run's answers."
    )
    config = dataclasses.replace(PRESETS[known.preset], teacher=teachers.PRESETS[scripted])
    args = tyro.cli(Args, default=Args(config=config), args=rest, description=description)
    args = dataclasses.replace(args, host_teacher=host_teacher)
    try:
        args.config.validate()
        if args.seeds < 1:
            raise ConfigError(f"seeds={args.seeds!r} is invalid: allowed >= 1")
        if args.checkpoint_every < 0:
            raise ConfigError(f"checkpoint_every={args.checkpoint_every!r} is invalid: allowed >= 0")
        if args.time_limit < 0:
            raise ConfigError(f"time_limit={args.time_limit!r} is invalid: allowed >= 0")
        if args.lam_grid and args.config.algo != "rebel":
            raise ConfigError(f"lam_grid={args.lam_grid!r} is invalid: allowed only with --algo rebel")
        if args.teacher_grid and not args.config.preference:
            raise ConfigError(f"teacher_grid={args.teacher_grid!r} is invalid: allowed only with a preference algo")
        if host_teacher:
            _check_host_teacher(args)
        unknown = [t for t in args.teacher_grid if t not in teachers.PRESETS]
        if unknown:
            raise ConfigError(f"teacher_grid={unknown!r} is invalid: allowed {', '.join(teachers.PRESETS)}")
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from err
    return args


def _check_host_teacher(args: Args) -> None:
    """``--teacher human|replay``: one column of a preference method; ``--human.*`` in range."""
    teacher = f"--teacher {args.host_teacher}"
    if not args.config.preference:
        raise ConfigError(f"{teacher} is invalid with --algo {args.config.algo}: allowed only with a preference algo")
    if args.columns != 1:
        raise ConfigError(f"{teacher} labels one run: seeds={args.seeds}, lam_grid and teacher_grid must give 1 column")
    if not 0 <= args.human.port < 65536:
        raise ConfigError(f"human.port={args.human.port!r} is invalid: allowed 0 to 65535 (0: any free port)")
    if args.human.timeout < 0:
        raise ConfigError(f"human.timeout={args.human.timeout!r} is invalid: allowed >= 0 (0: no limit)")
    if args.human.clip_size < 16:
        raise ConfigError(f"human.clip_size={args.human.clip_size!r} is invalid: allowed >= 16")
    if args.host_teacher == "replay" and (args.human.labels is None or not args.human.labels.is_file()):
        raise ConfigError(f"human.labels={args.human.labels!r} is invalid: --teacher replay needs an existing file")
    if args.host_teacher == "human" and args.human.labels is not None:
        raise ConfigError("human.labels is only for --teacher replay (a human run writes RUN_DIR/labels.jsonl)")


def main(argv: list[str] | None = None) -> dict:
    args = parse(argv)
    if args.distributed:
        jax.distributed.initialize()
    try:
        return run(args)
    except HumanError as err:  # No OpenGL for the clips, a label file of another run, ...
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from err
