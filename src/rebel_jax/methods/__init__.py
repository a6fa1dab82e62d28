"""Preference-learning methods, one file each, and the table that names them (see :mod:`.base`).

A method defined outside this package joins the table with :func:`register`, or, from an installed package of its
own, through the ``rebel_jax.methods`` entry point group (:func:`load_entry_points`, which the command line calls):

    [project.entry-points."rebel_jax.methods"]
    rime_plus = "my_package.rime_plus:RIMEPlus"     # a Method subclass, or an instance

Then ``python -m rebel_jax.train rime_plus --rime_plus.SETTING VALUE`` runs it, its settings made into flags from
its ``config`` dataclass, and ``--resume`` finds it again the same way.
"""

from __future__ import annotations

from importlib import metadata

from rebel_jax.methods.base import Method
from rebel_jax.methods.mrn import MRN
from rebel_jax.methods.pebble import PEBBLE
from rebel_jax.methods.qpa import QPA
from rebel_jax.methods.rebel import REBEL
from rebel_jax.methods.rime import RIME
from rebel_jax.methods.rune import RUNE
from rebel_jax.methods.surf import SURF

REGISTRY: dict[str, Method] = {m.name: m for m in (PEBBLE(), SURF(), REBEL(), QPA(), RUNE(), RIME(), MRN())}
"""The methods a run can name (``python -m rebel_jax.train NAME``): ``pebble``, ``surf``, ``rebel``, ``qpa``, ``rune``,
``rime``, ``mrn``, and those registered since."""

ENTRY_POINTS = "rebel_jax.methods"
"""The entry point group through which an installed package adds its methods."""

RESERVED = ("sac", "drqv2")
"""The agents' names, which no method may take."""

_loaded: set[str] = set()


def register(method: Method | type[Method]) -> Method:
    """Adds ``method`` (an instance, or a subclass made with no arguments) to :data:`REGISTRY` under its name.

    Raises:
      ValueError: if the name is taken, is one of the agents' (``sac``, ``drqv2``), or is not a lowercase
        identifier (it names the method's flags, ``--NAME.*``).
    """
    if isinstance(method, type):
        method = method()
    if not isinstance(method, Method):
        raise ValueError(f"{method!r} is not a rebel_jax.methods.Method")
    name = method.name
    if not (isinstance(name, str) and name.isidentifier() and name == name.lower()):
        raise ValueError(f"a method's name must be a lowercase identifier (it names its --NAME.* flags), not {name!r}")
    if name in REGISTRY or name in RESERVED:
        raise ValueError(f"a method named {name!r} exists already")
    REGISTRY[name] = method
    return method


def load_entry_points() -> list[str]:
    """Registers the methods of the installed packages' ``rebel_jax.methods`` entry points (each once per process).

    Returns:
      The names registered by this call.

    Raises:
      ValueError: naming the entry point, if one cannot be loaded or registered.
    """
    added = []
    for point in metadata.entry_points(group=ENTRY_POINTS):
        key = f"{point.name}={point.value}"
        if key in _loaded:
            continue
        try:
            method = register(point.load())
        except Exception as err:  # a package's own import error, or a name already taken
            raise ValueError(f"the {ENTRY_POINTS} entry point {point.name} = {point.value} failed: {err}") from err
        _loaded.add(key)
        added.append(method.name)
    return added


def get(name: str) -> Method:
    """The registered method ``name``.

    Raises:
      KeyError: naming the registered methods, if there is none of that name.
    """
    if name not in REGISTRY:
        raise KeyError(f"no method {name!r}; registered: {', '.join(REGISTRY)}")
    return REGISTRY[name]
