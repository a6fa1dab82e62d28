"""A short pixel PEBBLE run at 84x84 on one GPU: compile time, round times with and without a feedback
session, and the device's peak memory (a smoke test of the sizes, not a learning result).

Not yet run to the end (2026-11-24): no device time was left, and on the 2-core CPU its first round
(compilation, then 500 vector steps of DrQ-v2 updates of 256) did not finish in 400 s.

    python benchmarks/pixel_preference_smoke.py --algo pebble --task walker_walk_pixels
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import jax
import jax.numpy as jnp

from rebel_jax import frame_replay
from rebel_jax.config import Config, EnvConfig, FeedbackConfig, TrainConfig
from rebel_jax.drqv2 import task_config
from rebel_jax.pixel_train import PixelTrainer
from rebel_jax.queries import QueryConfig
from rebel_jax.train import compiled, seed_keys


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--algo", default="pebble")
    p.add_argument("--task", default="walker_walk_pixels")
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--sampling", default="uniform")
    args = p.parse_args()
    base = Config(
        algo=args.algo,
        env=EnvConfig(task=args.task, num_envs=2, episode_length=1000),
        train=TrainConfig(total_steps=4000, seed_steps=1000, steps_per_round=1000, eval_every=1000, eval_episodes=1),
        feedback=FeedbackConfig(labels=40, per_session=10, interval=1000),
        query=QueryConfig(segment_length=50, sampling=args.sampling),
    )
    cfg = dataclasses.replace(base, drqv2=task_config(args.task, base.drqv2))
    trainer = PixelTrainer(cfg)
    init, round_fn, _ = compiled(trainer)
    state = init(seed_keys(0, args.seeds))
    rows = []
    for r in range(args.rounds):
        start = time.time()
        state, metrics = round_fn(state, jnp.int32(r))
        metrics = jax.device_get(metrics)
        rows.append(
            {
                "round": r,
                "seconds": round(time.time() - start, 2),
                **{
                    k: float(v.mean())
                    for k, v in metrics.items()
                    if k in ("labels_used", "reward_epochs", "reward_loss", "reward_correlation", "diverged")
                },
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    buffer = jax.tree.map(lambda x: x[0], state.buffer)
    stats = jax.devices()[0].memory_stats() or {}
    print(
        json.dumps(
            {
                "device": str(jax.devices()[0]),
                "buffer_gb_per_seed": frame_replay.nbytes(buffer) / 1e9,
                "peak_gb": stats.get("peak_bytes_in_use", 0) / 1e9,
                "trace_count": trainer.trace_count,
            }
        )
    )


if __name__ == "__main__":
    main()
