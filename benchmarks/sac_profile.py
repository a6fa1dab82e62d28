"""Where the GPU time of the state SAC update, and of a whole training round, goes, kernel by kernel.

    python benchmarks/sac_profile.py --peak-tflops 800 \\
        --xla-flags=--xla_gpu_enable_command_buffer=          # the update at the paper preset, 5, 10, 20 columns
    python benchmarks/sac_profile.py --part round --columns 5 \\
        --xla-flags=--xla_gpu_enable_command_buffer=          # one PEBBLE walker_walk round of the paper preset
    python benchmarks/sac_profile.py --part round --columns 5 --impl warp \\
        --xla-flags=--xla_gpu_enable_command_buffer=          # the same with MuJoCo Warp's step
    python benchmarks/sac_profile.py --hidden 32 --batch-size 16 --columns 2 --repeats 1   # a CPU check
    python benchmarks/sac_profile.py --part round --preset tiny --task probe_point --columns 2   # a CPU check

``--part update`` profiles the seed-vmapped SAC update (``SAC.update`` of ``--columns`` seeds under ``jax.vmap``, the
program ``train_throughput.py update`` times: a fixed random batch, ``--updates-per-call`` updates in one ``lax.scan``
per jitted call) at the preset's sizes (``paper``: 2x1024 MLPs, batch 1024) and ``--precision``. ``--part round``
profiles one round of the trainer (``rebel_jax.train.compiled``'s seed-vmapped round, ``--algo`` on ``--task``),
round ``--round-index`` after a warm-up call of the same round; a round whose index has a feedback session includes
it.

The trace is read as ``kernel_profile`` says: the events of the program summed per HLO instruction, each put in a
category by its opcode (matrix products, fusions by kind: ``kLoop`` elementwise, ``kInput`` reductions, ...) and in
a part of the program by the Python call stack XLA kept for it (:data:`UPDATE_PARTS`, :data:`ROUND_PARTS`): for the
update the critic's and actor's losses (forward and backward), the temperature, the optimiser (optax's Adam) and the
target critic's Polyak step; for the round the physics, the SAC updates, acting, replay, the rewards and the feedback
session; in both, what XLA made without a call stack (copies, layout changes and casts it inserted: where float32
master copies and bf16 casts would show) apart from the ``other`` instructions of the code. The row (merged into
``benchmarks/results/sac_profile.json``) gives milliseconds per update (or per round) in all, per category, per part
and part by category, for the ``--top`` instructions, the traced events (on a GPU, kernels) per update, and the wall
time of the same calls: what the kernels leave of it is launch gaps and the host.
The update's row also gives the FLOPs of the matrix products of one compiled update (``kernel_profile.dot_flops``),
XLA's own count of all its FLOPs (``cost_analysis``), the analytic count ``rebel_jax.agents.sac.update_flops``, the
compiled update's launches (``train_throughput.hlo_counts``), and the achieved TFLOP/s of the matrix products against
``--peak-tflops`` (the card's bf16 matmul ceiling, e.g. about 800 on an H100; given, never guessed).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys

import jax
import jax.numpy as jnp
from kernel_profile import Rule, categories, dot_flops, module_name, parts, summarize, trace
from timing import add_xla_flags_argument, merge_rows, provenance, use_xla_flags
from train_throughput import hlo_counts

from rebel_jax.agents.sac import SAC, Transition, update_flops
from rebel_jax.api import make_trainer
from rebel_jax.config import PRESETS
from rebel_jax.core.errors import ConfigError
from rebel_jax.train import compiled as compiled_trainer
from rebel_jax.train import seed_keys

RESULTS = pathlib.Path(__file__).parent / "results" / "sac_profile.json"
PARTS = ("update", "round")
UPDATE_PARTS = (
    Rule("target update (Polyak)", "rebel_jax/agents/sac.py", "polyak"),
    Rule("optimiser (Adam)", "/optax/"),
    Rule("critic loss", "rebel_jax/agents/sac.py", "make_critic_loss"),
    Rule("actor loss", "rebel_jax/agents/sac.py", "make_actor_loss"),
    Rule("temperature", "rebel_jax/agents/sac.py", "alpha"),  # make_alpha_loss, SAC._alpha_step
    Rule("SAC.update itself (keys, counters)", "rebel_jax/agents/sac.py", "SAC.update"),
)
"""The parts of one SAC update, first match wins (Polyak's step calls optax's ``incremental_update``)."""
ROUND_PARTS = (
    Rule("SAC updates", "rebel_jax/agents/sac.py", "SAC.update"),
    Rule("feedback session", "", "feedback_session"),
    Rule("physics", "/mujoco/"),
    Rule("physics", "/brax/"),
    Rule("physics", "rebel_jax/envs/"),
    Rule("acting", "rebel_jax/agents/sac.py", "SAC.act"),  # act and act_deterministic
    Rule("replay", "rebel_jax/agents/replay.py"),
    Rule("intrinsic reward (pre-training)", "rebel_jax/preference/pretrain.py"),
    Rule("learned reward", "rebel_jax/preference/reward_model.py"),
    Rule("learned reward", "rebel_jax/methods/"),
    Rule("SAC updates", "rebel_jax/", "_updates"),  # the updates' loop: its carry's copies and casts
)
"""The parts of one round, first match wins. The environment's task rewards and resets count as physics; the
learned reward of the stored transitions and of the update batches as ``learned reward``; what the loop of a vector
step's updates does besides (its carry's copies and casts) as ``SAC updates``."""


def random_minibatch(sac, keys: jax.Array) -> Transition:
    """One random minibatch of ``sac``'s size for each of ``keys``' columns (leading axis ``len(keys)``)."""
    columns, n = len(keys), sac.cfg.batch_size
    return Transition(
        obs=jax.random.normal(keys[0], (columns, n, sac.obs_size)),
        action=jax.random.uniform(keys[0], (columns, n, sac.action_size), minval=-1, maxval=1),
        reward=jax.random.uniform(keys[0], (columns, n)),
        next_obs=jax.random.normal(keys[-1], (columns, n, sac.obs_size)),
        discount=jnp.ones((columns, n)),
    )


def update_program(sac, columns: int, per_call: int):
    """(jitted, state-donating ``(state, key) -> state`` doing ``per_call`` seed-vmapped ``sac`` updates of
    ``columns`` seeds on one fixed random batch, the first state, the batch), as ``train_throughput.py`` builds it.
    """
    keys = jax.random.split(jax.random.PRNGKey(0), columns)
    state = jax.jit(jax.vmap(sac.init))(keys)
    batch = random_minibatch(sac, keys)

    def many(state, key):
        body = lambda s, k: (jax.vmap(sac.update)(s, batch, jax.random.split(k, columns))[0], None)
        return jax.lax.scan(body, state, jax.random.split(key, per_call))[0]

    return jax.jit(many, donate_argnums=0), state, batch


def one_update(sac, state, batch):
    """One seed-vmapped update of ``state``'s seeds on ``batch``, compiled from shapes (for its counts)."""
    keys = jax.ShapeDtypeStruct((batch.reward.shape[0], 2), jnp.uint32)
    shapes = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), (state, batch))
    return jax.jit(jax.vmap(sac.update)).lower(*shapes, keys).compile()


def sac_config(args):
    """The preset's SAC settings with the command line's precision and sizes."""
    base = PRESETS[args.preset].sac
    return dataclasses.replace(
        base,
        precision=args.precision,
        hidden=args.hidden or base.hidden,
        depth=args.depth or base.depth,
        batch_size=args.batch_size or base.batch_size,
    )


def save_hlo(args, text: str, name: str) -> str:
    """``text``, written to ``--hlo-dir``/``name``.txt if given (to look up an instruction of the profile)."""
    if args.hlo_dir is not None:
        args.hlo_dir.mkdir(parents=True, exist_ok=True)
        (args.hlo_dir / f"{name}.txt").write_text(text)
    return text


def update_row(args, columns: int) -> dict:
    cfg = sac_config(args)
    sac = SAC(cfg, args.obs_size, args.action_size)
    run, state, batch = update_program(sac, columns, args.updates_per_call)
    single = one_update(sac, state, batch)
    single_text = single.as_text()
    cost = single.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    program = run.lower(state, jax.random.PRNGKey(1)).compile()
    text = save_hlo(args, program.as_text(), f"update_{columns}")
    state = jax.block_until_ready(program(state, jax.random.PRNGKey(2)))  # warm-up
    step = lambda state, i: program(state, jax.random.PRNGKey(10 + i))
    events, lines, wall, _ = trace(step, state, args.repeats, module_name(text))
    if not events:
        raise SystemExit("the trace holds no event of the update's program; nothing to report")
    updates = args.repeats * args.updates_per_call
    matmul = dot_flops(single_text)
    wall_s = wall / updates
    tflops = matmul / wall_s / 1e12
    return {
        **provenance(),
        "part": "update",
        "preset": args.preset,
        "columns": columns,
        "precision": cfg.precision,
        "hidden": cfg.hidden,
        "depth": cfg.depth,
        "batch_size": cfg.batch_size,
        "obs_size": args.obs_size,
        "action_size": args.action_size,
        "updates": updates,
        "wall_ms_per_update": round(wall_s * 1e3, 4),
        "matmul_flops_per_update": matmul,
        "analytic_flops_per_update": columns * update_flops(cfg, args.obs_size, args.action_size),
        "xla_flops_per_update": cost.get("flops"),
        "matmul_tflops": round(tflops, 3),
        "peak_tflops": args.peak_tflops,
        "fraction_of_peak": round(tflops / args.peak_tflops, 4) if args.peak_tflops else None,
        "compiled_launches_per_update": hlo_counts(single)["launches"],
        "lines": lines,
        **summarize(events, categories(text), updates, args.top, parts(text, UPDATE_PARTS)),
    }


def round_config(args):
    """The preset with the command line's algorithm, task, precision and round length."""
    cfg = PRESETS[args.preset]
    cfg = dataclasses.replace(
        cfg,
        algo=args.algo,
        env=dataclasses.replace(cfg.env, task=args.task or cfg.env.task, impl=args.impl),
        sac=dataclasses.replace(cfg.sac, precision=args.precision),
        train=dataclasses.replace(cfg.train, steps_per_round=args.steps_per_round or cfg.train.steps_per_round),
    )
    return cfg.validate()


def round_row(args, columns: int) -> dict:
    cfg = round_config(args)
    trainer = make_trainer(cfg)
    init, round_fn, _ = compiled_trainer(trainer)
    state = init(seed_keys(cfg.train.seed, columns))
    index = jnp.int32(args.round_index)
    program = round_fn.lower(state, index).compile()
    text = save_hlo(args, program.as_text(), f"round_{cfg.algo}_{cfg.env.task}_{columns}")
    state = jax.block_until_ready(program(state, index)[0])  # warm-up: the same round, once
    step = lambda state, i: program(state, index)[0]
    events, lines, wall, _ = trace(step, state, args.repeats, module_name(text))
    if not events:
        raise SystemExit("the trace holds no event of the round's program; nothing to report")
    vector_steps = trainer.steps_per_round
    summary = summarize(events, categories(text), args.repeats, args.top, parts(text, ROUND_PARTS))
    rename = {"traced_ms_per_update": "traced_ms_per_round", "kernels_per_update": "kernels_per_round"}
    return {
        **provenance(),
        "part": "round",
        "preset": args.preset,
        "algo": cfg.algo,
        "task": cfg.env.task,
        "impl": cfg.env.impl,
        "columns": columns,
        "precision": cfg.sac.precision,
        "hidden": cfg.sac.hidden,
        "batch_size": cfg.sac.batch_size,
        "num_envs": cfg.env.num_envs,
        "steps_per_round": cfg.train.steps_per_round,
        "round_index": args.round_index,
        "vector_steps": vector_steps,
        "updates_per_vector_step": trainer.updates_per_step,
        "rounds": args.repeats,
        "wall_ms_per_round": round(wall * 1e3 / args.repeats, 4),
        "wall_ms_per_vector_step": round(wall * 1e3 / args.repeats / vector_steps, 4),
        "lines": lines,
        **{rename.get(k, k): v for k, v in summary.items()},
    }


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--part", default="update", choices=PARTS)
    p.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    p.add_argument("--columns", nargs="+", type=int, default=[5, 10, 20], help="seeds in one vmapped program")
    p.add_argument("--precision", default="bf16", choices=["tf32", "highest", "bf16"])
    p.add_argument("--peak-tflops", type=float, default=0.0, help="the card's bf16 matmul ceiling (0: not given)")
    p.add_argument("--repeats", type=int, default=5, help="traced calls (rounds for --part round)")
    p.add_argument("--top", type=int, default=20, help="instructions listed by time")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    p.add_argument("--hlo-dir", type=pathlib.Path, default=None, help="write each profiled program's HLO text here")
    update = p.add_argument_group("--part update")
    update.add_argument("--hidden", type=int, default=0, help="hidden width (0: the preset's)")
    update.add_argument("--depth", type=int, default=0, help="hidden layers (0: the preset's)")
    update.add_argument("--batch-size", type=int, default=0, help="transitions per update (0: the preset's)")
    update.add_argument("--obs-size", type=int, default=24, help="observation size (walker's 24)")
    update.add_argument("--action-size", type=int, default=6, help="action size (walker's 6)")
    update.add_argument("--updates-per-call", type=int, default=20)
    rounds = p.add_argument_group("--part round")
    rounds.add_argument("--algo", default="pebble", help="the trainer's algorithm (default pebble)")
    rounds.add_argument("--task", default="", help="the task (default: the preset's, walker_walk for paper)")
    rounds.add_argument("--steps-per-round", type=int, default=0, help="environment steps per round (0: preset's)")
    rounds.add_argument("--impl", default="jax", choices=["jax", "warp"], help="the physics step (env.impl)")
    rounds.add_argument("--round-index", type=int, default=2, help="which round (2: paper's first without session)")
    add_xla_flags_argument(p)
    return p


def usage_error(message: str) -> SystemExit:
    """``error: message`` on stderr and exit status 2, as the command line's user errors."""
    print(f"error: {message}", file=sys.stderr, flush=True)
    return SystemExit(2)


def check(args) -> None:
    """Refuses counts below 1, a negative peak and a round the run does not have (:func:`usage_error`)."""
    counts = {"--repeats": args.repeats, "--updates-per-call": args.updates_per_call, "--top": args.top}
    counts.update({"--columns": min(args.columns)})
    for name, value in counts.items():
        if value < 1:
            raise usage_error(f"{name} must be at least 1, not {value}")
    if args.peak_tflops < 0:
        raise usage_error(f"--peak-tflops must be positive (or 0: not given), not {args.peak_tflops}")
    if args.part == "round":
        try:
            rounds = round_config(args).train.num_rounds
        except ConfigError as err:
            raise usage_error(str(err)) from None
        if not 0 <= args.round_index < rounds:
            raise usage_error(f"--round-index {args.round_index} is not a round of this run (0..{rounds - 1})")


def main(argv=None):
    args = parser().parse_args(argv)
    check(args)
    use_xla_flags(args.xla_flags)
    row = {"update": update_row, "round": round_row}[args.part]
    key = ("device", "commit", "part", "preset", "algo", "task", "columns", "precision", "hidden", "batch_size")
    key += ("impl", "steps_per_round", "round_index", "xla_flags")
    for columns in args.columns:
        result = row(args, columns)
        print(json.dumps({k: v for k, v in result.items() if k != "top"}, indent=1), flush=True)
        merge_rows(args.out, [result], key)


if __name__ == "__main__":
    main()
