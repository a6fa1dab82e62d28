"""The run's own options beside the config (``--seeds``, ``--run-dir``, ``--resume``, ...), the parsed command
line (:class:`Args`) and the command line's constants."""

from __future__ import annotations

import dataclasses
import sys
from typing import Annotated, Literal

import tyro

from rebel_jax.config import Config, method_sections
from rebel_jax.run import rundir
from rebel_jax.run.human import HumanOptions

PROG = "python -m rebel_jax.train"
EXIT_USAGE = rundir.EXIT_USAGE
MAX_STEPS = 2**31 - 1
"""The largest ``--total-steps`` and ``--buffer-capacity``: the rounds count steps and index the buffer in int32."""
OBS = ("state", "pixels")
"""``--obs``: what the agent observes; ``pixels`` runs the task's pixel version (``<task>_pixels``)."""
UNPREFIXED = ("env", "train")
"""Config sections whose flags carry no prefix (``--task``, ``--total-steps``): the run's task and schedule."""
HELP_ALL = "--help-all"
CORE_PARTS = tuple(f.name for f in dataclasses.fields(Config) if f.name not in ("algo", "method_settings"))
"""The config's own sections, each a group of flags."""


def parts() -> tuple[str, ...]:
    """Every section of the config, each a group of flags: its own, then each registered method's settings
    (``--NAME.*``, from the method's config dataclass)."""
    return (*CORE_PARTS, *method_sections())


@dataclasses.dataclass(frozen=True)
class RunOptions:
    """The run's own flags (beside its config's)."""

    seeds: int = 1
    """Seeds run together (vmapped; sharded over all devices when there are several)."""
    run_dir: str | None = None
    """The run's directory; default ``runs/<algo>_<task>_<time>``. It must not hold another run
    (see ``--resume`` and ``--overwrite``)."""
    resume: bool = False
    """Continue the run in ``run_dir`` from its latest readable checkpoint (from scratch, with a
    notice, if it has none). The configuration must equal the saved one, except a larger
    ``--total-steps``, which extends the run."""
    overwrite: bool = False
    """Replace the run in ``run_dir``: its config, logs, checkpoints and TensorBoard files are deleted first."""
    checkpoint_every: int = 1
    """Rounds between checkpoints; 0 disables them (``--resume`` still reads existing ones). A save's files are
    written during the next round (the last round's before the final evaluation); a save that still holds up the
    run longer than its round (a large pixel replay on a GPU) prints a note with an interval that keeps saving
    under a fifth of the time."""
    time_limit: float = 0.0
    """Seconds of wall time: stop after the last round that ends within it (checkpointing that
    round) and continue later with ``--resume``. For calls with a wall-clock limit; 0: none."""
    on_divergence: Literal["stop", "continue"] = "stop"
    """When a seed's losses, parameters or returns become NaN or infinite: ``stop`` the run after
    that round (exit status 3, the round is not checkpointed) or ``continue`` with the other seeds."""
    progress: bool = True
    """Show a progress bar."""
    tensorboard: bool = True
    """Write TensorBoard event files."""
    compile_cache: str | None = None
    """The persistent compilation cache's directory: a later run that compiles the same programs loads them from
    there. Default: ``JAX_COMPILATION_CACHE_DIR`` where set, else ``$REBEL_JAX_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/rebel_jax/jax``, else ``~/.cache/rebel_jax/jax`` (:mod:`rebel_jax.run.compile_cache`)."""
    no_compile_cache: Annotated[bool, tyro.conf.FlagCreatePairsOff] = False
    """No persistent compilation cache: compile every program in this process."""
    distributed: bool = False
    """Several processes (hosts, or one per GPU) run this same command: each calls
    ``jax.distributed.initialize`` first, with ``JAX_COORDINATOR_ADDRESS`` (host:port of process 0),
    ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID`` from the environment, or what JAX detects (SLURM).
    The seeds are sharded over every process's devices; process 0 writes the logs, all write the
    checkpoints (orbax), so ``--run-dir`` must be given and be on a file system they share."""
    lam_grid: tuple[float, ...] = ()
    """``rebel`` only: run every seed with each of these lambdas in one vmapped program
    (columns are lambda-major: lambda 0 seed 0, lambda 0 seed 1, ...; seed i uses the same key
    for every lambda). Empty: ``rebel.lam`` only."""

    video_steps: int = 250
    """Agent steps of the evaluation clip written at the end of the run (``eval.gif``: the first
    column's deterministic policy, 120x120, camera 0; the quadruped's by MuJoCo's renderer, skipped without OpenGL);
    0: none. Only for MuJoCo tasks (state or pixel), and not
    under ``--time-limit`` (``python -m rebel_jax.run.video RUN_DIR`` renders one later)."""

    teacher_grid: tuple[str, ...] = ()
    """Preference methods only: run every seed (and lambda) with each of these B-Pref teachers
    in one vmapped program (columns: lambda, then teacher, then seed). Empty: ``--teacher``."""
    human: HumanOptions = HumanOptions()
    """``--teacher human`` (the labelling page) and ``--teacher replay`` (its saved answers)."""


@dataclasses.dataclass(frozen=True)
class Args(RunOptions):
    """Train one configuration on several seeds."""

    config: Config = Config()
    """The run's configuration (every section's flags)."""
    host_teacher: str = ""
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

    def column_names(self) -> list[str]:
        """``seed i`` for each column, with its lambda (of a grid) and teacher (of a grid)."""
        names = []
        for i, (lam, teacher) in enumerate(self.grid()):
            which = ([f"lambda {lam:g}"] if self.lam_grid else []) + ([f"teacher {teacher}"] if teacher else [])
            names.append(f"seed {i % self.seeds}" + (f" ({', '.join(which)})" if which else ""))
        return names


def swept_knob(cfg) -> bool:
    """Whether the run's method has a traced knob (REBEL's lambda), which ``--lam-grid`` sweeps as columns."""
    return cfg.method is not None and cfg.method.knob(cfg) is not None


def usage_error(err: Exception) -> SystemExit:
    print(f"error: {err}", file=sys.stderr)
    return SystemExit(EXIT_USAGE)
