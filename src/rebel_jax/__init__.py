"""rebel_jax: preference-based RL (PEBBLE, PEBBLE+SURF, REBEL) in pure JAX on MJX."""

__version__ = "0.1.0"
