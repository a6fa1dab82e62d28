"""Preference-learning methods, one file each, and the table that names them (see :mod:`.base`)."""

from __future__ import annotations

from rebel_jax.methods.base import Method
from rebel_jax.methods.pebble import PEBBLE
from rebel_jax.methods.qpa import QPA
from rebel_jax.methods.rebel import REBEL
from rebel_jax.methods.rune import RUNE
from rebel_jax.methods.surf import SURF

REGISTRY: dict[str, Method] = {m.name: m for m in (PEBBLE(), SURF(), REBEL(), QPA(), RUNE())}
"""The methods a run can name with ``algo`` (``--algo NAME``): ``pebble``, ``surf``, ``rebel``, ``qpa``, ``rune``."""


def register(method: Method) -> Method:
    """Adds ``method`` to :data:`REGISTRY` under ``method.name`` (a method defined outside the package).

    Raises:
      ValueError: if the name is taken, or is one of the agents' (``sac``, ``drqv2``).
    """
    if method.name in REGISTRY or method.name in ("sac", "drqv2"):
        raise ValueError(f"a method named {method.name!r} exists already")
    REGISTRY[method.name] = method
    return method


def get(name: str) -> Method:
    """The registered method ``name``.

    Raises:
      KeyError: naming the registered methods, if there is none of that name.
    """
    if name not in REGISTRY:
        raise KeyError(f"no method {name!r}; registered: {', '.join(REGISTRY)}")
    return REGISTRY[name]
