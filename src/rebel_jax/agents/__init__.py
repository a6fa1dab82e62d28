"""The reinforcement-learning agents and what they learn from: SAC on states (:mod:`~rebel_jax.agents.sac`),
DrQ-v2 on pixels (:mod:`~rebel_jax.agents.drqv2`), the interface the trainer drives them through
(:mod:`~rebel_jax.agents.base`), their networks (:mod:`~rebel_jax.agents.networks`), and their replays: a ring of
transitions (:mod:`~rebel_jax.agents.replay`) and a ring of frames (:mod:`~rebel_jax.agents.frame_replay`).

The two replays stay two modules: a state transition is stored whole, a pixel transition as indices into a ring of
single frames from which frame stacks are rebuilt; they share the replay contract, not their storage.

May import: :mod:`rebel_jax.core`. Nothing here knows about preferences.
"""
