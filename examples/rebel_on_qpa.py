"""REBEL on QPA: QPA's policy-aligned queries, hybrid replay and reward schedule, with REBEL's ``lambda * V``.

QPA (:mod:`.qpa`) and REBEL (:mod:`.rebel`) answer the same question, the learned reward's error where the current
policy goes, from two sides: QPA asks about and trains on what the policy does now, REBEL adds the learned reward's
value under the policy to the reward loss. This method is both at once, to ask whether REBEL's term adds anything on
top of QPA's fix. Every hook is QPA's but the loss terms, which are QPA's (the Bradley-Terry loss over its crops)
followed by REBEL's value term; REBEL's settings (``rebel.*``, lambda traced, ``--lam-grid``) apply as for ``rebel``.
At lambda 0 it is QPA (tests/test_examples.py), as ``rebel`` at lambda 0 is PEBBLE.

Run it as a method of the command line (this file registers it, then runs ``rebel_jax.train``'s main)::

    python examples/rebel_on_qpa.py rebel_qpa --preset qpa --task walker_walk --feedback.labels 100 --seeds 5 \
        --lam-grid 0 0.001 --sac.precision bf16 --run-dir runs/rebel_qpa_walker_walk
"""

from __future__ import annotations

from rebel_jax import methods
from rebel_jax.methods.qpa import QPA
from rebel_jax.methods.rebel import REBEL
from rebel_jax.run import cli


class REBELOnQPA(QPA, REBEL):
    name = "rebel_qpa"
    config = None  # no settings of its own: it reads QPA's and REBEL's
    uses = ("qpa", "rebel")

    def validate(self, cfg):
        QPA.validate(self, cfg)
        REBEL.validate(self, cfg)

    def reward_terms(self, trainer, ts, key, agent_step):
        """QPA's terms, then REBEL's value term (REBEL's first term, the plain Bradley-Terry loss, gives way to
        QPA's over crops)."""
        value_terms = REBEL.reward_terms(self, trainer, ts, key, agent_step)[1:]
        return [*QPA.reward_terms(self, trainer, ts, key, agent_step), *value_terms]


if __name__ == "__main__":
    methods.register(REBELOnQPA())
    cli.main()
