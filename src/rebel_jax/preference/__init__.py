"""Learning a reward from preferences: the reward ensemble on states (:mod:`~rebel_jax.preference.reward_model`)
and on frames (:mod:`~rebel_jax.preference.pixel_reward`), its training (:mod:`~rebel_jax.preference.reward_train`),
the query rules (:mod:`~rebel_jax.preference.queries`), the scripted teachers
(:mod:`~rebel_jax.preference.teachers`), the label budget (:mod:`~rebel_jax.preference.budget`), the unsupervised
pre-training reward (:mod:`~rebel_jax.preference.pretrain`) and the feedback session that runs select, teach and
learn inside a round (:mod:`~rebel_jax.preference.feedback`, :mod:`~rebel_jax.preference.pixel_feedback`).

The state and pixel twins stay apart where they differ in substance: the pixel ensemble owns a convolutional encoder
and reads segments as frame indices into the agent's frame ring, and its session gathers frames from that ring on the
device instead of slicing stored observation vectors. What they share (the Bradley-Terry loss, the early-stopped
training loop, the query rules, the teachers, the budget) lives once, here.

May import: :mod:`rebel_jax.core` and :mod:`rebel_jax.agents` (the replays a session reads, the networks).
"""
