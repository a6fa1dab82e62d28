"""Frozen configuration dataclasses, named presets and validation.

Every field is documented; ``python -m rebel_jax.train --help`` shows these docstrings.
Static sizes (network widths, batch sizes, counts) are Python ints baked into the
compiled program; float hyperparameters are plain data.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
import pathlib
import typing
from typing import Annotated

import tyro

from rebel_jax import methods
from rebel_jax.agents.drqv2 import DrQV2Config, task_config
from rebel_jax.agents.sac import MAX_UTD, Precision, SACConfig  # noqa: F401 - re-exported
from rebel_jax.core.errors import ConfigError  # noqa: F401 - re-exported: callers catch config.ConfigError
from rebel_jax.core.errors import check as _check
from rebel_jax.core.ranges import ANY_INTEGER, check_ranges
from rebel_jax.methods.qpa import QPAConfig
from rebel_jax.methods.rebel import AgentPreferenceConfig
from rebel_jax.methods.surf import SURFConfig
from rebel_jax.preference.budget import FeedbackConfig  # noqa: F401 - re-exported
from rebel_jax.preference.pixel_reward import PixelRewardConfig
from rebel_jax.preference.pretrain import PretrainConfig
from rebel_jax.preference.queries import QueryConfig
from rebel_jax.preference.reward_model import RewardConfig
from rebel_jax.preference.teachers import TeacherConfig

AGENTS = ("sac", "drqv2")
"""The agents alone, on the task's true reward: SAC on state tasks, DrQ-v2 on pixel tasks."""


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """The task and how many copies of it each seed runs."""

    task: str = "walker_walk"
    """Task name: walker_stand, walker_walk, walker_run, cheetah_run, quadruped_walk or quadruped_run (or
    ``probe_point``, a pure-JAX point mass that compiles in seconds, for tests of the training loop);
    ``<task>_pixels`` (and ``probe_point_pixels``; not the quadruped's) observe frame stacks, for ``--algo drqv2``,
    ``pebble``, ``surf`` and ``rebel``; ``metaworld_<name>`` for Meta-World's button-press, sweep-into, hammer,
    drawer-open, door-open, door-unlock and window-open (states only; ``--impl warp`` on a GPU)."""
    solver: str = "default"
    """MJX solver preset: ``default`` (fast, see BENCHMARKS.md) or ``dm_control`` (100/50 iterations)."""
    num_envs: int = 10
    """Environments stepped together per seed; each vector step collects ``num_envs`` transitions.

    B-Pref steps one environment; MJX's per-step latency (BENCHMARKS.md) makes several per seed
    necessary. 10 is the most with which B-Pref's first feedback session (at 10k steps) finds
    complete episodes to draw queries from (``query.pool='episodes'``), as B-Pref's 10."""
    episode_length: int = 1000
    """Control steps per episode (dm_control: 1000)."""
    all_contacts: bool = False
    """Check every pair of geoms for contact at every physics step. Off: leave out the pairs that never came near
    each other in dm_control (the quadruped's lower legs against its torso and eyes; docs/tasks.md), as MuJoCo's own
    bounding-box test leaves them out; no effect on walker and cheetah."""
    impl: str = "jax"
    """The physics step's implementation: ``jax`` (MJX in JAX operations) or ``warp`` (MuJoCo Warp's kernels through
    MJX, needs ``pip install -e '.[warp]'``). Observations and rewards are computed in JAX either way; the two agree
    to float rounding (tests/test_warp.py), which chaos then amplifies over an episode."""
    unroll_substeps: bool = False
    """A control step's physics substeps compiled one after another, not as a loop. With ``impl='warp'`` the loop
    carries all of Warp's data, and unrolled rounds were about 2% shorter on a GPU (BENCHMARKS.md section
    3); with the JAX step the physics alone was not faster, so it is off by default."""

    def validate(self) -> None:
        from rebel_jax.envs import (
            IMPLS,
            METAWORLD_TASKS,
            PIXEL_TASKS,
            PROBES,
            SOLVERS,
            TASKS,
            no_pixel_version,
            not_runnable,
        )
        from rebel_jax.envs.dmc import check_impl
        from rebel_jax.envs.metaworld import EPISODE_LENGTH

        if no_pixel_version(self.task):
            raise ConfigError(f"env.task={self.task!r} is invalid: {no_pixel_version(self.task)}")
        if not_runnable(self.task, self.impl):
            raise ConfigError(f"env.task={self.task!r} is invalid: {not_runnable(self.task, self.impl)}")
        names = [*sorted(TASKS), *PIXEL_TASKS, *METAWORLD_TASKS, *PROBES]
        if self.task not in names:
            close = difflib.get_close_matches(self.task, names, n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise ConfigError(f"env.task={self.task!r} is invalid{hint}: allowed one of {names}")
        if self.task in METAWORLD_TASKS and self.episode_length > EPISODE_LENGTH:
            raise ConfigError(
                f"env.episode_length={self.episode_length} is invalid for {self.task}: Meta-World ends its episodes "
                f"at {EPISODE_LENGTH} steps (--preset paper_metaworld or qpa_metaworld sets it)"
            )
        _check(self.solver in SOLVERS, "env.solver", self.solver, f"one of {sorted(SOLVERS)}")
        _check(self.impl in IMPLS, "env.impl", self.impl, f"one of {list(IMPLS)}")
        if self.impl == "warp":
            try:
                check_impl(self.impl)
            except ValueError as err:
                raise ConfigError(str(err)) from None
        _check(self.num_envs >= 1, "env.num_envs", self.num_envs, ">= 1")
        _check(self.episode_length >= 1, "env.episode_length", self.episode_length, ">= 1")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """The schedule of one run."""

    total_steps: int = 500_000
    """Environment steps per seed (all ``num_envs`` environments together)."""
    seed_steps: int = 1_000
    """Initial environment steps with uniformly random actions."""
    steps_per_round: int = 10_000
    """Environment steps per jitted round (the unit of progress, logging and checkpoints)."""
    eval_every: int = 10_000
    """Environment steps between evaluations; a multiple of ``steps_per_round``."""
    eval_episodes: int = 10
    """Deterministic evaluation episodes on the true reward."""
    buffer_capacity: int = 0
    """Replay capacity in transitions; 0 means ``total_steps`` (nothing evicted, as B-Pref), on pixel tasks
    ``pixel_feedback.DEFAULT_CAPACITY`` (100k, at most ``total_steps``)."""
    seed: Annotated[int, ANY_INTEGER] = 0
    """Base PRNG seed; seed i of a sweep uses ``fold_in(seed, i)``."""
    overlap: bool = False
    """The agent's updates at a vector step sample the replay as it was before that step's transitions (one vector
    step behind), so that they do not wait for its physics: on a GPU the env step then runs on a second stream,
    beside the updates. A protocol change (B-Pref's updates see the newest transitions), off in every preset; its
    speed and its learning curves are not measured. Refused on GPUs with JAX >= 0.11, where XLA aborted the
    second-stream program (JAX 0.11.2); ``benchmarks/overlap.py`` times the two side by side."""

    unroll_updates: bool = True
    """A vector step's agent updates compiled as straight-line code rather than a loop: the same updates (equal to
    float32 rounding), 5-7% shorter rounds on a GPU (BENCHMARKS.md), a longer compile (the ``paper`` round's CPU
    compile 41 s against 29); off in ``demo``, which compiles on a CPU."""

    def validate(self, num_envs: int) -> None:
        for name in ("total_steps", "steps_per_round", "eval_every", "eval_episodes"):
            _check(getattr(self, name) >= 1, f"train.{name}", getattr(self, name), ">= 1")
        _check(self.seed_steps >= 0, "train.seed_steps", self.seed_steps, ">= 0")
        if self.overlap:  # The first updates must find transitions in the replay of the step before.
            _check(
                self.seed_steps > num_envs,
                "train.seed_steps",
                self.seed_steps,
                f"> env.num_envs={num_envs} with train.overlap",
            )
        _check(
            self.steps_per_round % num_envs == 0,
            "train.steps_per_round",
            self.steps_per_round,
            f"a multiple of env.num_envs={num_envs}",
        )
        _check(
            self.total_steps % self.steps_per_round == 0,
            "train.total_steps",
            self.total_steps,
            f"a multiple of train.steps_per_round={self.steps_per_round} (whole rounds)",
        )
        _check(
            self.eval_every % self.steps_per_round == 0,
            "train.eval_every",
            self.eval_every,
            f"a multiple of train.steps_per_round={self.steps_per_round}",
        )
        _check(self.buffer_capacity >= 0, "train.buffer_capacity", self.buffer_capacity, ">= 0")

    @property
    def capacity(self) -> int:
        return self.buffer_capacity or self.total_steps

    @property
    def num_rounds(self) -> int:
        return math.ceil(self.total_steps / self.steps_per_round)


def _check_round_multiple(value: int, field: str, steps_per_round: int) -> None:
    _check(value % steps_per_round == 0, field, value, f"a multiple of train.steps_per_round={steps_per_round}")


@dataclasses.dataclass(frozen=True)
class Config:
    """A whole run.

    The preference methods' own settings are not fields: each method declares its config dataclass next to its code
    (``Method.config``), and the run's config holds one instance per method under the method's name
    (:attr:`method_settings`). ``cfg.section("rebel")``, or ``cfg.rebel``, reads one (the method's defaults where
    none was given); ``Config(rebel=...)``, ``dataclasses.replace(cfg, rebel=...)`` and :func:`replace` set them.
    """

    algo: str = "sac"
    """sac (true reward), drqv2 (DrQ-v2 on a pixel task, true reward), or a preference method of the registry:
    pebble, surf (PEBBLE+SURF), rebel, qpa, rune, rime, mrn (docs/methods.md) or one of a package's own; on a pixel
    task the preference methods train DrQ-v2 on the learned reward."""
    env: Annotated[EnvConfig, tyro.conf.OmitArgPrefixes] = EnvConfig()
    sac: Annotated[SACConfig, tyro.conf.OmitArgPrefixes] = SACConfig()
    train: Annotated[TrainConfig, tyro.conf.OmitArgPrefixes] = TrainConfig()
    feedback: Annotated[FeedbackConfig, tyro.conf.OmitArgPrefixes] = FeedbackConfig()
    reward: RewardConfig = RewardConfig()
    teacher: TeacherConfig = TeacherConfig()
    query: QueryConfig = QueryConfig()
    pretrain: PretrainConfig = PretrainConfig()
    """Unsupervised pre-training; used by the preference methods only (``--algo sac`` skips it)."""
    drqv2: DrQV2Config = DrQV2Config()
    """DrQ-v2's settings; used on pixel tasks (``--algo drqv2``, and the agent of ``--algo pebble`` there). The
    defaults are DrQ-v2's cheetah_run ones; walker's are ``--drqv2.nstep 1 --drqv2.batch-size 512
    --drqv2.std-steps 100000`` (``drqv2.task_config``)."""
    pixel_reward: PixelRewardConfig = PixelRewardConfig()
    """SURF's pixel reward ensemble; used by ``--algo pebble`` on a pixel task (``reward`` is for state tasks)."""
    method_settings: tuple = ()
    """``((name, settings), ...)``, sorted by name: the methods' settings that differ from their defaults."""

    def section(self, name: str):
        """The settings of the method ``name`` (its ``Method.config``; the defaults unless this config sets them).

        Raises:
          KeyError: if no registered method of that name has settings.
        """
        for given, value in self.method_settings:
            if given == name:
                return value
        method = methods.REGISTRY.get(name)
        if method is None or method.config is None:
            raise KeyError(f"no method {name!r} with settings; methods with settings: {', '.join(method_sections())}")
        return method.config()

    def __getattr__(self, name: str):
        """``cfg.rebel``: :meth:`section` for a registered method's name."""
        method = methods.REGISTRY.get(name) if not name.startswith("_") else None
        if method is None or method.config is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return self.section(name)

    @property
    def preference(self) -> bool:
        """Whether the agent learns from preferences (a method of :data:`rebel_jax.methods.REGISTRY`)."""
        return self.algo in methods.REGISTRY

    @property
    def method(self) -> methods.Method | None:
        """The preference method ``algo`` names (None for the agents alone, sac and drqv2)."""
        return methods.REGISTRY.get(self.algo)

    @property
    def pixels(self) -> bool:
        """Whether the task observes frame stacks (``<task>_pixels``)."""
        return self.env.task.endswith("_pixels")

    def unused_parts(self) -> dict[str, str]:
        """The parts of this config that the run never reads, each with where it is read instead: ``sac`` on
        state tasks, ``drqv2`` on pixel tasks; ``feedback``, ``query``, ``teacher``, ``pretrain`` and ``reward``
        (``pixel_reward`` on pixels) by the preference methods; ``surf`` and ``rebel`` by their own algo."""
        where = {
            "sac": "a state task",
            "drqv2": "a pixel task",
            **dict.fromkeys(
                ("feedback", "query", "teacher", "pretrain"), f"a preference algo ({', '.join(methods.REGISTRY)})"
            ),
            "reward": "a preference algo on a state task",
            "pixel_reward": "a preference algo on a pixel task",
        }
        readers: dict[str, list[str]] = {}  # a method's own parts (surf, rebel, qpa, rune) and who reads each
        for m in methods.REGISTRY.values():
            for part in m.sections():
                readers.setdefault(part, []).append(m.name)
        where |= {part: "--algo " + " or --algo ".join(names) for part, names in readers.items()}
        used = {"drqv2" if self.pixels else "sac"}
        if self.method is not None:
            used.update(self.method.sections())
        if self.preference:
            used |= {"feedback", "query", "teacher", "pretrain", "pixel_reward" if self.pixels else "reward"}
        return {part: text for part, text in where.items() if part not in used}

    @property
    def feedback_start(self) -> int:
        """Env step of the first feedback session (= end of pre-training).

        Pixel tasks have no unsupervised phase: SURF's pixel runs set ``num_unsup_frames=0`` (alinlab/SURF
        branch ``pixel``, README.md:22, :32), so their first feedback session comes after the seed steps."""
        return self.train.seed_steps + (0 if self.pixels else self.pretrain.steps)

    def check_complete_episode(self, setting: str, what: str, alternative: str) -> None:
        """``setting`` draws ``what`` from complete episodes: the first feedback session must find one."""
        most = self.feedback_start // self.env.episode_length
        _check(
            self.env.num_envs <= most,
            "env.num_envs",
            self.env.num_envs,
            f"<= {most} with {setting}: {what} come from complete episodes, and the first feedback session "
            f"(env step {self.feedback_start}) must find one (or use {alternative})",
        )

    def validate(self) -> Config:
        names = [*AGENTS, *methods.REGISTRY]
        _check(self.algo in names, "algo", self.algo, ", ".join(names))
        # Every numeric field in its declared range, before the checks that relate fields; the methods' sections too.
        check_ranges(self, skip=("method_settings",))
        for name in method_sections():
            check_ranges(self.section(name), name + ".")
        self.env.validate()
        self.sac.validate()
        self.train.validate(self.env.num_envs)
        pixels = self.pixels
        if self.algo == "drqv2" or pixels:
            allowed = (
                f"drqv2 or a preference method ({', '.join(methods.REGISTRY)}) with the pixel task {self.env.task!r}"
            )
            _check(self.algo != "sac", "algo", self.algo, allowed)
            _check(pixels, "env.task", self.env.task, "a pixel task (<task>_pixels) with --algo drqv2")
            self.drqv2.validate()
            if self.preference:
                self.pixel_reward.validate()
            every, envs = self.drqv2.update_every, self.env.num_envs
            _check(
                envs % every == 0 or every % envs == 0,
                "env.num_envs",
                envs,
                f"a multiple or a divisor of drqv2.update_every={every} (whole updates per vector step)",
            )
        if self.preference:
            for part in (self.feedback, self.reward, self.teacher, self.pretrain):
                part.validate()
            self.query.validate(self.env.episode_length)
            self.method.validate(self)
            if self.query.pool == "episodes" and not pixels:  # pixel_feedback.check_config checks in agent steps
                self.check_complete_episode("query.pool='episodes'", "queries", "--query.pool rows")
            steps = self.train.steps_per_round
            _check_round_multiple(self.feedback_start, "train.seed_steps + pretrain.steps", steps)
            _check_round_multiple(self.feedback.interval, "feedback.interval", steps)
            # State tasks' labels are replay places; pixel tasks' label store keeps copies (pixel_reward).
            _check(
                pixels or self.train.capacity >= self.train.total_steps,
                "train.buffer_capacity",
                self.train.buffer_capacity,
                f"0 or >= train.total_steps={self.train.total_steps} (relabelling and queries assume no eviction)",
            )
        return self


FIELDS = tuple(f.name for f in dataclasses.fields(Config))
_generated_init = Config.__init__


def method_sections() -> tuple[str, ...]:
    """The registered methods with settings of their own: the config's sections beside its fields."""
    return tuple(name for name, m in methods.REGISTRY.items() if m.config is not None)


def _with_sections(settings: tuple, sections: dict) -> tuple:
    """``settings`` with ``sections`` (name -> the method's config) set, sorted by name (raises TypeError for a name
    that is no registered method with settings, or a value of another type than the method's config)."""
    merged = dict(settings)
    for name, value in sections.items():
        method = methods.REGISTRY.get(name)
        if method is None or method.config is None:
            raise TypeError(f"Config got an unexpected keyword argument {name!r} (no registered method with settings)")
        if not isinstance(value, method.config):
            raise TypeError(f"Config's {name} must be a {method.config.__name__}, not {type(value).__name__}")
        merged[name] = value
    # A method's defaults are not kept: two configs of the same settings compare equal however they were made.
    return tuple(sorted((k, v) for k, v in merged.items() if v != methods.REGISTRY[k].config()))


def _init(self, *args, **kwargs):
    """``Config``'s dataclass ``__init__``, also taking each method's settings by its name (``rebel=...``)."""
    sections = {k: kwargs.pop(k) for k in list(kwargs) if k not in FIELDS}
    _generated_init(self, *args, **kwargs)
    if sections or self.method_settings:
        object.__setattr__(self, "method_settings", _with_sections(tuple(self.method_settings), sections))


Config.__init__ = _init


def replace(cfg: Config, **changes) -> Config:
    """``cfg`` with ``changes``: its fields, or methods' settings by the methods' names (``rebel=...``)."""
    return dataclasses.replace(cfg, **changes)


def to_dict(cfg: Config) -> dict:
    """``cfg`` as ``config.json`` holds it: its fields, then every registered method's settings under the method's
    name (the defaults where not set), as ``dataclasses.asdict`` makes them (the file's format before methods
    declared their settings)."""
    data = dataclasses.asdict(cfg)
    del data["method_settings"]
    return data | {name: dataclasses.asdict(cfg.section(name)) for name in method_sections()}


def from_dict(cls, data: dict):
    """A (nested, frozen) config dataclass from ``dataclasses.asdict`` output read back from JSON (fields
    missing from ``data`` keep their defaults)."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for field in dataclasses.fields(cls):
        if field.name not in data or field.name == "method_settings":
            continue
        value, hint = data[field.name], hints[field.name]
        if dataclasses.is_dataclass(hint):
            value = from_dict(hint, value)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[field.name] = value
    if cls is Config:  # the registered methods' settings, under their names; a section no method reads is left
        for name in method_sections():
            if isinstance(data.get(name), dict):
                kwargs[name] = from_dict(methods.REGISTRY[name].config, data[name])
    return cls(**kwargs)


def read_config(path: str | os.PathLike) -> Config:
    """The :class:`Config` a run wrote to its ``config.json`` (the installed packages' methods registered first, so
    that their settings are read too)."""
    methods.load_entry_points()
    return from_dict(Config, json.loads(pathlib.Path(path).read_text()))


def _tiny() -> Config:
    return Config(
        env=EnvConfig(num_envs=4, episode_length=100),
        sac=SACConfig(hidden=64, batch_size=128, utd=0.25),
        train=TrainConfig(total_steps=8_000, seed_steps=400, steps_per_round=2_000, eval_every=2_000, eval_episodes=2),
        feedback=FeedbackConfig(labels=60, per_session=20, interval=2_000),
        reward=RewardConfig(hidden=64),
        query=QueryConfig(segment_length=25),
        pretrain=PretrainConfig(steps=1_600),
        surf=SURFConfig(pool_size=512),
        rebel=AgentPreferenceConfig(segment_length=25),
    )


def _demo() -> Config:
    """``make train``: PEBBLE learning cheetah_run from 400 oracle labels in about 3 minutes on 2 CPU cores.

    Chosen by measuring (README.md, "make train"): cheetah_run's random policy scores about 1 in
    250 steps, and the cheetah's reward (its forward speed, an observed velocity) is learnt from
    few labels. Episodes are 250 steps (dm_control's are 1000), so a run of 32k steps per seed
    has 16 evaluations. Small networks, half an update per transition and larger learning rates
    than B-Pref's make the most of the CPU; 40 labels per session every 2k steps from 2k on.
    """
    return Config(
        algo="pebble",
        env=EnvConfig(task="cheetah_run", num_envs=8, episode_length=250),
        sac=SACConfig(hidden=64, batch_size=128, utd=0.5, actor_lr=1e-3, critic_lr=1e-3),
        train=TrainConfig(
            total_steps=32_000,
            seed_steps=1_000,
            steps_per_round=2_000,
            eval_every=2_000,
            eval_episodes=8,
            unroll_updates=False,
        ),
        feedback=FeedbackConfig(labels=400, per_session=40, interval=2_000),
        reward=RewardConfig(hidden=64),
        query=QueryConfig(segment_length=25),
        pretrain=PretrainConfig(steps=1_000),
        surf=SURFConfig(pool_size=512),
        rebel=AgentPreferenceConfig(segment_length=25),
    )


_PAPER = Config(
    query=QueryConfig(sampling="disagreement"),
    pretrain=PretrainConfig(running_std="bpref"),
    feedback=FeedbackConfig(budget="asked"),
)


def _paper_quadruped() -> Config:
    """B-Pref's quadruped_walk protocol (rll-research/BPref@f3ece2e, ``scripts/quadruped_walk/run_sac.sh`` and
    ``scripts/quadruped_walk/1000/oracle/run_PEBBLE.sh``): ``paper``'s settings except the actor and critic learning
    rates (1e-4), 1M steps, and 1,000 labels, 100 per session, every 30k steps. QPA's quadruped runs use the
    same budget."""
    return dataclasses.replace(
        _PAPER,
        env=EnvConfig(task="quadruped_walk"),
        sac=SACConfig(actor_lr=1e-4, critic_lr=1e-4),
        train=TrainConfig(total_steps=1_000_000),
        feedback=dataclasses.replace(_PAPER.feedback, labels=1_000, per_session=100, interval=30_000),
    )


def _surf_pixels(task: str) -> Config:
    """SURF's pixel protocol on ``task`` (alinlab/SURF, branch ``pixel``; notes/surf_pixel_audit.md), for
    ``--algo pebble`` (the default), ``surf``, ``rebel`` and ``drqv2``: the ``paper`` preset's accounting with
    DrQ-v2's agent for the task (``drqv2.task_config``), 500k agent steps (1M frames; the issue's walker runs stop
    at 250k, ``--total-steps``), DrQ-v2's 4,000 seed frames, 10 evaluation episodes every 10k steps.

    - Queries: uniform only (pixel_train_PEBBLE_semi.py:250-257; feed_type 0, cfgs/config_pebble.yaml:44) from the
      last 20 episodes (reward_max_episodes, config_pebble.yaml:56).
    - Labels (README.md:22 walker, :32 cheetah; num_interact in frames, so agent steps are half): walker 200, 10
      per session, every 30k frames; cheetah 1,000, 25 per session, every 20k frames.
    - SURF (same commands): threshold_u 0.99, mu 1, reward_update 20, pool 5 x the session's queries
      (inv_label_ratio 5); walker time crop 2 and lambda_u 0.1, cheetah crop 5 and lambda_u left at 1
      (cfgs/config_pebble_semi.yaml:66-67).
    - 4 envs and rounds of 1,000 agent steps: the first feedback session (after the 2,000 seed steps) needs a complete
      500-step episode in each env, and 1,000 divides the seed steps and both session intervals. DrQ-v2 alone
      needs no such episode; its runs so far used 10 envs (``--num-envs 10``).
    """
    walker = task.startswith("walker")
    queries, interval, labels = (10, 15_000, 200) if walker else (25, 10_000, 1_000)
    crop, weight = (2, 0.1) if walker else (5, 1.0)
    return dataclasses.replace(
        _PAPER,
        algo="pebble",
        env=EnvConfig(task=f"{task}_pixels", num_envs=4),
        train=TrainConfig(total_steps=500_000, seed_steps=2_000, steps_per_round=1_000, eval_every=10_000),
        feedback=FeedbackConfig(labels=labels, per_session=queries, interval=interval, budget="asked"),
        query=dataclasses.replace(_PAPER.query, sampling="uniform", recent_episodes=20),
        surf=SURFConfig(threshold=0.99, ratio=1, reward_update=20, crop=crop, weight=weight, pool_size=5 * queries),
        drqv2=task_config(task),
    )


def _paper_metaworld() -> Config:
    """B-Pref's Meta-World protocol (rll-research/BPref@f3ece2e, ``scripts/button_press/run_sac.sh:2`` and
    ``scripts/button_press/10000/oracle/run_PEBBLE.sh:2``; sweep_into's scripts are the same): ``paper``'s settings
    except Meta-World's 500-step episodes, SAC's 3 hidden layers of 256, batch 512 and learning rates 3e-4, 1M steps,
    and 10,000 labels, 50 per session every 5,000 steps (``num_interact``) with 10 reward epochs (``reward_update``).
    Rounds of 5,000 steps so that a session falls on each. The task: drawer-open (sweep-into, B-Pref's second, also
    runs here; docs/tasks.md); ``--task metaworld_<name>`` picks another."""
    return dataclasses.replace(
        _PAPER,
        env=EnvConfig(task="metaworld_drawer-open", episode_length=500),  # Meta-World's max_path_length
        sac=SACConfig(hidden=256, depth=3, batch_size=512, actor_lr=3e-4, critic_lr=3e-4),
        train=TrainConfig(total_steps=1_000_000, steps_per_round=5_000),
        feedback=dataclasses.replace(_PAPER.feedback, labels=10_000, per_session=50, interval=5_000),
        reward=RewardConfig(max_epochs=10),
    )


_QPA = dataclasses.replace(
    _PAPER,
    algo="qpa",
    reward=RewardConfig(ensemble_size=1),
    query=dataclasses.replace(_PAPER.query, sampling="uniform"),
)
"""QPA's walker_walk protocol (huxiao09/QPA@7e9e49e:run_QPA.sh:5): the ``paper`` preset with one reward member
(``ensemble_size=1``) and uniform queries (``explore=false``; ``--algo qpa`` draws them uniformly anyway); its
other settings are the ``qpa`` section's defaults. cheetah_run: ``--task cheetah_run --total-steps 1000000``."""


def _qpa_metaworld() -> Config:
    """QPA's Meta-World protocol (huxiao09/QPA@7e9e49e:run_QPA.sh:35, drawer-open): the ``qpa`` preset with
    Meta-World's 500-step episodes, SAC's learning rates 1e-4, 1M steps, 3,000 labels, 30 per session every 5,000
    steps (``num_interact``), queries from the last 30 episodes (``max_reward_buffer_size``), 100 evaluation episodes
    (``num_eval_episodes``), and QPA's Meta-World reward sessions (``qpa.reward_session='epochs'``: up to 200 epochs,
    ``reward_update``, stopped above 0.97 accuracy; train_QPA.py:136-141).

    - door-open (run_QPA.sh:40): ``--task metaworld_door-open --qpa.recent-episodes 60``.
    - door-unlock (run_QPA.sh:45): ``--task metaworld_door-unlock --feedback.labels 2000 --feedback.per-session 100
      --feedback.interval 20000``.
    - The networks: the scripts set none, so QPA's SAC defaults ran, 2 layers of 1024 and batch 1024
      (config/agent/sac.yaml:22,31-32,39-40), which this preset keeps; that file's comment "512 for Meta-world" is
      ``--sac.batch-size 512``.
    """
    return dataclasses.replace(
        _QPA,
        env=EnvConfig(task="metaworld_drawer-open", episode_length=500),
        sac=SACConfig(actor_lr=1e-4, critic_lr=1e-4),
        train=TrainConfig(total_steps=1_000_000, steps_per_round=5_000, eval_episodes=100),
        feedback=dataclasses.replace(_QPA.feedback, labels=3_000, per_session=30, interval=5_000),
        reward=dataclasses.replace(_QPA.reward, max_epochs=200),
        qpa=QPAConfig(recent_episodes=30, reward_session="epochs"),
    )


_RIME = dataclasses.replace(
    _PAPER,
    algo="rime",
    train=TrainConfig(total_steps=1_000_000),
    feedback=dataclasses.replace(_PAPER.feedback, labels=1_000, per_session=100, interval=20_000),
    teacher=TeacherConfig(eps_mistake=0.3),
)
"""RIME's walker_walk protocol (CJReinforce/RIME_ICML2024@4ad03f4:run_parallel.sh:5,25-27,103): the ``paper`` preset
(disagreement queries, B-Pref's running std, the ``asked`` budget) with 1M steps, 1,000 labels, 100 per session
every 20k steps, and the ``mistake`` teacher at eps 0.3 (the preset's teacher unless ``--teacher`` names another);
SAC at 5e-4 and 50 reward epochs are ``paper``'s. cheetah_run: ``--task cheetah_run --pretrain.steps 2000``
(run_parallel.sh:15)."""

PRESETS: dict[str, Config] = {
    "paper": _PAPER,
    "paper_quadruped": _paper_quadruped(),
    "paper_metaworld": _paper_metaworld(),
    "qpa": _QPA,
    "qpa_metaworld": _qpa_metaworld(),
    "rime": _RIME,
    "tiny": _tiny(),
    "demo": _demo(),
    "surf_pixels_walker": _surf_pixels("walker_walk"),
    "surf_pixels_cheetah": _surf_pixels("cheetah_run"),
}
"""``paper``: B-Pref's walker_walk settings (rll-research/BPref@f3ece2e), with its disagreement query
sampling (``feed_type=1`` in B-Pref's and SURF's walker commands) and its running std of the kNN
reward (``pretrain.running_std='bpref'``, BPref ``utils.py:211-247``; notes/bpref_audit.md).
``paper_quadruped``: B-Pref's quadruped_walk settings (``_paper_quadruped``), the default on a quadruped task.
``paper_metaworld``: B-Pref's Meta-World settings (``_paper_metaworld``), the default on a Meta-World task.
``qpa``: QPA's protocol (``_QPA``); ``qpa_metaworld``: its Meta-World protocol (``_qpa_metaworld``). ``rime``:
RIME's walker_walk protocol (``_RIME``). ``tiny``: CPU tests of the CLI. ``demo``: ``make train``, a small
preference-learning run that learns on a CPU (``_demo``).
``surf_pixels_walker`` and ``surf_pixels_cheetah``: SURF's pixel runs (``_surf_pixels``)."""
