"""The configuration error and its check, below every module that validates a setting.

``config.py`` composes the leaf configs (queries, reward model, teachers, pre-training), and
each of them validates its own fields; all raise :class:`ConfigError` from here, so no leaf
module imports ``config``.
"""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration value is out of its allowed range."""


def check(cond: bool, field: str, value, allowed: str) -> None:
    """Raises ``ConfigError("{field}={value!r} is invalid: allowed {allowed}")`` unless ``cond``."""
    if not cond:
        raise ConfigError(f"{field}={value!r} is invalid: allowed {allowed}")
