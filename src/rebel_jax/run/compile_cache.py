"""JAX's persistent compilation cache for the command lines (``python -m rebel_jax.train`` and ``rebel_jax.run.video``).

A round program takes tens of seconds to minutes to compile; JAX can keep the compiled programs on disk and load
them in a later process that compiles the same program (same code, shapes, flags, jaxlib and devices). The command
lines turn that cache on by default, in a per-user directory (:func:`default_dir`):

1. ``--no-compile-cache``: no persistent cache (JAX's ``jax_enable_compilation_cache`` off);
2. ``--compile-cache DIR``: ``DIR``;
3. a cache directory already set in JAX's own configuration (``JAX_COMPILATION_CACHE_DIR``, or
   ``jax.config.update("jax_compilation_cache_dir", ...)`` before calling ``main``) is kept, with every other JAX
   cache setting as it is; likewise a cache that JAX's ``JAX_ENABLE_COMPILATION_CACHE=false`` turned off;
4. ``$REBEL_JAX_CACHE_DIR``, else ``$XDG_CACHE_HOME/rebel_jax/jax``, else ``~/.cache/rebel_jax/jax``.

Where this module picks the directory (1, 2 and 4), every compiled program is written, however short its compile
(``jax_persistent_cache_min_compile_time_secs`` 0 instead of JAX's 1 s, and no minimum entry size,
``jax_persistent_cache_min_entry_size_bytes`` -1, as JAX's guide sets them), unless the environment sets those JAX
variables itself: on a CPU most of a small run's programs compile in under a second each, and together they are
most of its start. These are JAX's documented options (docs/persistent_compilation_cache.md of jax-ml/jax); the
names are the same in jax 0.10.2 and 0.11.

Several processes of one ``--distributed`` run may use the same directory: JAX writes entries from process 0 only
(``_cache_write`` in jax-ml/jax@cec06d116c05f0d52adfceee3d3b730fdbcb0ce5:jax/_src/compiler.py:835) and every
process reads them, so the directory must be on a file system they share for the others to hit. The key leaves out
the device assignment on GPUs only (jax-ml/jax@cec06d116c05f0d52adfceee3d3b730fdbcb0ce5:jax/_src/cache_key.py:121),
so on CPUs the other processes' keys differ from process 0's and they compile again.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import sys
from collections.abc import Mapping

import jax

from rebel_jax.core.errors import ConfigError

ENV_DIR = "REBEL_JAX_CACHE_DIR"
"""The environment variable that moves the default cache directory."""
MIN_COMPILE_TIME = ("jax_persistent_cache_min_compile_time_secs", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", 0.0)
MIN_ENTRY_SIZE = ("jax_persistent_cache_min_entry_size_bytes", "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", -1)
"""(JAX option, its environment variable, the value set here unless that variable is set): cache every program."""


@dataclasses.dataclass(frozen=True)
class CacheChoice:
    """Where compiled programs are cached, and who decided.

    Attributes:
      directory: the cache directory; None: no persistent cache.
      source: what decided (a flag, an environment variable, JAX's configuration or ``default``), for messages.
      ours: whether :func:`apply` sets JAX's configuration (False: JAX's own settings are kept as they are).
    """

    directory: str | None
    source: str
    ours: bool


def default_dir(environ: Mapping[str, str] = os.environ) -> pathlib.Path:
    """The per-user cache directory: ``$REBEL_JAX_CACHE_DIR``, else ``$XDG_CACHE_HOME/rebel_jax/jax``, else
    ``~/.cache/rebel_jax/jax`` (an empty or relative ``XDG_CACHE_HOME`` is ignored, as the XDG base directory
    specification says)."""
    if environ.get(ENV_DIR, "").strip():
        return pathlib.Path(environ[ENV_DIR]).expanduser()
    xdg = environ.get("XDG_CACHE_HOME", "")
    base = pathlib.Path(xdg) if xdg and pathlib.Path(xdg).is_absolute() else pathlib.Path.home() / ".cache"
    return base / "rebel_jax" / "jax"


def choose(
    flag_dir: str | None,
    off: bool,
    jax_dir: str | None,
    jax_enabled: bool,
    environ: Mapping[str, str] = os.environ,
) -> CacheChoice:
    """The cache directory of a command (the order of the module's docstring).

    Args:
      flag_dir: ``--compile-cache DIR`` (None: not given).
      off: ``--no-compile-cache``.
      jax_dir: JAX's ``jax_compilation_cache_dir`` as it is now (set from ``JAX_COMPILATION_CACHE_DIR``).
      jax_enabled: JAX's ``jax_enable_compilation_cache`` as it is now.

    Returns:
      The :class:`CacheChoice`.

    Raises:
      ConfigError: both flags, or an empty ``--compile-cache``.
    """
    if off and flag_dir is not None:
        raise ConfigError(
            f"compile_cache={flag_dir!r} is invalid with --no-compile-cache: allowed one of --compile-cache DIR"
            " or --no-compile-cache"
        )
    if off:
        return CacheChoice(None, "--no-compile-cache", ours=True)
    if flag_dir is not None:
        if not flag_dir.strip():
            raise ConfigError(
                f"compile_cache={flag_dir!r} is invalid: allowed a directory path (--no-compile-cache: no cache)"
            )
        return CacheChoice(str(pathlib.Path(flag_dir).expanduser().absolute()), "--compile-cache", ours=True)
    if not jax_enabled:
        return CacheChoice(None, "JAX_ENABLE_COMPILATION_CACHE", ours=False)
    if jax_dir:
        return CacheChoice(jax_dir, "JAX_COMPILATION_CACHE_DIR", ours=False)
    source = ENV_DIR if environ.get(ENV_DIR, "").strip() else "default"
    return CacheChoice(str(default_dir(environ).absolute()), source, ours=True)


def _writable(directory: str) -> OSError | None:
    """Creates ``directory`` and checks that a file can be written there; the error, or None."""
    path = pathlib.Path(directory)
    probe = path / f".write-test-{os.getpid()}"
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        return err
    return None


def apply(choice: CacheChoice, environ: Mapping[str, str] = os.environ) -> CacheChoice:
    """Sets JAX's configuration to ``choice`` (nothing where ``choice.ours`` is False); call it before compiling.

    A directory that cannot be written is an error where ``--compile-cache`` named it; a default one is left out with
    a warning (the run goes on without the cache). JAX's cache state is reset, so that a process that compiled
    before (a caller of ``main``) uses the new setting from its next compile.

    Returns:
      The choice in effect (``directory`` None where the default directory was not writable).

    Raises:
      ConfigError: ``--compile-cache DIR`` names a directory that cannot be created or written.
    """
    if not choice.ours:
        return choice
    if choice.directory is not None and (err := _writable(choice.directory)) is not None:
        if choice.source == "--compile-cache":
            raise ConfigError(f"compile_cache={choice.directory!r} is invalid: allowed a writable directory ({err})")
        print(
            f"warning: the compilation cache directory {choice.directory} ({choice.source}) cannot be written ({err});"
            " running without the persistent compilation cache (--compile-cache DIR moves it)",
            file=sys.stderr,
        )
        choice = CacheChoice(None, choice.source, ours=True)
    from jax.experimental.compilation_cache import compilation_cache

    compilation_cache.reset_cache()
    jax.config.update("jax_enable_compilation_cache", choice.directory is not None)
    if choice.directory is not None:
        jax.config.update("jax_compilation_cache_dir", choice.directory)
        for option, variable, value in (MIN_COMPILE_TIME, MIN_ENTRY_SIZE):
            if variable not in environ:
                jax.config.update(option, value)
    return choice


def configure(flag_dir: str | None = None, off: bool = False, environ: Mapping[str, str] = os.environ) -> CacheChoice:
    """:func:`choose` from the flags and JAX's configuration as it is now, then :func:`apply`; the choice in effect.

    Raises:
      ConfigError: a bad ``--compile-cache`` (:func:`choose`, :func:`apply`).
    """
    jax_dir = jax.config.jax_compilation_cache_dir
    choice = choose(flag_dir, off, jax_dir, bool(jax.config.jax_enable_compilation_cache), environ)
    return apply(choice, environ)


def in_use() -> str | None:
    """The persistent compilation cache's directory as JAX's configuration says now; None: no cache."""
    if not jax.config.jax_enable_compilation_cache:
        return None
    return jax.config.jax_compilation_cache_dir or None
