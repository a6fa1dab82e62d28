"""REBEL (Chakraborty et al., AAAI 2025): the agent-preference term ``lambda * V`` added to the reward loss.

``V`` is the learned reward's value under the current policy, differentiated with respect to the reward's
parameters only (:mod:`rebel_jax.agent_preference`). ``rebel.form`` chooses the paper's lower bound
(``lambda * V``) or its penalty (``lambda * (V* - V)``, ``V*`` from the best labelled segments);
``rebel.source`` where ``V``'s trajectories come from: the evaluation episodes of the policy (``onpolicy``,
the paper's) or replay segments with actions redrawn from the current policy (``replay``). Lambda is traced
(``TrainState.lam``), so a sweep runs several lambdas as columns of one program; lambda 0 is PEBBLE.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rebel_jax import agent_preference, frame_replay, pixel_reward, reward_model
from rebel_jax.errors import check
from rebel_jax.methods.base import Method


class REBEL(Method):
    name = "rebel"
    config_field = "rebel"

    def validate(self, cfg):
        rebel = cfg.rebel
        rebel.validate()
        if rebel.source == "replay":
            length = rebel.segment_length
            check(length <= cfg.env.episode_length, "rebel.segment_length", length, "<= env.episode_length")
            return
        check(rebel.episodes <= cfg.train.eval_episodes, "rebel.episodes", rebel.episodes, "<= train.eval_episodes")
        if not cfg.pixels:  # the pixel trainer checks in agent steps
            check(rebel.horizon <= cfg.env.episode_length, "rebel.horizon", rebel.horizon, "<= env.episode_length")
            cfg.check_complete_episode("rebel.source='onpolicy'", "V's episodes", "--rebel.source replay")

    def knob(self, cfg) -> jax.Array:
        return jnp.asarray(cfg.rebel.lam, jnp.float32)

    def trajectory_size(self, cfg, episode_length, pixels):
        if cfg.rebel.source != "onpolicy":
            return None
        return cfg.rebel.onpolicy_size(cfg.train.eval_episodes, episode_length, pixels)

    def episode_lengths(self, cfg):
        if cfg.rebel.source == "replay":
            return {"rebel.segment_length": cfg.rebel.segment_length}
        return {"rebel.horizon": cfg.rebel.horizon}

    def value_trajectories(self, trainer, ts, key: jax.Array, agent_step):
        """V's trajectories: ``(obs, actions (N, T, A), predict_fn)``, ``predict_fn(params, obs, actions) -> (M, N,
        T)`` the members' rewards (None: the ensemble's ``predict`` on ``obs`` as they are).

        On a state task, ``onpolicy``: the first ``rebel.horizon`` steps of the evaluation environments' last
        complete episodes, N = ``rebel.episodes`` and T = ``rebel.horizon`` (by default all of them, whole);
        ``replay``: ``rebel.num_segments`` replay segments, actions redrawn from the current policy (``a_h ~
        pi_theta``, held fixed). On a pixel task the stacks are kept out of the closure (:meth:`_pixel_trajectories`).
        """
        if trainer.cfg.pixels:
            return self._pixel_trajectories(trainer, ts, key, agent_step)
        rebel = trainer.cfg.rebel
        if rebel.source == "onpolicy":
            last = ts.eval_trajectory["last"]
            return jnp.swapaxes(last["obs"], 0, 1), jnp.swapaxes(last["action"], 0, 1), None
        key_segments, key_actions = jax.random.split(key)
        seg = trainer.sample_segments(ts.buffer, key_segments, rebel.num_segments, rebel.segment_length)
        return seg.obs, trainer.agent.act(ts.agent, seg.obs, key_actions, None), None

    def _pixel_trajectories(self, trainer, ts, key: jax.Array, agent_step: jax.Array):
        """V's trajectories on a pixel task. ``onpolicy``: the first ``rebel.horizon`` agent steps of the last
        complete episodes of ``rebel.episodes`` evaluation environments (the mean action of the DrQ-v2 policy frozen
        at the episode start); ``obs`` are their kept newest frames (N, T, H, W, 3), whose stacks ``predict_fn``
        rebuilds (:func:`rebel_jax.frame_replay.episode_stacks`). ``replay``: ``rebel.num_segments`` replay segments
        of ``rebel.segment_length`` steps from the query pool, actions redrawn once from the current DrQ-v2 policy
        (its exploration noise at ``agent_step``) and held fixed; ``obs`` are their places (N, T, 2) = (row, env),
        whose frames ``predict_fn`` gathers from the replay (``pixel_reward.place_rewards``).
        """
        rebel, rcfg, buffer = trainer.cfg.rebel, trainer.reward_cfg, ts.buffer
        if rebel.source == "onpolicy":
            last = ts.eval_trajectory["last"]
            stack = trainer.env.frames

            def episode_rewards(params, frames, action):
                return reward_model.predict(rcfg, params, frame_replay.episode_stacks(frames, stack), action)

            return jnp.swapaxes(last["frame"], 0, 1), jnp.swapaxes(last["action"], 0, 1), episode_rewards
        key_segments, key_actions = jax.random.split(key)
        length = rebel.segment_length
        places = trainer.sample_segments(buffer, key_segments, rebel.num_segments, length)
        rows = pixel_reward.segment_rows(places.row, length)
        envs = jnp.broadcast_to(places.env[:, None], rows.shape)

        def act(inputs):
            row, env, key = inputs
            stacks = frame_replay.row_stacks(buffer, row % buffer.rows, env)
            return trainer.agent.act(ts.agent, stacks, key, agent_step)

        actions = jax.lax.map(act, (rows, envs, jax.random.split(key_actions, rebel.num_segments)))  # one at a time

        def predict_fn(params, place, action):
            return pixel_reward.place_rewards(rcfg, params, buffer, place, action)

        return jnp.stack([rows, envs], axis=-1), actions, predict_fn

    def best_segments(self, trainer, ts):
        """``V*``'s segments: the ``rebel.best_segments`` labelled segments (both sides of every stored pair) of
        highest ensemble-mean learned return at the session's start, and their validity (empty slots never win).
        On pixels their returns are computed by chunks and the segments gathered from the store's copies."""
        rcfg, k, reward = trainer.reward_cfg, trainer.cfg.rebel.best_segments, ts.reward
        if not trainer.cfg.pixels:
            return agent_preference.best_segments(rcfg, reward.params, reward.data, k)
        data = reward.data
        filled = jnp.tile(jnp.arange(data.capacity) < data.count, 2)  # a sides, then b sides
        returns = jnp.mean(pixel_reward.stored_returns(rcfg, reward.params, data), axis=0)
        index, valid = agent_preference.top_segments(returns, filled, k)
        return pixel_reward.stored_side(data, index), valid

    def reward_terms(self, trainer, ts, key, agent_step):
        """The BT loss and ``lambda * V`` (``rebel.form`` lower_bound) or ``lambda * (V* - V)`` (penalty), through
        :mod:`rebel_jax.agent_preference`. ``rebel.normalize`` divides by the spread of the per-step rewards of the
        minibatch's labelled pairs (no extra encoder pass on pixels)."""
        rcfg, rebel = trainer.reward_cfg, trainer.cfg.rebel
        obs, actions, predict_fn = self.value_trajectories(trainer, ts, key, agent_step)
        common = dict(estimator=rebel.estimator, normalize=rebel.normalize, predict_fn=predict_fn)
        if rebel.form == "penalty":  # V(pi*(nu)) from the best labelled segments, ranked once per session.
            best, valid = self.best_segments(trainer, ts)
            value = agent_preference.value_gap_term(rcfg, ts.lam, obs, actions, best, valid, rebel.gamma, **common)
        else:
            value = agent_preference.agent_value_term(rcfg, ts.lam, obs, actions, rebel.gamma, **common)
        return [reward_model.bt_loss(rcfg), value]
