"""RIME (Cheng et al., ICML 2024): robust reward learning from noisy labels (CJReinforce/RIME_ICML2024@4ad03f4).

Every reward epoch first selects the labelled pairs it learns from (reward_model_RIME.py:56-107): with
``ce_i = -ln pbar_i[y_i]``, the cross-entropy of the ensemble-mean preference probability against the stored
label, a pair is trusted below ``tau_lower = -ln(x + 1e-8) + alpha x + min(beta_t var, cap)`` (x an EMA of the
trusted losses' maximum, var their cumulative variance, beta_t decaying over the run's epochs) and its label is
flipped, for that epoch only, above ``tau_upper = -ln(flip_tau)``. The epoch then trains on the trusted and the
flipped pairs, the reward lr rising linearly from 0 over the first ``warmup_epochs`` epochs. During pre-training
the ensemble is fitted to the normalised kNN entropy (its warm start, train_RIME.py:315-336) and SAC learns from
RIME's intrinsic reward (agent/sac_RIME.py:188-197); the critic is kept after pre-training. docs/methods.md
lists the differences from the original.
"""

from __future__ import annotations

import dataclasses
import math

import flax.struct
import jax
import jax.numpy as jnp
import optax

from rebel_jax.core.errors import check
from rebel_jax.methods.base import Method
from rebel_jax.preference import reward_model, reward_train
from rebel_jax.preference.reward_model import PairStore


@dataclasses.dataclass(frozen=True)
class RIMEConfig:
    """RIME's settings: its DMC command's (CJReinforce/RIME_ICML2024@4ad03f4:run_parallel.sh:103, train_RIME.py:42)."""

    alpha: float = 0.5
    """Weight of x in tau_lower (``threshold_alpha``)."""
    beta_init: float = 3.0
    """beta_t at the run's first reward epoch (``threshold_beta_init``)."""
    beta_min: float = 1.0
    """beta_t from ``decay_epochs`` epochs on (``threshold_beta_min``)."""
    decay_epochs: int = 60
    """k: reward epochs of the run over which beta_t falls linearly to ``beta_min`` (Meta-World: 600)."""
    flip_tau: float = 0.001
    """A pair's label is flipped for an epoch when its loss exceeds ``-ln(flip_tau)`` (``flipping_tau``)."""
    var_cap: float = 3.0
    """Cap of the uncertainty term ``beta_t var`` (reward_model_RIME.py:92)."""
    ema_rate: float = 0.1
    """Rate of the EMAs of the trusted losses' mean and maximum (``RunningMeanStd(mode='fixed', lr=0.1)``)."""
    least_epochs: int = 15
    """A session stops early only after more than this many epochs (``least_reward_update``)..."""
    stop_accuracy: float = 0.98
    """...once the members' mean accuracy on the epoch's training pairs exceeds this (train_RIME.py:183)."""
    warmup_epochs: int = 50
    """The reward lr rises linearly from 0 over this many epochs from the first feedback on: ``num_warmup_steps =
    int(labels / per_session * least_reward_update / 3 + 0.5)``, 50 at 1,000 labels in 100s (train_RIME.py:77)."""
    warm_steps: int = 5
    """Warm-start reward steps per environment step of pre-training (train_RIME.py:321; 0: no warm start)."""

    def validate(self) -> None:
        check(self.alpha >= 0, "rime.alpha", self.alpha, ">= 0")
        check(self.beta_min >= 0, "rime.beta_min", self.beta_min, ">= 0")
        check(self.beta_init >= self.beta_min, "rime.beta_init", self.beta_init, f">= rime.beta_min={self.beta_min}")
        check(self.decay_epochs >= 1, "rime.decay_epochs", self.decay_epochs, ">= 1")
        check(0 < self.flip_tau < 1, "rime.flip_tau", self.flip_tau, "(0, 1)")
        check(self.var_cap >= 0, "rime.var_cap", self.var_cap, ">= 0")
        check(0 < self.ema_rate <= 1, "rime.ema_rate", self.ema_rate, "(0, 1]")
        check(self.least_epochs >= 0, "rime.least_epochs", self.least_epochs, ">= 0")
        check(self.stop_accuracy > 0, "rime.stop_accuracy", self.stop_accuracy, "> 0")
        check(self.warmup_epochs >= 0, "rime.warmup_epochs", self.warmup_epochs, ">= 0")
        check(self.warm_steps >= 0, "rime.warm_steps", self.warm_steps, ">= 0")


@flax.struct.dataclass
class RIMEState:
    """One seed's RIME statistics, kept over the whole run (utils.py:195-227; agent/sac_RIME.py:47)."""

    kl_mean: jax.Array
    """EMA of the trusted losses' mean (kept as the original does; the rule does not read it)."""
    kl_var: jax.Array
    """Variance of every trusted loss so far (Chan's merge; 1 before any)."""
    kl_max: jax.Array
    """x: EMA of each epoch's largest trusted loss (0 at first)."""
    kl_count: jax.Array
    """Trusted losses so far."""
    epochs: jax.Array
    """Reward epochs so far (``update_step``): beta_t's and the lr warm-up's step."""
    ent_min: jax.Array
    """Smallest kNN distance of pre-training's minibatches (``s_ent_stats[0]``)."""
    ent_max: jax.Array
    """Largest one (``s_ent_stats[1]``)."""


def init_rime_state() -> RIMEState:
    """The statistics before any data: ``RunningMeanStd(mean=0, std=1.0)``, ``s_ent_stats = [inf, -inf]``."""
    zero, one = jnp.zeros(()), jnp.ones(())
    return RIMEState(zero, one, zero, zero, jnp.zeros((), jnp.int32), jnp.full((), jnp.inf), jnp.full((), -jnp.inf))


def selection_losses(logits: jax.Array, labels: jax.Array) -> jax.Array:
    """``-sum_c y_c ln(mean_m softmax_m[c])`` per pair (reward_model_RIME.py:60-84), ``logits`` (M, N) the members'
    ``G(b) - G(a)``, ``labels`` (N,) P(b preferred); no epsilon in the log, as the original."""
    prob_b, prob_a = jnp.mean(jax.nn.sigmoid(logits), 0), jnp.mean(jax.nn.sigmoid(-logits), 0)
    return -(labels * jnp.log(prob_b) + (1.0 - labels) * jnp.log(prob_a))


def select(rime: RIMEConfig, state: RIMEState, ce: jax.Array, valid: jax.Array):
    """The trusted (``ce < tau_lower``) and flipped (``ce > -ln flip_tau``) masks among ``valid`` pairs, and
    ``tau_lower = -ln(x + 1e-8) + alpha x + min(beta_t var, cap)`` (reward_model_RIME.py:50-51, 87-99)."""
    fall = (rime.beta_init - rime.beta_min) / rime.decay_epochs
    beta = jnp.maximum(rime.beta_min, rime.beta_init - fall * state.epochs)
    x = state.kl_max
    tau = -jnp.log(x + 1e-8) + rime.alpha * x + jnp.minimum(beta * state.kl_var, rime.var_cap)
    return valid & (ce < tau), valid & (ce > -math.log(rime.flip_tau)), tau


def update_stats(rime: RIMEConfig, state: RIMEState, ce: jax.Array, trusted: jax.Array) -> RIMEState:
    """``KL_div.update(ce[trusted])`` (utils.py:205-227, mode 'fixed'): EMAs of the mean and the maximum, Chan's
    merge of the population variance. Unchanged without a trusted pair (the original would fail there)."""
    n = jnp.sum(trusted).astype(jnp.float32)
    mean = jnp.sum(jnp.where(trusted, ce, 0.0)) / jnp.maximum(n, 1.0)
    var = jnp.sum(jnp.where(trusted, (ce - mean) ** 2, 0.0)) / jnp.maximum(n, 1.0)
    delta, total = mean - state.kl_mean, state.kl_count + n
    m2 = state.kl_var * state.kl_count + var * n + delta**2 * state.kl_count * n / jnp.maximum(total, 1e-30)
    new = state.replace(
        kl_mean=state.kl_mean + rime.ema_rate * delta,
        kl_max=state.kl_max + rime.ema_rate * (jnp.max(jnp.where(trusted, ce, -jnp.inf)) - state.kl_max),
        kl_var=m2 / jnp.maximum(total, 1e-30),
        kl_count=total,
    )
    return jax.tree.map(lambda a, b: jnp.where(n > 0, a, b), new, state)


def warmup_factor(epoch: jax.Array, warmup: int) -> jax.Array:
    """``get_constant_schedule_with_warmup``'s factor at step ``epoch``: ``epoch / warmup`` below ``warmup``, then 1
    (0 at the first epoch: ``LambdaLR`` applies step 0 when made, reward_model_RIME.py:47-48, 174)."""
    return jnp.where(epoch < warmup, epoch / max(1, warmup), 1.0).astype(jnp.float32)


def training_store(data: PairStore, labels: jax.Array, trusted: jax.Array, flipped: jax.Array) -> PairStore:
    """The epoch's training set, the original's ``concatenate([trusted, flipped])`` (reward_model_RIME.py:107): the
    trusted slots then the flipped ones packed at the front of a store of 2C slots with the epoch's ``labels``, so
    a pair both trusted and flipped is there twice, as in the original."""
    chosen = jnp.concatenate([trusted, flipped])
    slots = jnp.argsort(~chosen, stable=True) % data.capacity
    take = lambda x: x[slots]  # noqa: E731
    count = jnp.sum(chosen).astype(data.count.dtype)
    a, b = jax.tree.map(take, data.a), jax.tree.map(take, data.b)
    return PairStore(a=a, b=b, labels=labels[slots], ptr=jnp.zeros_like(data.ptr), count=count)


def with_lr(reward: reward_model.RewardState, lr: jax.Array) -> reward_model.RewardState:
    """``reward`` with the learning rate of its ``inject_hyperparams`` Adam state set to ``lr``."""
    opt = reward.opt_state
    hyper = dict(opt.hyperparams, learning_rate=jnp.asarray(lr, opt.hyperparams["learning_rate"].dtype))
    return reward.replace(opt_state=opt._replace(hyperparams=hyper))


def entropy_target(ent: jax.Array, mean, std, ent_min, ent_max) -> jax.Array:
    """The warm start's target ``((ent - mean) / std) / max |([min, max] - mean) / std|`` (train_RIME.py:326-328)."""
    scale = jnp.maximum(jnp.abs((ent_min - mean) / std), jnp.abs((ent_max - mean) / std))
    return (ent - mean) / std / scale


class RIME(Method):
    """PEBBLE with RIME's robust reward epochs: pairs trusted below a dynamic bound, labels flipped above one."""

    name = "rime"
    config = RIMEConfig
    pixels = False

    def validate(self, cfg):
        cfg.rime.validate()
        check(not cfg.pixels, "env.task", cfg.env.task, "a state task with --algo rime (warm start)")

    def init_state(self, trainer, key):
        del trainer, key  # Unused.
        return init_rime_state()

    def reward_optimizer(self, trainer):
        """Adam whose learning rate each epoch sets (the warm-up), one state from the warm start on."""
        return optax.inject_hyperparams(optax.adam)(learning_rate=trainer.reward_cfg.lr)

    def resets_critic(self, cfg):
        """RIME keeps the critic learnt in pre-training (train_RIME.py:247-278 has no ``reset_critic``)."""
        del cfg  # Unused.
        return False

    def train_reward(self, trainer, ts, stored, keys, kept, agent_step, first):
        """Up to ``reward.max_epochs`` epochs, each selecting, flipping and training (see the module docstring),
        stopped once the accuracy exceeds ``stop_accuracy`` after more than ``least_epochs`` (train_RIME.py:174-184).
        Metrics of the last epoch: ``trusted`` and ``flipped`` (shares of the labels), ``tau_lower``, ``lr``."""
        del agent_step, first  # Unused: the warm-up counts the run's epochs.
        rcfg, rime = trainer.reward_cfg, self.settings(trainer.cfg)
        most = jnp.where(kept > 0, rcfg.max_epochs, 0)
        data = stored.data
        valid, segments = jnp.arange(data.capacity) < data.count, (data.a, data.b)

        def epoch(carry):
            reward, state, done, _, _ = carry
            ret_a, ret_b = (jnp.sum(reward_model.predict(rcfg, reward.params, *s.inputs()), -1) for s in segments)
            ce = selection_losses(ret_b - ret_a, data.labels)
            trusted, flipped, tau = select(rime, state, ce, valid)
            labels = jnp.where(flipped, 1.0 - data.labels, data.labels)  # flipped for this epoch only
            lr = rcfg.lr * warmup_factor(state.epochs, rime.warmup_epochs)
            state = update_stats(rime, state, ce, trusted).replace(epochs=state.epochs + 1)  # before the epoch's steps
            train = with_lr(reward, lr).replace(data=training_store(data, labels, trusted, flipped))
            key = jax.random.fold_in(keys["train"], done)
            train, metrics = reward_train.train_epoch(rcfg, train, key, optimizer=trainer.reward_optimizer)
            n = jnp.maximum(data.count, 1)
            own = {"loss": metrics["loss"], "trusted": jnp.sum(trusted) / n, "flipped": jnp.sum(flipped) / n}
            own |= {"tau_lower": tau, "lr": lr}
            return train.replace(data=data), state, done + 1, metrics["accuracy"], own

        def running(carry):
            _, _, done, accuracy, _ = carry
            return (done < most) & ~((accuracy > rime.stop_accuracy) & (done > rime.least_epochs + 1))

        zeros = {k: jnp.zeros(()) for k in ("loss", "trusted", "flipped", "tau_lower", "lr")}
        start = (stored, ts.method, jnp.zeros((), jnp.int32), jnp.asarray(-1.0), zeros)
        reward, state, done, accuracy, own = jax.lax.while_loop(running, epoch, start)
        return reward, state, {"epochs": done, "train_accuracy": jnp.maximum(accuracy, 0.0), **own}

    def pretrain_step(self, trainer, ts, batches, key):
        """SAC's minibatches get RIME's reward ``clip((ent - mean) / (3 std), -1, 1)``; then ``warm_steps`` reward
        steps per environment step, each on one of those minibatches in turn (the original draws fresh ones), with
        the members' MSE to :func:`entropy_target` summed. ``ent`` is the kNN distance, read back from PEBBLE's
        reward ``ent / std`` with the statistics after the vector step's minibatches (``ts.entropy_stats``)."""
        del key  # Unused.
        rcfg, rime, stats = trainer.reward_cfg, self.settings(trainer.cfg), ts.entropy_stats
        std = jnp.maximum(jnp.sqrt(stats.var), 1e-8)
        ent = batches.reward * std
        state = ts.method.replace(
            ent_min=jnp.minimum(ts.method.ent_min, jnp.min(ent)), ent_max=jnp.maximum(ts.method.ent_max, jnp.max(ent))
        )
        target = entropy_target(ent, stats.mean, std, state.ent_min, state.ent_max)
        optimizer, minibatches = trainer.reward_optimizer, ent.shape[0]

        def loss_fn(params, obs, action, target):
            return jnp.sum(jnp.mean((reward_model.predict(rcfg, params, obs, action) - target) ** 2, -1))

        def step(i, carry):
            reward, total = carry
            u = i % minibatches
            loss, grads = jax.value_and_grad(loss_fn)(reward.params, batches.obs[u], batches.action[u], target[u])
            updates, opt_state = optimizer.update(grads, reward.opt_state, reward.params)
            return reward.replace(params=optax.apply_updates(reward.params, updates), opt_state=opt_state), total + loss

        steps = rime.warm_steps * trainer.num_train
        reward, total = jax.lax.fori_loop(0, steps, step, (with_lr(ts.reward, rcfg.lr), jnp.zeros(())))
        batches = batches.replace(reward=jnp.clip((ent - stats.mean) / (3.0 * std), -1.0, 1.0))
        return batches, reward, state, {"warm_loss": total / max(steps, 1), "warm_target": jnp.mean(target)}
