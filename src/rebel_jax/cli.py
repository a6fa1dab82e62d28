"""``python -m rebel_jax.train``: the host loop over jitted rounds, and its command line.

    python -m rebel_jax.train --preset paper --algo sac --task walker_walk --seeds 5

``--preset`` (``paper`` or ``tiny``) picks the defaults; every other flag overrides one
field of :class:`rebel_jax.config.Config` (``--help`` lists them with their docs).
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

from rebel_jax import sweep
from rebel_jax.checkpoint import Checkpointer
from rebel_jax.config import PRESETS, Config, ConfigError
from rebel_jax.logging import RunLogger
from rebel_jax.train import Trainer, compiled, seed_keys


@dataclasses.dataclass(frozen=True)
class Args:
    """Train one configuration on several seeds."""

    config: Annotated[Config, tyro.conf.OmitArgPrefixes]
    seeds: int = 1
    """Seeds run together (vmapped; sharded over all devices when there are several)."""
    run_dir: pathlib.Path | None = None
    """The run's directory; default ``runs/<algo>_<task>_<time>``."""
    resume: bool = False
    """Continue from the latest checkpoint in ``run_dir``."""
    checkpoint_every: int = 1
    """Rounds between checkpoints; 0 disables them."""
    progress: bool = True
    """Show a progress bar."""
    tensorboard: bool = True
    """Write TensorBoard event files."""
    distributed: bool = False
    """Call ``jax.distributed.initialize()`` first (multi-host runs)."""


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        return out.stdout.strip() or None
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
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
    }
    (run_dir / "meta.json").write_text(json.dumps(meta, indent=1))


def run(args: Args) -> dict:
    """Trains ``args.config`` on ``args.seeds`` seeds; returns the final per-seed evaluation."""
    cfg = args.config
    run_dir = args.run_dir or pathlib.Path("runs") / f"{cfg.algo}_{cfg.env.task}_{time.strftime('%Y%m%d-%H%M%S')}"
    trainer = Trainer(cfg)
    init, round_fn, evaluate = compiled(trainer)
    sharding = sweep.seed_sharding(args.seeds)
    keys = sweep.shard_seeds(seed_keys(cfg.train.seed, args.seeds), sharding)
    state = sweep.shard_seeds(init(keys), sharding)
    ckpt = Checkpointer(run_dir / "checkpoints") if args.checkpoint_every else None
    start = 0
    if args.resume:
        if ckpt is None or ckpt.latest() is None:
            raise FileNotFoundError(f"--resume: no checkpoint under {run_dir / 'checkpoints'}")
        start, state = ckpt.restore(state)
    else:
        _write_meta(run_dir, args)
    per_round = cfg.train.steps_per_round
    logger = RunLogger(run_dir, cfg.train.total_steps, start * per_round, args.progress, args.tensorboard)
    try:
        for r in range(start, cfg.train.num_rounds):
            t0 = time.perf_counter()
            state, metrics = round_fn(state, jnp.int32(r))
            metrics = jax.device_get(metrics)
            seconds = time.perf_counter() - t0
            env_steps = (r + 1) * per_round
            if env_steps % cfg.train.eval_every and r + 1 < cfg.train.num_rounds:
                metrics.pop("eval_return")
            extra = {"round": r, "seconds": seconds, "env_steps_per_s": per_round * args.seeds / seconds}
            logger.write(env_steps, metrics, extra)
            if ckpt is not None and ((r + 1) % args.checkpoint_every == 0 or r + 1 == cfg.train.num_rounds):
                ckpt.save(r + 1, state)
        final = np.asarray(evaluate(state.sac.actor_params, keys))
        result = {"final_eval_return": final.tolist(), "mean": float(final.mean()), "std": float(final.std())}
        (run_dir / "final.json").write_text(json.dumps(result, indent=1))
    finally:
        logger.close()
        if ckpt is not None:
            ckpt.close()
    print(f"final evaluation return over {args.seeds} seed(s): {result['mean']:.1f} +- {result['std']:.1f}")
    print(f"run directory: {run_dir}")
    return result


def parse(argv: list[str] | None = None) -> Args:
    """Reads ``--preset`` first, then every other flag as an override of that preset."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", choices=sorted(PRESETS), default="paper")
    known, rest = pre.parse_known_args(argv)
    description = f"{__doc__}\nPreset: --preset {{{','.join(sorted(PRESETS))}}} (default paper)."
    args = tyro.cli(Args, default=Args(config=PRESETS[known.preset]), args=rest, description=description)
    try:
        args.config.validate()
        if args.seeds < 1:
            raise ConfigError(f"seeds={args.seeds!r} is invalid: allowed >= 1")
        if args.checkpoint_every < 0:
            raise ConfigError(f"checkpoint_every={args.checkpoint_every!r} is invalid: allowed >= 0")
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(2) from err
    return args


def main(argv: list[str] | None = None) -> dict:
    args = parse(argv)
    if args.distributed:
        jax.distributed.initialize()
    return run(args)
