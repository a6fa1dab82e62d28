"""``mujoco.mjx``, imported with its optional-backend messages sent to logging.

Without the optional Warp backend (absent on the CPU machines and the GPU image alike),
importing ``mujoco.mjx`` prints "Failed to import warp: No module named 'warp'" and the same
for ``mujoco_warp``. Those lines go to this module's logger at DEBUG level, which Python's
default logging does not show; anything else the import prints is passed through.
"""

from __future__ import annotations

import contextlib
import io
import logging

logger = logging.getLogger(__name__)


def import_quietly() -> None:
    """Imports ``mujoco.mjx`` (a no-op if it already is), logging its "Failed to import" lines at DEBUG."""
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        import mujoco.mjx  # noqa: F401

    for line in printed.getvalue().splitlines():
        if line.startswith("Failed to import"):
            logger.debug("mujoco.mjx: %s", line)
        else:
            print(line)


import_quietly()
