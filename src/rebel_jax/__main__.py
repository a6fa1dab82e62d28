"""The command line: ``python -m rebel_jax`` (and ``python -m rebel_jax.train``), see :mod:`rebel_jax.cli`."""

from rebel_jax.cli import main

if __name__ == "__main__":
    main()
