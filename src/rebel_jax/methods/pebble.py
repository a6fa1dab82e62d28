"""PEBBLE (Lee et al., ICML 2021): every hook of :class:`~rebel_jax.methods.base.Method` as it is.

The Bradley-Terry loss on the labelled pairs, up to ``reward.max_epochs`` epochs a session stopped early at
``reward.stop_accuracy`` (rll-research/BPref@f3ece2e:train_PEBBLE.py), queries by ``query.sampling``, SAC on the
ensemble-mean learned reward after the unsupervised phase.
"""

from __future__ import annotations

from rebel_jax.methods.base import Method


class PEBBLE(Method):
    name = "pebble"
