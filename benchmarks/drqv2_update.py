"""The seed-vmapped DrQ-v2 update alone, its seeds batched (``drqv2.seed_loop`` off) against looped (on).

    python benchmarks/drqv2_update.py                      # 84x84, 5 seeds, walker (batch 512, n-step 1)
    python benchmarks/drqv2_update.py --size 16 --batch-size 8 --seeds 2 --repeats 2   # a CPU check

One row per setting (``--seed-loop``, ``--kernel-grad``: ``drqv2.kernel_grad``, and ``--first-channels``:
``drqv2.first_channels``, the first convolution's input zero-padded from 9 channels): the median
milliseconds of one update of every seed (``ms_per_update``), over ``--repeats`` calls of a jitted
``lax.scan`` of ``--updates-per-call`` updates after a warm-up call, on fixed random uint8 frame stacks;
the agent step is unbatched, as in the trainer. ``grouped_convolutions`` counts the compiled program's
convolutions with ``feature_group_count`` or ``batch_group_count`` above 1
(the batched update's encoder convolutions, which the loop removes). Rows merge into
``benchmarks/results/drqv2_update.json`` after each one. ``REBEL_JAX_GIT_COMMIT`` names the commit where
the tree was copied without its history.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import pathlib
import re

import jax
import jax.numpy as jnp
from timing import median_seconds, merge_rows, provenance

from rebel_jax.agents.drqv2 import DrQV2, DrQV2Config, PixelTransition, task_config

RESULTS = pathlib.Path(__file__).parent / "results" / "drqv2_update.json"
WALKER_ACTIONS = 6
FRAMES = 3  # frame stack: 3 RGB frames, 9 channels


def grouped_convolutions(hlo: str) -> int:
    """Convolutions of an HLO module's text with ``feature_group_count`` or ``batch_group_count`` above 1."""
    counts = (re.findall(r"(?:feature|batch)_group_count=(\d+)", line) for line in hlo.splitlines())
    return sum(any(int(n) > 1 for n in found) for found in counts)


def random_batch(key: jax.Array, shape: tuple[int, ...], size: int, gamma: float) -> PixelTransition:
    """Random transitions of walker's shapes: uint8 frame stacks (``size`` x ``size``, 3 frames), actions in
    [-1, 1], rewards in [0, 1), ``shape`` leading."""
    key_obs, key_next, key_action, key_reward = jax.random.split(key, 4)
    pixels = lambda key: jax.random.randint(key, (*shape, size, size, 3 * FRAMES), 0, 256).astype(jnp.uint8)
    return PixelTransition(
        obs=pixels(key_obs),
        action=jax.random.uniform(key_action, (*shape, WALKER_ACTIONS), minval=-1, maxval=1),
        reward=jax.random.uniform(key_reward, shape),
        discount=jnp.full(shape, gamma),
        next_obs=pixels(key_next),
    )


def update_scan(cfg: DrQV2Config, size: int, seeds: int, per_call: int):
    """(jitted ``(state, key) -> state`` of ``per_call`` seed-vmapped updates on fixed batches, the seeds' state)."""
    agent = DrQV2(cfg, (size, size, 3 * FRAMES), WALKER_ACTIONS)
    state = jax.jit(jax.vmap(agent.init))(jax.random.split(jax.random.PRNGKey(0), seeds))
    batch = random_batch(jax.random.PRNGKey(3), (seeds, cfg.batch_size), size, cfg.gamma)
    update = jax.vmap(agent.update, in_axes=(0, 0, 0, None))

    def many(state, key):
        def body(state, key):
            return update(state, batch, jax.random.split(key, seeds), jnp.int32(10_000))[0], None

        return jax.lax.scan(body, state, jax.random.split(key, per_call))[0]

    return jax.jit(many, donate_argnums=0), state


def program_fields(args, cfg: DrQV2Config) -> dict:
    """The fields of a result row that name the update's program."""
    return {
        "seeds": args.seeds,
        "size": args.size,
        "batch_size": cfg.batch_size,
        "nstep": cfg.nstep,
        "precision": cfg.precision,
        "seed_loop": cfg.seed_loop,
    }


def rows(args):
    base = task_config("walker_walk", DrQV2Config(precision=args.precision))
    base = dataclasses.replace(base, batch_size=args.batch_size or base.batch_size)
    for loop, grad, first in itertools.product(args.seed_loop, args.kernel_grad, args.first_channels):
        cfg = dataclasses.replace(base, seed_loop=loop == "on", kernel_grad=grad, first_channels=first)
        run, state = update_scan(cfg, args.size, args.seeds, args.updates_per_call)
        compiled = run.lower(state, jax.random.PRNGKey(1)).compile()
        grouped = grouped_convolutions(compiled.as_text())
        sec = median_seconds(compiled, state, args.updates_per_call, args.repeats)
        row = {
            **provenance(),
            **program_fields(args, cfg),
            "kernel_grad": cfg.kernel_grad,
            "first_channels": cfg.first_channels,
            "ms_per_update": sec * 1e3,
            "ms_per_seed_update": sec * 1e3 / args.seeds,
            "grouped_convolutions": grouped,
        }
        print(json.dumps(row), flush=True)
        yield row


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--size", type=int, default=84, help="image height and width")
    p.add_argument("--batch-size", type=int, default=0, help="transitions per update (0: walker's 512)")
    p.add_argument("--precision", default="tf32", choices=["tf32", "highest", "bf16"])
    p.add_argument("--seed-loop", nargs="+", default=["off", "on"], choices=["off", "on"])
    p.add_argument("--kernel-grad", nargs="+", default=["xla"], choices=["xla", "patches"])
    p.add_argument("--first-channels", nargs="+", type=int, default=[0], help="0: the 9 channels as they are")
    p.add_argument("--updates-per-call", type=int, default=10)
    p.add_argument("--repeats", type=int, default=5, help="timed calls per row")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    merge_rows(
        args.out,
        rows(args),
        ("device", "commit", "seeds", "size", "batch_size", "precision", "seed_loop", "kernel_grad", "first_channels"),
    )


if __name__ == "__main__":
    main()
