"""What every layer may import, and which imports nothing of rebel_jax: the one-line error of bad input
(:mod:`~rebel_jax.core.errors`) and the ranges that every setting is checked against before anything is written
(:mod:`~rebel_jax.core.ranges`)."""
