"""The allowed range of every numeric setting, declared with the setting and checked before anything runs.

A field of a frozen config dataclass declares its range in its type, ``Annotated[float, Range(0, 1)]``; a numeric
field without one gets its type's default: an ``int`` in [0, 2**31 - 1] (it sizes or counts arrays indexed in
int32), a ``float`` finite in float32. :func:`check_ranges` walks a config (nested dataclasses and tuples included)
and raises :class:`rebel_jax.core.errors.ConfigError` in one line naming the first field out of its range and the
range. Checks that relate several fields stay in each config's ``validate``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing

import numpy as np

from rebel_jax.core.errors import ConfigError

INT_MAX = 2**31 - 1
"""The largest integer setting by default: sizes, counts and steps are indexed in int32 by the compiled programs."""
FLOAT_MAX = float(np.finfo(np.float32).max)
"""The largest magnitude of a float setting: the programs compute in float32."""


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a numeric field may take: ``lo`` to ``hi`` (None: the type's default bound), either end open.

    Attributes:
      lo: the least value (None: 0 for ints, -FLOAT_MAX for floats).
      hi: the largest value (None: INT_MAX for ints, FLOAT_MAX for floats).
      lo_open: ``lo`` itself is refused.
      hi_open: ``hi`` itself is refused.
      inf: ``+inf`` is allowed beside the range (e.g. a rational teacher's beta).
      note: what a special value means, said with the range (``0: no limit``).
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    inf: bool = False
    note: str = ""

    def bounds(self, kind: type) -> tuple[float, float]:
        """(lo, hi) with the type's defaults filled in."""
        if kind is int:
            return (0 if self.lo is None else self.lo), (INT_MAX if self.hi is None else self.hi)
        return (-FLOAT_MAX if self.lo is None else self.lo), (FLOAT_MAX if self.hi is None else self.hi)

    def describe(self, kind: type) -> str:
        """The range in words: ``integers 1 to 2147483647``, ``finite numbers in (0, 1]``."""
        lo, hi = self.bounds(kind)
        if kind is int and math.isinf(lo) and math.isinf(hi):
            text = "any integer"
        elif kind is int:
            text = f"integers {int(lo) + self.lo_open} to {int(hi) - self.hi_open}"
        else:
            text = f"numbers in {'(' if self.lo_open else '['}{lo:g}, {hi:g}{')' if self.hi_open else ']'}"
            if self.lo is None and self.hi is None:
                text = f"finite numbers within float32 (|x| <= {hi:g}, none that rounds to 0)"
        text += " or inf" if self.inf else ""
        return text + (f" ({self.note})" if self.note else "")

    def admits(self, value: float, kind: type) -> bool:
        """Whether ``value`` is in the range (a nonzero float must also stay nonzero in float32)."""
        if self.inf and value == math.inf:
            return True
        if isinstance(value, float) and not math.isfinite(value):
            return False
        lo, hi = self.bounds(kind)
        if kind is float and 0 < abs(value) <= FLOAT_MAX and np.float32(value) == 0:
            return False
        above = value > lo if self.lo_open else value >= lo
        below = value < hi if self.hi_open else value <= hi
        return above and below


DEFAULT = Range()
ANY_INTEGER = Range(-math.inf, math.inf)
"""Every integer (a seed: ``train.seed_keys`` spells the whole integer into its keys)."""
POSITIVE = Range(0, lo_open=True)
"""Greater than 0 (a size, a count, a learning rate)."""
NON_NEGATIVE = Range(0)
UNIT = Range(0, 1)
"""A fraction or a probability: [0, 1]."""


def _kind(hint) -> type | None:
    """``int`` or ``float`` for a numeric field's type (optional, or a tuple of them), None for any other."""
    if typing.get_origin(hint) is typing.Annotated:
        hint = typing.get_args(hint)[0]
    if hint in (int, float):
        return hint
    args = [a for a in typing.get_args(hint) if a is not type(None) and a is not Ellipsis]
    if typing.get_origin(hint) in (typing.Union, types.UnionType, tuple):
        kinds = {_kind(a) for a in args}
        return kinds.pop() if len(kinds) == 1 else None
    return None


@functools.cache
def field_ranges(cls: type) -> dict[str, tuple[type, Range]]:
    """Each numeric field of the dataclass ``cls``: its kind (int or float) and its declared or default range."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = {}
    for field in dataclasses.fields(cls):
        hint = hints[field.name]
        kind = _kind(hint)
        if kind is None:
            continue
        declared = [m for m in getattr(hint, "__metadata__", ()) if isinstance(m, Range)]
        out[field.name] = (kind, declared[0] if declared else DEFAULT)
    return out


def check_value(name: str, value, kind: type, allowed: Range) -> None:
    """Raises ConfigError naming ``name`` and the range unless ``value`` (or each of a tuple's values) fits it."""
    for item in value if isinstance(value, tuple) else (value,):
        if item is None or isinstance(item, bool):
            continue
        if not allowed.admits(item, kind):
            raise ConfigError(f"{name}={value!r} is invalid: allowed {allowed.describe(kind)}")


def check_ranges(cfg, prefix: str = "", skip: tuple[str, ...] = ()) -> None:
    """Checks every numeric field of the dataclass ``cfg`` and of the dataclasses in it against its range.

    Args:
      cfg: a dataclass instance (a config or one of its sections).
      prefix: put before each field's name in a refusal (``sac.``).
      skip: names of ``cfg``'s own fields not to check (checked elsewhere).

    Raises:
      ConfigError: one line, ``{prefix}{field}={value!r} is invalid: allowed {range}``, for the first field out of
        its range.
    """
    ranges = field_ranges(type(cfg))
    for field in dataclasses.fields(cfg):
        if field.name in skip:
            continue
        value = getattr(cfg, field.name)
        if dataclasses.is_dataclass(value):
            check_ranges(value, f"{prefix}{field.name}.")
        elif field.name in ranges:
            check_value(prefix + field.name, value, *ranges[field.name])
