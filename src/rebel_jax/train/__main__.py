"""``python -m rebel_jax.train``: runs the command line, :mod:`rebel_jax.run`'s entry point, by its name (``runpy``),
so that the trainer's package imports nothing of the layer above it."""

import runpy

if __name__ == "__main__":
    runpy.run_module("rebel_jax.run", run_name="__main__", alter_sys=True)
