"""A run on the host: the command line (:mod:`~rebel_jax.run.cli`, its flags in :mod:`~rebel_jax.run.cli_args`),
the run directory and its fail-closed checks (:mod:`~rebel_jax.run.rundir`, :mod:`~rebel_jax.run.cli_rundir`),
checkpoints (:mod:`~rebel_jax.run.checkpoint`), logs (:mod:`~rebel_jax.run.logging`), what a finished run prints
and saves (:mod:`~rebel_jax.run.cli_outputs`, :mod:`~rebel_jax.run.plots`, :mod:`~rebel_jax.run.video`), the
compilation cache (:mod:`~rebel_jax.run.compile_cache`), and the labelling page for people
(:mod:`~rebel_jax.run.human`).

May import every layer below: :mod:`rebel_jax.api`, :mod:`rebel_jax.train`, :mod:`rebel_jax.config` and what they
stand on. Nothing below imports it.
"""
