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

    # -- state tasks ----------------------------------------------------------------------
    def value_trajectories(self, trainer, ts, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """V's trajectories on a state task: ``(obs (N, H, obs_size), actions (N, H, act_size))``.

        ``onpolicy``: the first ``rebel.horizon`` steps of the evaluation environments' last complete
        episodes, N = ``rebel.episodes`` and H = ``rebel.horizon`` (by default all of them, whole).
        ``replay``: ``num_segments`` replay segments, actions redrawn from the current policy
        (``a_h ~ pi_theta``, held fixed).
        """
        if trainer.cfg.rebel.source == "onpolicy":
            last = ts.eval_trajectory["last"]
            return jnp.swapaxes(last["obs"], 0, 1), jnp.swapaxes(last["action"], 0, 1)
        rebel = trainer.cfg.rebel
        key_segments, key_actions = jax.random.split(key)
        seg = trainer.sample_segments(ts.buffer, key_segments, rebel.num_segments, rebel.segment_length)
        return seg.obs, trainer.agent.act(ts.agent, seg.obs, key_actions, None)

    def state_terms(self, trainer, ts, key):
        rcfg, rebel = trainer.reward_cfg, trainer.cfg.rebel
        obs, actions = self.value_trajectories(trainer, ts, key)
        common = (rebel.gamma, rebel.estimator, rebel.normalize)
        if rebel.form == "penalty":  # V(pi*(nu)) from the best labelled segments, ranked once per session.
            best = agent_preference.best_segments(rcfg, ts.reward.params, ts.reward.data, rebel.best_segments)
            value = agent_preference.value_gap_term(rcfg, ts.lam, obs, actions, *best, *common)
        else:
            value = agent_preference.agent_value_term(rcfg, ts.lam, obs, actions, *common)
        return [reward_model.bt_loss(rcfg), value]

    # -- pixel tasks ----------------------------------------------------------------------
    def pixel_value_trajectories(self, trainer, ts, key: jax.Array, agent_step: jax.Array):
        """V's trajectories on a pixel task: ``(obs, actions (N, T, A), predict_fn)``, ``predict_fn(params, obs,
        actions) -> (M, N, T)`` the members' rewards, the stacks kept out of the closure.

        ``onpolicy``: the first ``rebel.horizon`` agent steps of the last complete episodes of ``rebel.episodes``
        evaluation environments (the mean action of the DrQ-v2 policy frozen at the episode start); ``obs`` are
        their kept newest frames (N, T, H, W, 3), whose stacks ``predict_fn`` rebuilds
        (:func:`rebel_jax.frame_replay.episode_stacks`). ``replay``: ``rebel.num_segments`` replay segments of
        ``rebel.segment_length`` steps from the query pool, actions redrawn once from the current DrQ-v2 policy
        (its exploration noise at ``agent_step``) and held fixed; ``obs`` are their places (N, T, 2) = (row, env),
        whose frames ``predict_fn`` gathers from the replay (``pixel_reward.place_rewards``).
        """
        rebel, rcfg, buffer = trainer.cfg.rebel, trainer.cfg.pixel_reward, ts.buffer
        if trainer.cfg.rebel.source == "onpolicy":
            last = ts.eval_trajectory["last"]
            stack = trainer.env.frames

            def episode_rewards(params, frames, action):
                return pixel_reward.predict(rcfg, params, frame_replay.episode_stacks(frames, stack), action)

            return jnp.swapaxes(last["frame"], 0, 1), jnp.swapaxes(last["action"], 0, 1), episode_rewards
        key_segments, key_actions = jax.random.split(key)
        recent = trainer.cfg.query.recent_episodes
        length = rebel.segment_length
        places = pixel_reward.sample_segments(
            key_segments, buffer, rebel.num_segments, length, trainer.episode_length, recent
        )
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

    def pixel_terms(self, trainer, ts, key, agent_step) -> tuple:
        """``lambda * V`` or ``lambda * (V* - V)`` on pixels, through :mod:`rebel_jax.agent_preference` as on state
        tasks. ``V*`` comes from the ``rebel.best_segments`` labelled segments (both sides of every stored pair, the
        label store's copies) of highest ensemble-mean learned return at the session's start, with their stored
        actions. ``rebel.normalize`` divides by the spread of the per-step rewards the BT term computed on the
        minibatch (no extra encoder pass)."""
        rebel, rcfg = trainer.cfg.rebel, trainer.cfg.pixel_reward
        obs, actions, predict_fn = self.pixel_value_trajectories(trainer, ts, key, agent_step)

        def spread_fn(params, bt):
            del params  # Unused: the BT term's rewards are the parameters' already.
            return agent_preference.reward_spread(bt["rewards_a"], bt["rewards_b"], bt["weight"])

        common = dict(estimator=rebel.estimator, normalize=rebel.normalize, predict_fn=predict_fn, spread_fn=spread_fn)
        if rebel.form == "lower_bound":
            return (agent_preference.agent_value_term(rcfg, ts.lam, obs, actions, rebel.gamma, **common),)
        data = ts.reward.data
        filled = jnp.tile(jnp.arange(data.capacity) < data.count, 2)  # a sides, then b sides
        returns = jnp.mean(pixel_reward.stored_returns(rcfg, ts.reward.params, data), axis=0)
        index, valid = agent_preference.top_segments(returns, filled, rebel.best_segments)
        best = pixel_reward.stored_side(data, index)

        def best_predict_fn(params, frames, action):
            return pixel_reward.frame_rewards(rcfg, params, frames, action)

        args = (rcfg, ts.lam, obs, actions, best.frames, best.action, valid, rebel.gamma)
        return (agent_preference.value_gap_term(*args, best_predict_fn=best_predict_fn, **common),)
