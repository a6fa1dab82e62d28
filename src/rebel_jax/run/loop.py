"""One run's rounds in a prepared run directory, as one object.

The command line (:mod:`rebel_jax.run.cli`) builds the config and the run directory once and hands them to a
:class:`Run`: it builds the trainer and its compiled programs, starts the state or restores it from the newest
checkpoint, and trains round after round (:meth:`Run.rounds`) with its checkpoints and logs; :meth:`Run.finish`
evaluates the final policy and writes ``final.json``, the learning curve and the clip. The command line prints
what comes back (:func:`rebel_jax.run.cli_outputs.report`).

With several processes (``--distributed``) every process runs its devices' seeds and saves its part of each
checkpoint; process 0 alone writes ``metrics.jsonl``, ``final.json``, TensorBoard files and the clip, and prints.
"""

from __future__ import annotations

import concurrent.futures
import functools
import json
import math
import pathlib
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding

from rebel_jax import api
from rebel_jax.config import ConfigError
from rebel_jax.preference import teachers
from rebel_jax.run import rundir, video
from rebel_jax.run.checkpoint import Checkpointer, CheckpointMismatch
from rebel_jax.run.cli_args import Args, swept_knob
from rebel_jax.run.cli_outputs import _eval_clip, _final_result, _learning_curve, method_metrics
from rebel_jax.run.cli_rundir import device_columns, start_run_files
from rebel_jax.run.human import HostTeacher
from rebel_jax.run.logging import RunLogger, write_json
from rebel_jax.train import compiled, grow_replay, placement, replay_rows, seed_keys

EXIT_DIVERGED = 3
STATE_FLAGS = {
    "buffer": "--buffer-capacity (0: --total-steps)",
    "agent": "--sac.hidden / --sac.depth (pixels: --drqv2.hidden, --drqv2.feature-dim)",
    "reward": "--reward.hidden, --reward.label-capacity (pixels: --pixel-reward.*)",
    "env": "--num-envs / --eval-episodes",
    "eval_trajectory": "--rebel.horizon / --rebel.episodes",
}
"""The flags that drive the size of each part of the run's state (for ``rundir.check_memory``)."""


def _restore(run_dir: pathlib.Path, ckpt: Checkpointer, state, sharding):
    """(first round to run, state) from the newest readable checkpoint; (0, ``state``) if there is none.

    A checkpoint of a run now extended by a larger ``--total-steps`` holds a smaller replay buffer:
    it is restored as saved (each buffer leaf's rows read from the checkpoint) and then grown.
    """
    rows = replay_rows(state)  # (seeds, rows, envs)
    leaves = jax.tree.leaves(state)
    reward_leaf = next(i for i, x in enumerate(leaves) if x is state.buffer.true_reward)
    first = next(i for i, x in enumerate(leaves) if x is jax.tree.leaves(state.buffer)[0])  # the buffer's leaves

    def adapt(like, shapes):
        saved = shapes[str(reward_leaf)]  # another leaf where other code saved another state: the check refuses it
        if len(saved) < 2 or saved[1] == rows:
            return like

        def saved_rows(i, x):  # x[:, :n] where the saved leaf has n < x.shape[1] rows (any other difference is
            saved = shapes.get(str(first + i), x.shape)  # left for the checkpoint's shape check to refuse)
            return x[:, : saved[1]] if x.ndim >= 2 and len(saved) == x.ndim and saved[1] < x.shape[1] else x

        buffer, treedef = jax.tree.flatten(like.buffer)
        return like.replace(buffer=jax.tree.unflatten(treedef, [saved_rows(i, x) for i, x in enumerate(buffer)]))

    finished = (run_dir / "final.json").exists()
    if ckpt.latest() is None and not finished:
        print(f"note: --resume: no checkpoint in {run_dir} yet; starting the run from scratch", file=sys.stderr)
        return 0, state
    try:
        start, restored = ckpt.restore(state, adapt=adapt)
    except CheckpointMismatch as err:  # Other code wrote it: refuse, and keep the run's logs as they are.
        commit = json.loads((run_dir / "meta.json").read_text()).get("git_commit", "unknown")
        raise ConfigError(
            f"--resume: {err}. It was written by other code (meta.json: git_commit {commit}); resume it "
            "with that code, or start a new --run-dir"
        ) from err
    except FileNotFoundError as err:
        if finished:  # Starting over would replace a finished run's results.
            raise ConfigError(
                f"--resume: {err}, and {run_dir} holds a finished run (final.json): it would start over and replace "
                "it; use another --run-dir, or --overwrite to replace it"
            ) from None
        print(f"note: --resume: {err}; starting the run from scratch", file=sys.stderr)
        return 0, state
    if replay_rows(restored) != rows:
        restored = placement.shard_seeds(grow_replay(restored, state), sharding)
    return start, restored


def _slow_checkpoint_note(r: int, saving: float, seconds: float, every: int) -> str:
    """Said once per run when a checkpoint takes longer than the round it follows (e.g. a large replay on a GPU)."""
    suggested = every * math.ceil(4 * saving / max(seconds, 1e-9))  # saves then take at most a fifth of the time
    return (
        f"note: round {r}'s checkpoint took {saving:.1f} s, longer than the round ({seconds:.1f} s): "
        f"--checkpoint-every {suggested} would spend at most a fifth of the time saving "
        f"(a kill then loses up to {suggested} rounds; 0 saves none)"
    )


def column_keys(args: Args, sharding: NamedSharding | None = None, total: int | None = None) -> jax.Array:
    """One key per column: the seed keys tiled over the grid (each lambda's and teacher's seed i uses key i), then
    the last one repeated up to ``total`` columns (``placement.padded_columns``; default ``args.columns``)."""
    keys = jnp.tile(seed_keys(args.config.train.seed, args.seeds), (args.columns // args.seeds, 1))
    return placement.shard_seeds(placement.pad_columns(keys, total or args.columns), sharding)


def initial_state(args: Args, init: Callable, keys: jax.Array, sharding: NamedSharding | None = None, trainer=None):
    """The run's first state: ``init`` (of ``train.compiled``) of the :func:`column_keys`, with each column's
    lambda and teacher knobs set by the trainer (``Trainer.with_knobs``; ``api.make_trainer(args.config)`` unless
    given); padding columns (beyond ``args.columns``) take the last column's."""
    trainer = trainer or api.make_trainer(args.config)
    grid = args.grid()
    grid += grid[-1:] * (keys.shape[0] - len(grid))
    lams = [lam for lam, _ in grid] if swept_knob(args.config) else None
    teacher_cfgs = [teachers.PRESETS[t] for _, t in grid] if args.teacher_grid else None
    return placement.shard_seeds(trainer.with_knobs(init(keys), lams, teacher_cfgs), sharding)


def _compiled_beside_kernels(trainer, round_fn: Callable, shapes, one_device: bool) -> tuple[Callable, float]:
    """With MuJoCo Warp's step, its kernels built in a thread (``DMCEnv.build_warp_kernels``) while XLA compiles
    the round ahead of its first call (on one device; several devices compile theirs at the first call), and the
    seconds that took; ``round_fn`` and 0 with the JAX step. The build ends here, before any program steps the
    environments (the cheetah's reset does)."""
    env = trainer.env
    while not hasattr(env, "build_warp_kernels") and hasattr(env, "env"):  # a PixelEnv holds its DMCEnv
        env = env.env
    if getattr(env, "impl", "jax") != "warp":
        return round_fn, 0.0
    if placement.is_primary():
        print("building MuJoCo Warp's kernels while the round program compiles", flush=True)
    started = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="warp_kernels") as pool:
        build = pool.submit(env.build_warp_kernels)
        if one_device:
            round_fn = round_fn.lower(shapes, jax.ShapeDtypeStruct((), jnp.int32)).compile()
        failed = build.exception()  # waits for the build
        if failed is not None:  # the first step builds them instead
            print(f"note: MuJoCo Warp's kernels were not built ahead: {failed}", file=sys.stderr)
    return round_fn, time.perf_counter() - started


FINAL_FLAGS = (False, True)
"""The final evaluation: the policy's and random actions' episodes on the same initial states, in one batch."""


def _final_evaluation(evaluate: Callable, trainer, shapes, keys: jax.Array) -> Callable:
    """The final evaluation as a function of the policy: (returns, success rates), each (columns, 2) in the order of
    :data:`FINAL_FLAGS`, the success rates None on a task that does not report success (``Trainer.evaluate``).

    On one device its program is compiled here: called while the first round runs on an accelerator (dispatched,
    not yet waited for), the compile is hidden behind the round instead of adding to the job's end (on a GPU,
    seconds). Several devices compile at the call."""
    success = trainer.reports_success
    options = {"success": True} if success else {}  # a task without success: its program as before

    def split(out):
        return out if success else (out, None)

    if not hasattr(evaluate, "compile_ahead"):
        return lambda policy: split(evaluate(policy, keys, FINAL_FLAGS, **options))
    program = evaluate.compile_ahead(jax.eval_shape(trainer.policy_params, shapes), keys, FINAL_FLAGS, **options)
    return lambda policy: split(program(policy, keys))


class Run:
    """The rounds of one run in ``run_dir`` (prepared by ``cli_rundir.prepare_run_dir``).

    Args:
      args: the parsed command line (its config, seeds, grids and run options).
      run_dir: the run directory.
      command: the command line as typed (``meta.json``).
      resuming: whether ``run_dir`` holds a run to resume; default ``--resume`` and a saved ``config.json`` (with
        several processes, the command line decides on process 0 and tells all).

    Used as a context manager: its checkpointer, logger and labelling page are closed on the way out, each one
    even if another fails.
    """

    def __init__(self, args: Args, run_dir: pathlib.Path, command: str, resuming: bool | None = None):
        cfg = self.cfg = args.config
        self.args, self.run_dir = args, run_dir
        self.primary = primary = placement.is_primary()
        self.ckpt = self.logger = self.host = None
        if resuming is None:
            resuming = args.resume and (run_dir / "config.json").exists()
        total = device_columns(run_dir, args, jax.device_count(), resuming)  # args.columns, padded for the devices
        self.trainer = trainer = api.make_trainer(
            cfg, host_teacher=bool(args.host_teacher), columns=-(-total // jax.device_count())
        )
        # The human teacher's page and renderer start first: a machine that cannot render fails now.
        if args.host_teacher:
            self.host = HostTeacher(trainer, args.host_teacher, run_dir, args.human, args.resume)
        self.sharding = sharding = placement.seed_sharding(total)
        init, round_fn, evaluate = compiled(trainer, sharding)
        keys = column_keys(args, sharding, total)
        shapes = jax.eval_shape(init, keys)  # nothing allocated yet
        devices = sharding.mesh.devices.ravel().tolist() if sharding else jax.devices()[:1]
        rundir.check_memory(rundir.tree_bytes(shapes), devices, STATE_FLAGS, memory_of=jax.local_devices()[0])
        self.round_fn, self.ahead = _compiled_beside_kernels(trainer, round_fn, shapes, sharding is None)
        state = initial_state(args, init, keys, sharding, trainer)
        use_ckpt = args.checkpoint_every or args.resume or args.time_limit
        checksums = not resuming or bool(json.loads((run_dir / "meta.json").read_text()).get(rundir.CHECKSUMS_FIELD))
        self.ckpt = Checkpointer(run_dir / "checkpoints", require_checksums=checksums) if use_ckpt else None
        start = 0
        if resuming:
            start, state = _restore(run_dir, self.ckpt, state, sharding)
        if primary:
            start_run_files(run_dir, args, command, total, resuming, start)
        self.state, self.start = state, start
        self.names = args.column_names()
        per_round = cfg.train.steps_per_round
        if primary:
            self.logger = RunLogger(
                run_dir, cfg.train.total_steps, start * per_round, args.progress, args.tensorboard, self.names
            )
        if primary and not args.progress and start < cfg.train.num_rounds:  # A plain log says what its first wait is.
            print(
                f"{start * per_round:,}/{cfg.train.total_steps:,} steps: "
                f"{'' if self.ahead else 'compiling the round program, then '}round {start + 1} of "
                f"{cfg.train.num_rounds}{'' if self.ahead else ' (minutes for a large preset on a CPU)'}",
                flush=True,
            )
        self.final_evaluation = functools.cache(lambda: _final_evaluation(evaluate, trainer, shapes, keys))
        self.ever_diverged = np.zeros(args.columns, bool)
        self.final = self.random = self.success = None

    def __enter__(self) -> Run:
        return self

    def __exit__(self, *exc) -> None:
        rundir.close_all((self.ckpt, self.logger, self.host))  # each one, even if another fails: orbax's threads end

    def real_columns(self, tree):
        """The run's columns of ``tree``, without the padding."""
        return jax.tree.map(lambda x: x[: self.args.columns], tree)

    def rounds(self) -> dict | None:
        """Trains from the first round not yet run to the last: ``{"stopped_at_round": r}`` if ``--time-limit``
        stopped it (after saving a checkpoint), else None.

        Raises:
          SystemExit: with :data:`EXIT_DIVERGED` if a seed diverged and ``--on-divergence stop``.
        """
        args, cfg, ckpt = self.args, self.cfg, self.ckpt
        per_round = cfg.train.steps_per_round
        started, slowest = time.perf_counter() - self.ahead, 0.0  # --time-limit counts the compile ahead too
        slow_save_noted = False
        for r in range(self.start, cfg.train.num_rounds):
            # Process 0's clock decides for all (every process must run the same rounds).
            out_of_time = time.perf_counter() - started + 1.2 * slowest > args.time_limit
            if args.time_limit and r > self.start and placement.from_primary(int(out_of_time)):
                if ckpt is not None and ckpt.latest() != r:
                    ckpt.save(r, self.state)
                if self.primary:
                    print(f"--time-limit {args.time_limit:g} s: stopped after round {r - 1}; continue with --resume")
                return {"stopped_at_round": r}
            session = {}
            if self.host is not None:  # The human or replay teacher's session, between rounds.
                self.state, session = self.host.before_round(self.state, r)
            t0 = time.perf_counter()
            self.state, metrics = self.round_fn(self.state, jnp.int32(r))
            if r == self.start:
                self.final_evaluation()  # compiled while the round runs
            metrics = {**self.real_columns(placement.to_host(metrics)), **session}
            seconds = time.perf_counter() - t0 + (self.ahead if r == self.start else 0.0)  # with its compile
            slowest = max(slowest, seconds) if r > self.start else 0.0
            env_steps = (r + 1) * per_round
            if env_steps % cfg.train.eval_every and r + 1 < cfg.train.num_rounds:
                metrics.pop("eval_return")
                metrics.pop("eval_success", None)
            diverged = np.asarray(metrics["diverged"], float).reshape(-1) > 0
            extra = {"round": r, "seconds": seconds, "env_steps_per_s": per_round * args.columns / seconds}
            if self.logger is not None:
                self.logger.write(env_steps, metrics, extra)
            if diverged.any():
                self._diverged(r, diverged)
            if args.checkpoint_every and ((r + 1) % args.checkpoint_every == 0 or r + 1 == cfg.train.num_rounds):
                t0 = time.perf_counter()  # The wait for the previous save and this one's copy to the host; its
                ckpt.save(r + 1, self.state, wait=r + 1 == cfg.train.num_rounds)  # files are written next round.
                saving = time.perf_counter() - t0
                if self.primary and not slow_save_noted and saving > seconds and r + 1 < cfg.train.num_rounds:
                    slow_save_noted = True
                    print(_slow_checkpoint_note(r, saving, seconds, args.checkpoint_every), file=sys.stderr)
        return None

    def _diverged(self, r: int, diverged: np.ndarray) -> None:
        """Round ``r`` left seeds ``diverged``: stop (``--on-divergence stop``: final.json says so, exit status 3)
        or warn once per seed and go on."""
        which = ", ".join(self.names[i] for i in np.flatnonzero(diverged & ~self.ever_diverged))
        self.ever_diverged |= diverged
        if self.args.on_divergence == "stop":
            nan = np.full(self.args.columns, np.nan)
            success = nan if self.trainer.reports_success else None
            result = {**_final_result(nan, nan, self.ever_diverged, self.names, success), "round": r}
            if self.primary:
                write_json(self.run_dir / "final.json", result)
            last = self.ckpt.latest() if self.ckpt is not None else None
            kept = f"its checkpoints resume at round {last}" if last is not None else "no checkpoint"
            print(
                f"error: round {r}: {', '.join(result['diverged'])} diverged (NaN or inf in losses, "
                f"parameters or returns); the run stopped ({kept}). "
                "--on-divergence continue runs the other seeds on.",
                file=sys.stderr,
            )
            raise SystemExit(EXIT_DIVERGED)
        if which:
            print(f"warning: round {r}: {which} diverged; going on (--on-divergence continue)", file=sys.stderr)

    def finish(self) -> tuple[dict, list[pathlib.Path | None]]:
        """The final evaluation (the policy's and random actions' episodes on the same initial states) and what the
        run leaves: ``final.json`` (returned), the learning curve and the clip (their paths; None where one was
        not written). Sets :attr:`final` and :attr:`random`, the two returns per column, and :attr:`success`, the
        policy's success rate per column on a task that reports success (else None)."""
        args, run_dir = self.args, self.run_dir
        policy = self.trainer.policy_params(self.state)
        returns, success = self.real_columns(placement.to_host(self.final_evaluation()(policy)))
        self.final, self.random = np.asarray(returns).T
        self.success = None if success is None else np.asarray(success)[:, FINAL_FLAGS.index(False)]
        result = _final_result(self.final, self.random, self.ever_diverged, self.names, self.success)
        files = []
        if self.primary:
            own = method_metrics(run_dir, args.columns)
            if own:  # the method's own metrics, their last logged values
                result["method_metrics"] = own
            write_json(run_dir / "final.json", result)
            if self.host is not None:
                self.host.finish(result)  # The labelling page says the run has finished, and where its files are.
            files.append(_learning_curve(args, run_dir, self.random))
        if args.video_steps > 0 and video.drawable(self.trainer.env):
            policy = placement.to_host(policy)  # Every process: a collective with several.
            if self.primary:
                files.append(_eval_clip(args, self.trainer, policy, run_dir))
        return result, files
