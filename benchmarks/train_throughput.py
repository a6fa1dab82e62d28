"""SAC training throughput at ``paper`` sizes.

Usage:
  python benchmarks/train_throughput.py update [--seeds 1 5 10] [--precisions tf32 highest bf16]
  python benchmarks/train_throughput.py runs RUN_DIR [RUN_DIR ...]

``update`` times the jitted, seed-vmapped SAC update alone (median of repeated scans
of 20 updates after a warm-up) and reports updates/s and achieved TFLOP/s against the
card's bf16 matmul ceiling. ``runs`` turns finished training runs (``python -m
rebel_jax.train``) into rows of whole-round throughput: seed-env-steps/s over the
rounds after the first (which includes compilation) and the projected wall time of
500k steps. Both merge rows into ``benchmarks/results/train_throughput.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import statistics
import sys

import jax
import jax.numpy as jnp
from timing import median_seconds

from rebel_jax import replay
from rebel_jax.config import PRESETS
from rebel_jax.sac import SAC, update_flops

RESULTS = pathlib.Path(__file__).parent / "results" / "train_throughput.json"
BF16_CEILING_TFLOPS = {"NVIDIA H100 80GB HBM3": 798.0, "NVIDIA H200": 788.0}  # measured, see BENCHMARKS.md
UPDATES_PER_CALL = 20


def _device() -> str:
    return jax.devices()[0].device_kind if jax.default_backend() != "cpu" else "cpu"


def _row(**kw) -> dict:
    base = {"device": _device(), "date": datetime.date.today().isoformat(), "jax": jax.__version__}
    return {**base, "command": " ".join(["python"] + sys.argv), **kw}


def time_update(num_seeds: int, precision: str, repeats: int = 5) -> float:
    """Median seconds of one seed-vmapped SAC update at ``paper`` sizes."""
    cfg = PRESETS["paper"]
    sac_cfg = cfg.sac.__class__(**{**vars(cfg.sac), "precision": precision})
    sac = SAC(sac_cfg, 24, 6)
    keys = jax.random.split(jax.random.PRNGKey(0), num_seeds)
    state = jax.jit(jax.vmap(sac.init))(keys)
    batch = replay.Transition(
        obs=jax.random.normal(keys[0], (num_seeds, sac_cfg.batch_size, 24)),
        action=jax.random.uniform(keys[0], (num_seeds, sac_cfg.batch_size, 6), minval=-1, maxval=1),
        reward=jax.random.uniform(keys[0], (num_seeds, sac_cfg.batch_size)),
        next_obs=jax.random.normal(keys[-1], (num_seeds, sac_cfg.batch_size, 24)),
        discount=jnp.ones((num_seeds, sac_cfg.batch_size)),
    )

    def many(state, key):
        body = lambda s, k: (jax.vmap(sac.update)(s, batch, jax.random.split(k, num_seeds))[0], None)
        return jax.lax.scan(body, state, jax.random.split(key, UPDATES_PER_CALL))[0]

    run = jax.jit(many, donate_argnums=0)
    return median_seconds(run, state, UPDATES_PER_CALL, repeats)


def update_rows(args):
    flops = update_flops(PRESETS["paper"].sac, 24, 6)
    for seeds in args.seeds:
        for precision in args.precisions:
            sec = time_update(seeds, precision)
            tflops = seeds * flops / sec / 1e12
            ceiling = BF16_CEILING_TFLOPS.get(_device())
            row = _row(
                what="update",
                algo="sac",
                preset="paper",
                seeds=seeds,
                precision=precision,
                num_envs=None,
                seed_env_steps_per_s=None,
                updates_per_s=seeds / sec,
                ms_per_update=sec * 1e3,
                update_tflops=tflops,
                fraction_of_bf16_ceiling=None if ceiling is None else tflops / ceiling,
                wall_s_500k=None,
            )
            print(f"update seeds {seeds:2d} {precision:7s}: {sec * 1e3:7.3f} ms  {tflops:7.1f} TFLOP/s")
            sys.stdout.flush()
            yield row


def run_rows(args):
    for run_dir in args.run_dirs:
        cfg = json.loads((run_dir / "config.json").read_text())
        meta = json.loads((run_dir / "meta.json").read_text())
        records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
        steady = [r["env_steps_per_s"] for r in records[1:]] or [records[0]["env_steps_per_s"]]
        rate = statistics.median(steady)
        seeds = meta["seeds"]
        total = records[-1]["env_steps"]
        updates = max(1, round(cfg["sac"]["utd"] * cfg["env"]["num_envs"]))
        flops = update_flops(PRESETS["paper"].sac, 24, 6)
        yield {
            "device": meta["devices"][0],
            "date": meta["started"][:10],
            "jax": meta["jax"],
            "command": meta["command"],
            "what": "round",
            "task": cfg["env"]["task"],
            "algo": cfg["algo"],
            "preset": "paper",
            "seeds": seeds,
            "precision": cfg["sac"]["precision"],
            "num_envs": cfg["env"]["num_envs"],
            "utd": cfg["sac"]["utd"],
            "seed_env_steps_per_s": rate,
            "updates_per_s": rate * updates / cfg["env"]["num_envs"],
            "update_tflops": None,
            "rounds_tflops_incl_env": rate * updates / cfg["env"]["num_envs"] * flops / 1e12,
            "wall_s_500k": 500_000 * seeds / rate,
            "wall_s_measured": sum(r["seconds"] for r in records),
            "env_steps": total,
        }


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mode", choices=["update", "runs"])
    p.add_argument("run_dirs", nargs="*", type=pathlib.Path)
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 5, 10])
    p.add_argument("--precisions", nargs="+", default=["tf32", "highest", "bf16"])
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    args = p.parse_args()
    results = json.loads(args.out.read_text()) if args.out.exists() else {"rows": []}
    key = lambda r: (r["device"], r["what"], r.get("algo"), r.get("task"), r["seeds"], r["precision"], r["num_envs"], r.get("utd"))
    for row in update_rows(args) if args.mode == "update" else run_rows(args):
        results["rows"] = [r for r in results["rows"] if key(r) != key(row)] + [row]
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
