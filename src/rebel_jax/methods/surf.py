"""SURF (Park et al., ICLR 2022): pseudo-labels on an unlabelled pool and temporal cropping.

Segments are stored ``surf.crop`` steps longer on each side; the labelled pairs train on random crops
(:func:`rebel_jax.surf.cropped_bt_loss`) and the pool's confident pairs on their pseudo-labels
(:func:`rebel_jax.surf.pseudo_label_term`). A session grows the pool by ``surf.pool_size`` pairs, then runs a
fixed number of steps with no early stop (alinlab/SURF@866630a:train_PEBBLE_semi_dataaug.py:162; on pixels
``surf.reward_update`` passes, alinlab/SURF@214bc1d:pixel_train_PEBBLE_semi.py:275-281).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rebel_jax import pixel_reward, queries, reward_model, surf
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

    def state_terms(self, trainer, ts, key):
        del key  # Unused.
        rcfg, pool = trainer.reward_cfg, ts.reward.pool
        pseudo = surf.pseudo_label_term(
            rcfg, trainer.cfg.surf, pool.obs_a, pool.act_a, pool.obs_b, pool.act_b, pool.count
        )
        return [surf.cropped_bt_loss(rcfg, trainer.cfg.surf), pseudo]

    def train_state_reward(self, trainer, ts, stored, keys, kept):
        cfg, rcfg = trainer.cfg, trainer.reward_cfg
        pool_a, pool_b = queries.sample_pairs(
            ts.buffer,
            keys["pool"],
            cfg.surf.pool_size,
            trainer.stored_length,
            cfg.env.episode_length,
            cfg.query.recent_episodes,
            cfg.query.pool,
        )
        stored = surf.add_unlabelled(stored, pool_a, pool_b, kept > 0)
        terms = self.state_terms(trainer, ts.replace(reward=stored), keys["terms"])
        steps = surf.surf_iterations(cfg.surf.reward_update, stored.data.count, rcfg.batch_size, kept)
        return reward_model.train_iterations(rcfg, stored, keys["train"], terms, steps)

    def train_pixel_reward(self, trainer, ts, stored, keys, kept, agent_step):
        del agent_step  # Unused.
        cfg, scfg, rcfg = trainer.cfg, trainer.cfg.surf, trainer.cfg.pixel_reward
        pool = pixel_reward.sample_segments(
            keys["value"],
            ts.buffer,
            2 * scfg.pool_size,
            trainer.stored,
            trainer.episode_length,
            cfg.query.recent_episodes,
        )
        pool_a = jax.tree.map(lambda x: x[: scfg.pool_size], pool)
        pool_b = jax.tree.map(lambda x: x[scfg.pool_size :], pool)
        ones = jnp.full((scfg.pool_size,), (kept > 0).astype(jnp.float32))
        stored = stored.replace(
            pool=pixel_reward.append_segments(stored.pool, ts.buffer, pool_a, pool_b, ones * 0, ones)
        )
        terms = (pixel_reward.pseudo_label_term(rcfg, scfg, stored.pool),)
        epochs = jnp.where(kept > 0, scfg.reward_update, 0)  # none without new labels, as on state tasks
        return pixel_reward.train(rcfg, stored, keys["train"], terms, trainer.crop, epochs, float("inf"))
