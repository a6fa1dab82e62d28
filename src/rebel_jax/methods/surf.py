"""SURF (Park et al., ICLR 2022): pseudo-labels on an unlabelled pool and temporal cropping.

Segments are stored ``surf.crop`` steps longer on each side; the labelled pairs train on random crops
(:func:`rebel_jax.reward_model.bt_loss` with ``crop``) and the pool's confident pairs on their pseudo-labels
(:func:`rebel_jax.surf.pseudo_label_term`). A session grows the pool by ``surf.pool_size`` pairs, then runs a
fixed number of steps with no early stop (alinlab/SURF@2088ee8:train_PEBBLE_semi_dataaug.py:162; on pixels
``surf.reward_update`` passes, alinlab/SURF@214bc1d:pixel_train_PEBBLE_semi.py:275-281).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rebel_jax import pixel_reward, reward_model, reward_train, surf
from rebel_jax.methods.base import Method


class SURF(Method):
    name = "surf"
    config_field = "surf"

    def validate(self, cfg):
        cfg.surf.validate(cfg.query.segment_length)

    def crop(self, cfg) -> int:
        return cfg.surf.crop

    def pool_size(self, cfg) -> int:
        return cfg.surf.pool_size

    def reward_terms(self, trainer, ts, key, agent_step):
        """The BT loss on random crops of the labelled pairs and the pseudo-label term on the pool."""
        del key, agent_step  # Unused.
        rcfg, scfg = trainer.reward_cfg, trainer.cfg.surf
        pseudo = surf.pseudo_label_term(rcfg, scfg, ts.reward.pool)
        if not trainer.cfg.pixels:
            return [reward_model.bt_loss(rcfg, scfg.crop), pseudo]

        def pixel_pseudo(params, batch, key):  # the pool's draws from fold_in(key, 0), as pixel runs always drew them
            return pseudo(params, batch, jax.random.fold_in(key, 0))

        # SURF's pixel code counts the training accuracy on the crops (pixel_reward_model.py:909-919).
        return [reward_model.bt_loss(rcfg, scfg.crop, crop_accuracy=True), pixel_pseudo]

    def grow_pool(self, trainer, ts, stored, key, kept):
        """``stored`` with ``surf.pool_size`` unlabelled pairs of recent episodes added to its pool (none if no
        answer was kept)."""
        size = trainer.cfg.surf.pool_size
        pool_a, pool_b = trainer.sample_pairs(ts.buffer, key, size, trainer.cfg.query.recent_episodes)
        if not trainer.cfg.pixels:
            return surf.add_unlabelled(stored, pool_a, pool_b, kept > 0)
        ones = jnp.full((size,), (kept > 0).astype(jnp.float32))
        return stored.replace(pool=pixel_reward.append_segments(stored.pool, ts.buffer, pool_a, pool_b, ones * 0, ones))

    def train_reward(self, trainer, ts, stored, keys, kept, agent_step):
        """A fixed number of steps, none without new labels: ``ceil(surf.reward_update * labels /
        reward.batch_size)`` minibatch steps on a state task, ``surf.reward_update`` epochs on a pixel task."""
        rcfg, scfg = trainer.reward_cfg, trainer.cfg.surf
        stored = self.grow_pool(trainer, ts, stored, keys["pool"], kept)
        terms = self.reward_terms(trainer, ts.replace(reward=stored), keys["terms"], agent_step)
        if trainer.cfg.pixels:
            epochs = jnp.where(kept > 0, scfg.reward_update, 0)
            return reward_train.train(rcfg, stored, keys["train"], terms, epochs, float("inf"))
        steps = surf.surf_iterations(scfg.reward_update, stored.data.count, rcfg.batch_size, kept)
        return reward_train.train_iterations(rcfg, stored, keys["train"], terms, steps)
