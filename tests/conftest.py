"""Shared test setup: JAX's persistent compilation cache, compiled env functions, xdist groups.

MJX compiles slowly on CPU, so every compiled environment function is built once per
session here and shared by the tests. ``make test`` runs two pytest-xdist workers with
``--dist loadgroup``: each test file is one group (so its module fixtures compile once), and
the env files share a group (so they share the compiled environments); the grouping is done
by :func:`pytest_xdist_make_scheduler` below.
"""

from __future__ import annotations

import functools
import importlib
import os
import pathlib
import warnings

import jax
import pytest

_CACHE = pathlib.Path(os.environ.get("REBEL_JAX_TEST_CACHE", pathlib.Path(__file__).parents[1] / ".jax_cache"))
jax.config.update("jax_compilation_cache_dir", str(_CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
# The command lines' own cache (rebel_jax.run.compile_cache): in subprocesses that are not given the one above, the
# same directory rather than the user's ~/.cache.
os.environ.setdefault("REBEL_JAX_CACHE_DIR", str(_CACHE))


def _add_xla_flag(flag: str) -> None:
    """Appends ``flag`` to ``XLA_FLAGS`` unless that option is set already (read when the backend starts)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if flag.split("=")[0] not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {flag}".strip()


# jaxlib 0.10.2's CPU runtime at times deadlocks running these programs (every thread idle in
# block_until_ready; e.g. 7 of 12 runs of one train init) unless this scheduler is off (0 of 24).
# Set before the first computation creates the backend; subprocesses inherit it.
_NO_DEADLOCK = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
_add_xla_flag(_NO_DEADLOCK)
warnings.filterwarnings("ignore", message=".*settotalmass.*")

# The suite is bound by XLA's compiles. Runs that leave out the heavy tests (``make test``) compile with JAX's
# ``jax_disable_most_optimizations``: XLA's backend optimisation level 0 and LLVM's expensive passes off
# (``jax/_src/compiler.py``). The tests' programs run slower, but their runs are short. On a fresh clone the
# ``make test`` suite took 528 s instead of 643 s at level 1, the setting before (jaxlib 0.10.2, 2 cores,
# 2026-11-25). It is set through the environment, so the CLI tests' subprocesses compile alike (the same
# compilation cache keys, the same numbers). An explicit ``JAX_DISABLE_MOST_OPTIMIZATIONS`` is kept:
# ``JAX_DISABLE_MOST_OPTIMIZATIONS=0 make test`` tests XLA's default optimisation. The heavy runs use XLA's
# default, at which their learning thresholds were measured.
FAST_COMPILE = "JAX_DISABLE_MOST_OPTIMIZATIONS"
# With it, XLA's CPU backend also emits its fusions the older way (LLVM IR directly, not through the MLIR fusion
# emitters): a compile of the human-session test's REBEL round took 7.8 s instead of 12.4 s, and cheetah's batched
# MJX step 7.7 s instead of 12.6 s, with no slower runs; the fresh-clone suite's tests took 349 s instead of 534 s
# (jaxlib 0.10.2, this 2-core machine, 2026-11-25). At XLA's default optimisation it did not help. With the legacy
# emitters alone, two programs that compute the same thing (PEBBLE, and REBEL at lambda 0) differed by an ulp, most
# likely because LLVM contracts a multiply and an add into one FMA wherever a fusion holds both, and the programs
# fuse differently: capping the instruction set at AVX (``--xla_cpu_max_isa=AVX``; FMA comes with AVX2) made them
# equal bit for bit again, as under the new emitters. The flags are jaxlib's (pinned in pyproject.toml); a jaxlib
# that no longer knows one would stop at start-up, naming it.
LEGACY_FUSION_EMITTERS = ("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_max_isa=AVX")


def pytest_configure(config):
    if "not heavy" in (config.option.markexpr or "") and FAST_COMPILE not in os.environ:
        os.environ[FAST_COMPILE] = "1"
    fast = os.environ.get(FAST_COMPILE, "0") not in ("", "0")
    jax.config.update("jax_disable_most_optimizations", fast)
    if fast:
        for flag in LEGACY_FUSION_EMITTERS:
            _add_xla_flag(flag)


class CompiledEnv:
    """An environment with its jitted reset/step (single and batched), built lazily."""

    def __init__(self, task: str, solver: str):
        from rebel_jax.envs import make_env

        self.env = make_env(task, solver=solver)

    @functools.cached_property
    def reset(self):
        return jax.jit(self.env.reset)

    @functools.cached_property
    def step(self):
        return jax.jit(self.env.step)

    @functools.cached_property
    def batch_reset(self):
        return jax.jit(jax.vmap(self.env.reset))

    @functools.cached_property
    def batch_step(self):
        return jax.jit(jax.vmap(self.env.step))

    @functools.cached_property
    def observe(self):
        return jax.jit(jax.vmap(self.env.observe))


@pytest.fixture
def benchmark_script(monkeypatch):
    """``benchmark_script(name)``: the script ``benchmarks/<name>.py`` as a module, with ``benchmarks/`` on
    ``sys.path`` for this test (the scripts import each other: ``timing``, ``kernel_profile``, ...)."""
    monkeypatch.syspath_prepend(str(pathlib.Path(__file__).parents[1] / "benchmarks"))
    return importlib.import_module


@pytest.fixture(scope="session")
def compiled_env():
    """``compiled_env(task, solver="default")`` returns a shared :class:`CompiledEnv`."""
    cache: dict[tuple[str, str], CompiledEnv] = {}

    def get(task: str, solver: str = "default") -> CompiledEnv:
        if (task, solver) not in cache:
            cache[(task, solver)] = CompiledEnv(task, solver)
        return cache[(task, solver)]

    return get


_SHARED_GROUPS = {"test_envs.py": "envs", "test_envs_dm_control.py": "envs"}
# The groups that take longest (mostly compiling MJX, cold cache), longest first.
_SLOWEST_FIRST = (
    "envs",
    "test_envs_quadruped.py",
    "test_preference_train.py",
    "test_human_session.py",
    "test_pixel_preference.py",
    "test_cli_reliability.py",
    "test_faithful_protocol.py",
    "test_drqv2.py",
    "test_pixels.py",
    "test_train.py",
)


def _group(nodeid: str) -> str:
    """The xdist work unit of a test: its file, or the group its file shares."""
    name = nodeid.split("::", 1)[0].rsplit("/", 1)[-1]
    return _SHARED_GROUPS.get(name, name)


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup`` with every test file one group (and the env files one together).

    Marking tests ``xdist_group`` does not group them with the pinned pytest 9.2 and
    pytest-xdist 3.8: xdist appends the group to ``item._nodeid``, which pytest 9.2 no longer
    reads, so every test became its own unit, split over both workers, and module fixtures
    ran once per worker and again whenever another file's test came in between. This
    scheduler groups by file name instead.
    """
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class FileGroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _group(nodeid)

        def _assign_work_unit(self, node) -> None:
            # The slowest groups first, so that neither worker is left with one at the end.
            for group in _SLOWEST_FIRST:
                if group in self.workqueue:
                    self.workqueue.move_to_end(group, last=False)
                    break
            super()._assign_work_unit(node)

    return FileGroupScheduling(config, log)
