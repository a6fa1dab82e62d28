"""The command line, ``python -m rebel_jax.run`` or ``python -m rebel_jax.train``: :func:`rebel_jax.run.cli.main`."""

import os
import sys

from rebel_jax.run import rundir
from rebel_jax.run.cli import main

if __name__ == "__main__":
    try:
        main()
    except SystemExit as end:
        if end.code != rundir.EXIT_IO:
            raise
        # An I/O failure ended the run, its one line printed and every file closed: leave now, before the
        # interpreter's shutdown reports the failed save's leftovers (orbax's pending writes) after that line.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rundir.EXIT_IO)
