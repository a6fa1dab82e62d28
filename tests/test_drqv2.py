"""DrQ-v2's pieces against NumPy references of the original (facebookresearch/drqv2), and its update's contracts.

Tiny images (16x16) and small networks: the encoder then ends at 1x1x32 features.
"""

from __future__ import annotations

import dataclasses
import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from rebel_jax.agents.drqv2 import (
    CLAMP_EPS,
    DrQV2,
    DrQV2Config,
    PixelTransition,
    draw_shifts,
    nstep_return,
    random_shift,
    shift_images,
    std_schedule,
    task_config,
    truncated_sample,
)
from rebel_jax.agents.networks import Encoder, conv_patch_kernel_grad, encoder_output_size
from rebel_jax.config import ConfigError


def _grid_sample_reference(x: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """PyTorch's ``grid_sample`` (bilinear, zeros padding, align_corners=False) written out in NumPy.

    Args: x (N, C, H, W); grid (N, Ho, Wo, 2) normalised (x, y). Returns (N, C, Ho, Wo).
    """
    n, c, h, w = x.shape
    ix = ((grid[..., 0].astype(np.float64) + 1) * w - 1) / 2
    iy = ((grid[..., 1].astype(np.float64) + 1) * h - 1) / 2
    x0, y0 = np.floor(ix).astype(int), np.floor(iy).astype(int)
    out = np.zeros((n, c, *grid.shape[1:3]))
    for dx in (0, 1):
        for dy in (0, 1):
            xs, ys = x0 + dx, y0 + dy
            weight = (1 - np.abs(ix - xs)) * (1 - np.abs(iy - ys))
            inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
            for b in range(n):
                xb, yb = np.clip(xs[b], 0, w - 1), np.clip(ys[b], 0, h - 1)
                out[b] += np.where(inside[b], weight[b], 0.0)[None] * x[b][:, yb, xb]
    return out


def _drqv2_shift_reference(obs_nhwc: np.ndarray, shifts: np.ndarray, pad: int) -> np.ndarray:
    """``RandomShiftsAug.forward`` (drqv2.py:19-45) in NumPy, float32 grid as PyTorch builds it, given shifts."""
    x = np.transpose(obs_nhwc.astype(np.float32), (0, 3, 1, 2))
    n, _, h, _ = x.shape
    x = np.pad(x, ((0, 0), (0, 0), (pad, pad), (pad, pad)), mode="edge")  # F.pad(..., 'replicate')
    eps = np.float32(1.0 / (h + 2 * pad))
    arange = np.linspace(-1.0 + eps, 1.0 - eps, h + 2 * pad, dtype=np.float32)[:h]
    arange = np.repeat(arange[None], h, axis=0)[..., None]
    base = np.concatenate([arange, np.transpose(arange, (1, 0, 2))], axis=2)  # (h, h, 2): (x, y)
    shift = shifts.astype(np.float32)[:, None, None, :] * np.float32(2.0 / (h + 2 * pad))
    out = _grid_sample_reference(x, base[None] + shift)
    return np.transpose(out, (0, 2, 3, 1))


@pytest.mark.parametrize("pad", [1, 4])
def test_shift_images_equals_drqv2_grid_sample(pad):
    rng = np.random.default_rng(pad)
    size, channels = 12, 9
    shifts = np.array([(sx, sy) for sx in range(2 * pad + 1) for sy in range(2 * pad + 1)])
    obs = rng.integers(0, 256, (len(shifts), size, size, channels), dtype=np.uint8)
    ours = np.asarray(jax.jit(shift_images, static_argnums=2)(jnp.asarray(obs), jnp.asarray(shifts), pad))
    reference = _drqv2_shift_reference(obs, shifts, pad)
    assert ours.dtype == np.uint8
    # Float32 grid coordinates land within ~1e-5 pixel of the centres: the bilinear mix differs by < 0.01/255.
    np.testing.assert_allclose(ours.astype(np.float64), reference, atol=1e-2)
    assert not np.array_equal(ours[0], ours[-1]), "the two extreme shifts differ"


def test_random_shift_uses_its_drawn_shifts_in_range():
    pad, key = 4, jax.random.key(3)
    obs = jax.random.randint(jax.random.key(0), (256, 8, 8, 3), 0, 256).astype(jnp.uint8)
    shifts = np.asarray(draw_shifts(key, 256, pad))
    assert shifts.min() == 0 and shifts.max() == 2 * pad  # every value of [0, 2 pad] is drawn
    assert len({tuple(s) for s in shifts}) > 40  # x and y drawn independently: 81 pairs possible
    np.testing.assert_array_equal(random_shift(key, obs, pad), shift_images(obs, jnp.asarray(shifts), pad))
    np.testing.assert_array_equal(random_shift(key, obs, 0), obs)


def _nstep_loop(rewards, discounts, gamma):
    """DrQ-v2's loop (replay_buffer.py:154-160), one transition at a time."""
    out_r, out_d = [], []
    for rs, ds in zip(rewards, discounts, strict=True):
        reward, discount = 0.0, 1.0
        for r, d in zip(rs, ds, strict=True):
            reward += discount * r
            discount *= d * gamma
        out_r.append(reward)
        out_d.append(discount)
    return np.array(out_r), np.array(out_d)


@pytest.mark.parametrize("n", [1, 3, 5])
def test_nstep_return_equals_the_python_loop_with_episode_ends(n):
    rng = np.random.default_rng(n)
    rewards = rng.normal(size=(200, n))
    discounts = (rng.uniform(size=(200, n)) > 0.3).astype(np.float64)  # many terminal steps
    assert (discounts == 0).any()
    reward, discount = nstep_return(jnp.asarray(rewards), jnp.asarray(discounts), 0.9)
    expected_r, expected_d = _nstep_loop(rewards, discounts, 0.9)
    np.testing.assert_allclose(reward, expected_r, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(discount, expected_d, rtol=1e-5, atol=1e-7)


def test_std_schedule_is_drqv2_linear():
    cfg = DrQV2Config(std_init=1.0, std_final=0.1, std_steps=1000)
    steps = np.array([0, 1, 250, 999, 1000, 5000])
    mix = np.clip(steps / 1000, 0.0, 1.0)  # utils.py:135-137
    np.testing.assert_allclose(jax.vmap(lambda s: std_schedule(cfg, s))(steps), (1 - mix) * 1.0 + mix * 0.1, rtol=1e-6)


def test_truncated_sample_clips_noise_clamps_and_passes_gradient():
    mean = jnp.linspace(-0.99, 0.99, 600).reshape(100, 6)
    key = jax.random.key(0)
    clipped = truncated_sample(mean, jnp.asarray(5.0), key, 0.3)
    assert float(jnp.max(jnp.abs(clipped - mean))) <= 0.3 + 1e-6
    eps = np.asarray(jax.random.normal(key, mean.shape))
    expected = np.clip(np.asarray(mean) + np.clip(5.0 * eps, -0.3, 0.3), -1 + CLAMP_EPS, 1 - CLAMP_EPS)
    np.testing.assert_allclose(clipped, expected, atol=1e-6)
    free = truncated_sample(mean, jnp.asarray(5.0), key, None)
    assert float(jnp.max(jnp.abs(free))) <= 1.0 - CLAMP_EPS + 1e-7
    assert float(jnp.max(jnp.abs(free - mean))) > 0.3  # exploration noise is not clipped (drqv2.py:172)
    grad = jax.grad(lambda m: jnp.sum(truncated_sample(m, jnp.asarray(5.0), key, None)))(mean)
    np.testing.assert_array_equal(grad, 1.0)  # the clamp is straight-through (utils.py:112-115)


def test_encoder_shapes_follow_drqv2():
    """Four 3x3 convolutions, strides 2, 1, 1, 1, 32 channels: 84x84 -> 35x35x32 (drqv2.py:53-59)."""
    params = jax.eval_shape(Encoder().init, jax.random.key(0), jax.ShapeDtypeStruct((1, 84, 84, 9), jnp.uint8))
    kernels = [p["kernel"].shape for p in params["params"].values()]
    assert kernels == [(3, 3, 9, 32)] + [(3, 3, 32, 32)] * 3
    out = jax.eval_shape(Encoder().apply, params, jax.ShapeDtypeStruct((2, 84, 84, 9), jnp.uint8))
    assert out.shape == (2, encoder_output_size(84, 84)) == (2, 32 * 35 * 35)


def test_task_config_follows_the_task_files():
    walker, cheetah = task_config("walker_walk_pixels"), task_config("cheetah_run_pixels")
    assert (walker.nstep, walker.batch_size, walker.std_steps) == (1, 512, 100_000)
    assert (cheetah.nstep, cheetah.batch_size, cheetah.std_steps) == (3, 256, 500_000)
    assert task_config("walker_run").std_steps == 500_000


SMALL = DrQV2Config(feature_dim=8, hidden=16, batch_size=8, lr=1e-3, std_steps=100, precision="highest")
OBS_SHAPE, ACTIONS = (16, 16, 9), 2


@functools.cache
def _small():
    agent = DrQV2(SMALL, OBS_SHAPE, ACTIONS)
    return agent, jax.jit(agent.init), jax.jit(agent.update)


def _batch(seed: int, n: int = 8) -> PixelTransition:
    rng = np.random.default_rng(seed)
    return PixelTransition(
        obs=rng.integers(0, 256, (n, *OBS_SHAPE), dtype=np.uint8),
        action=rng.uniform(-1, 1, (n, ACTIONS)).astype(np.float32),
        reward=rng.normal(size=n).astype(np.float32),
        discount=np.full(n, 0.99, np.float32),
        next_obs=rng.integers(0, 256, (n, *OBS_SHAPE), dtype=np.uint8),
    )


def _close(a, b, **tol):
    jax.tree.map(lambda x, y: np.testing.assert_allclose(np.asarray(x), np.asarray(y), **tol), a, b)


def test_update_reaches_the_encoder_only_through_the_critic():
    """The update equals, step by step, DrQ-v2's order written out here: the encoder and critic move by
    Adam on the critic loss alone; the actor by the updated critic at the pre-update encoder's detached
    features; the target by tau. The actor objective does depend on the encoder (checked), so an update
    that let the actor's gradient into the encoder would fail the comparison."""
    agent, init, update = _small()
    state, _ = update(init(jax.random.key(0)), _batch(1), jax.random.key(1), jnp.int32(0))  # non-trivial Adam state
    batch, key, step = _batch(2), jax.random.key(5), jnp.int32(40)
    new, metrics = update(state, batch, key, step)
    assert int(new.steps) == 2 and all(np.isfinite(float(v)) for v in metrics.values())

    key_obs, key_next, key_critic, key_actor = jax.random.split(key, 4)
    aug = batch.replace(
        obs=random_shift(key_obs, jnp.asarray(batch.obs), SMALL.pad),
        next_obs=random_shift(key_next, jnp.asarray(batch.next_obs), SMALL.pad),
    )
    std = std_schedule(SMALL, step)
    np.testing.assert_allclose(metrics["std"], 1.0 - 0.9 * 0.4, rtol=1e-6)
    adam = optax.adam(SMALL.lr)

    def critic_loss(encoder_params, critic_params):
        context = dict(actor_params=state.actor_params, target_params=state.target_critic_params, std=std)
        return agent.critic_loss({"encoder": encoder_params, "critic": critic_params}, aug, key_critic, **context)[0]

    # The references are jitted: one compile each, not an eager compile per operation.
    g_encoder, g_critic = jax.jit(jax.grad(critic_loss, argnums=(0, 1)))(state.encoder_params, state.critic_params)
    assert float(sum(jnp.sum(jnp.abs(g)) for g in jax.tree.leaves(g_encoder))) > 0  # the critic trains the encoder
    encoder = optax.apply_updates(state.encoder_params, adam.update(g_encoder, state.encoder_opt)[0])
    critic = optax.apply_updates(state.critic_params, adam.update(g_critic, state.critic_opt)[0])
    _close(new.encoder_params, encoder, rtol=1e-5, atol=1e-6)
    _close(new.critic_params, critic, rtol=1e-5, atol=1e-6)

    features = agent.encoder.apply(state.encoder_params, aug.obs)  # pre-update encoder (drqv2.py:244, 256)

    def actor_loss(actor_params, encoder_params=state.encoder_params, detach=True):
        h = agent.encoder.apply(encoder_params, aug.obs)
        h = jax.lax.stop_gradient(h) if detach else h
        return agent.actor_loss(actor_params, h, key_actor, critic_params=critic, std=std)[0]

    g_actor = jax.jit(jax.grad(actor_loss))(state.actor_params)
    actor = optax.apply_updates(state.actor_params, adam.update(g_actor, state.actor_opt)[0])
    _close(new.actor_params, actor, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(
        metrics["actor_loss"],
        agent.actor_loss(state.actor_params, features, key_actor, critic_params=critic, std=std)[0],
        rtol=1e-5,
    )
    leak = jax.jit(jax.grad(lambda e: actor_loss(state.actor_params, e, detach=False)))(state.encoder_params)
    assert float(sum(jnp.sum(jnp.abs(g)) for g in jax.tree.leaves(leak))) > 0  # without the detach it would move
    target = jax.tree.map(lambda t, c: (1 - SMALL.tau) * t + SMALL.tau * c, state.target_critic_params, critic)
    _close(new.target_critic_params, target, rtol=1e-5, atol=1e-7)


@pytest.mark.heavy  # make test checks vmapped seeds on whole rounds (test_pixel_train.py)
def test_update_vmapped_over_seeds_equals_separate_calls():
    agent, init, update = _small()
    keys = jax.random.split(jax.random.key(0), 2)
    states = [init(k) for k in keys]
    batches = [_batch(10 + i) for i in range(2)]
    update_keys = jax.random.split(jax.random.key(9), 2)
    stack = functools.partial(jax.tree.map, lambda *xs: jnp.stack(xs))
    steps = jnp.array([3, 70], jnp.int32)
    batched, _ = jax.jit(jax.vmap(agent.update))(stack(*states), stack(*batches), update_keys, steps)
    for i in range(2):
        single, _ = update(states[i], batches[i], update_keys[i], steps[i])
        _close(jax.tree.map(lambda x, i=i: x[i], batched), single, rtol=1e-4, atol=1e-5)


def _seed_batch(seeds: int = 2):
    """(batched agent, looped agent) and the (states, batches, update keys) of ``seeds`` seeds, stacked."""
    batched = DrQV2(dataclasses.replace(SMALL, seed_loop=False), OBS_SHAPE, ACTIONS)
    looped = DrQV2(dataclasses.replace(SMALL, seed_loop=True), OBS_SHAPE, ACTIONS)
    keys = jax.random.split(jax.random.key(0), seeds)
    stack = functools.partial(jax.tree.map, lambda *xs: jnp.stack(xs))
    states = jax.jit(jax.vmap(batched.init))(keys)
    batches = stack(*[_batch(20 + i) for i in range(seeds)])
    return (batched, looped), (states, batches, jax.random.split(jax.random.key(7), seeds))


def _group_counts(stablehlo: str) -> list[int]:
    """Every convolution's ``feature_group_count`` and ``batch_group_count`` in a StableHLO module's text."""
    return [int(n) for n in re.findall(r"(?:feature|batch)_group_count = (\d+)", stablehlo)]


@pytest.mark.heavy  # make test checks whole seed-looped rounds (test_pixel_train.py)
def test_seed_loop_update_equals_the_vmapped_update():
    """``drqv2.seed_loop``: the seeds' updates one at a time give the batched update's state and metrics, with
    the agent step unbatched as in the trainer; unbatched, the looped agent is the same function."""
    (batched, looped), (states, batches, keys) = _seed_batch()
    states, _ = jax.jit(jax.vmap(batched.update, in_axes=(0, 0, 0, None)))(states, batches, keys, jnp.int32(0))
    step = jnp.int32(40)
    args = (states, batches, jax.random.split(jax.random.key(8), 2), step)
    want = jax.jit(jax.vmap(batched.update, in_axes=(0, 0, 0, None)))(*args)
    got = jax.jit(jax.vmap(looped.update, in_axes=(0, 0, 0, None)))(*args)
    _close(got, want, rtol=1e-5, atol=1e-6)
    first = jax.tree.map(lambda x: x[0], args[:3])
    _close(jax.jit(looped.update)(*first, step), jax.jit(batched.update)(*first, step), rtol=0, atol=0)


def test_seed_loop_leaves_no_grouped_convolution():
    """Batched over seeds, the encoder's convolutions (forward, input and kernel gradients) become grouped
    ones, ``feature_group_count`` = seeds; looped, every one is a plain convolution. The same number in both."""
    (batched, looped), (states, batches, keys) = _seed_batch(3)
    texts = [
        jax.jit(jax.vmap(agent.update, in_axes=(0, 0, 0, None))).lower(states, batches, keys, jnp.int32(0)).as_text()
        for agent in (batched, looped)
    ]
    grouped, plain = (_group_counts(text) for text in texts)
    assert len(grouped) == len(plain) == 2 * 15  # 8 forward, 3 input-gradient and 4 kernel-gradient convolutions
    assert max(grouped) == 3 and set(plain) == {1}


def test_seed_loop_is_a_validated_setting():
    with pytest.raises(ConfigError, match="drqv2.seed_loop"):
        DrQV2Config(seed_loop="yes").validate()
    DrQV2Config(seed_loop=False).validate()
    assert DrQV2Config().seed_loop  # on by default: measured 6.8x faster on one H100 (BENCHMARKS.md)


@pytest.mark.parametrize(
    ("stride", "padding"), [(2, "VALID"), (1, "VALID"), (2, "SAME"), (1, ((1, 0), (2, 1)))]
)  # fmt: skip
def test_patch_kernel_gradient_equals_a_numpy_loop_and_xlas(stride, padding):
    """``conv_patch_kernel_grad``: the forward and input gradient are XLA's convolution's, and the kernel
    gradient is ``sum_{b,h,w} x[b, s h + i, s w + j, c] g[b, h, w, o]`` over the padded input, written out as
    a NumPy loop. The encoder's convolutions are VALID; the padded cases check the general form."""
    key_x, key_w, key_g = jax.random.split(jax.random.key(0), 3)
    x = jax.random.normal(key_x, (3, 11, 9, 5))
    kernel = jax.random.normal(key_w, (3, 3, 5, 4))
    conv = functools.partial(
        jax.lax.conv_general_dilated, window_strides=(stride, stride), padding=padding,
        dimension_numbers=("NHWC", "HWIO", "NHWC"), precision=jax.lax.Precision.HIGHEST,
    )  # fmt: skip
    y, vjp_xla = jax.vjp(conv, x, kernel)
    got_y, vjp_patches = jax.vjp(
        lambda x, w: conv_patch_kernel_grad(x, w, (stride, stride), padding, precision=jax.lax.Precision.HIGHEST),
        x,
        kernel,
    )
    grad_out = jax.random.normal(key_g, y.shape)
    pads = (
        jax.lax.padtype_to_pads(x.shape[1:3], (3, 3), (stride, stride), padding)
        if isinstance(padding, str)
        else padding
    )
    xn = np.pad(np.asarray(x, np.float64), ((0, 0), *pads, (0, 0)))
    gn = np.asarray(grad_out, np.float64)
    loop = np.zeros(kernel.shape)
    for h in range(y.shape[1]):
        for w in range(y.shape[2]):
            patch = xn[:, stride * h : stride * h + 3, stride * w : stride * w + 3, :]  # (B, 3, 3, C)
            loop += np.einsum("bijc,bo->ijco", patch, gn[:, h, w, :])
    (want_x, want_w), (got_x, got_w) = vjp_xla(grad_out), vjp_patches(grad_out)
    np.testing.assert_array_equal(got_y, y)
    np.testing.assert_array_equal(got_x, want_x)
    np.testing.assert_allclose(np.asarray(want_w), loop, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(got_w), loop, rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="without dilation or groups"):
        conv_patch_kernel_grad(x, kernel[..., :1, :], (1, 1), "VALID", feature_group_count=5)


@pytest.mark.heavy  # make test checks the patch-product gradient itself against XLA's and a NumPy loop (above)
@pytest.mark.parametrize("seed_loop", [True, False])
def test_patch_kernel_gradients_give_the_same_update(seed_loop):
    """``drqv2.kernel_grad patches`` changes how the encoder's kernel gradients are computed, not the update:
    the seed-vmapped update (looped or batched) equals XLA's up to float rounding."""
    (_, _), (states, batches, keys) = _seed_batch()
    agents = [
        DrQV2(dataclasses.replace(SMALL, seed_loop=seed_loop, kernel_grad=grad), OBS_SHAPE, ACTIONS)
        for grad in ("xla", "patches")
    ]
    want, got = (
        jax.jit(jax.vmap(agent.update, in_axes=(0, 0, 0, None)))(states, batches, keys, jnp.int32(40))
        for agent in agents
    )
    _close(got, want, rtol=1e-4, atol=1e-6)
    with pytest.raises(ConfigError, match="drqv2.kernel_grad"):
        DrQV2Config(kernel_grad="cudnn").validate()


def test_padding_the_first_convolution_s_channels_keeps_the_encoder_s_parameters_output_and_gradients():
    """``Encoder(first_channels=16)``: the first convolution sees its 9 channels zero-padded to 16; the parameters
    (one init, the kernel keeps 9 input channels), the features and the parameters' gradients are the same."""
    obs = jax.random.randint(jax.random.key(3), (2, *OBS_SHAPE), 0, 256).astype(jnp.uint8)
    plain, padded = (Encoder(channels=4, precision="highest", first_channels=c) for c in (0, 16))
    params = plain.init(jax.random.key(0), obs)
    assert jax.tree.map(jnp.shape, padded.init(jax.random.key(0), obs)) == jax.tree.map(jnp.shape, params)
    assert params["params"]["Conv_0"]["kernel"].shape == (3, 3, OBS_SHAPE[-1], 4)

    def loss(encoder, params):
        return jnp.sum(jnp.sin(encoder.apply(params, obs)))

    (want, want_grad), (got, got_grad) = (jax.value_and_grad(loss, 1)(e, params) for e in (plain, padded))
    _close(got, want, rtol=1e-5, atol=1e-6)
    _close(got_grad, want_grad, rtol=1e-4, atol=1e-6)


@pytest.mark.heavy  # make test checks the encoder itself (above); this compiles two seed-vmapped updates
def test_padding_the_first_convolution_s_channels_gives_the_same_update():
    """``drqv2.first_channels 16``: the same update up to float rounding."""
    (_, _), (states, batches, keys) = _seed_batch()
    agents = [DrQV2(dataclasses.replace(SMALL, first_channels=c), OBS_SHAPE, ACTIONS) for c in (0, 16)]
    padded_params = jax.vmap(agents[1].init)(keys)
    assert jax.tree.map(jnp.shape, padded_params) == jax.tree.map(jnp.shape, states)  # one init for both
    want, got = (
        jax.jit(jax.vmap(agent.update, in_axes=(0, 0, 0, None)))(states, batches, keys, jnp.int32(40))
        for agent in agents
    )
    _close(got, want, rtol=1e-4, atol=1e-6)
    with pytest.raises(ConfigError, match="drqv2.first_channels"):
        DrQV2Config(first_channels=-1).validate()


def test_act_explores_around_the_deterministic_action():
    agent, init, _ = _small()
    state = init(jax.random.key(0))
    obs = jnp.asarray(_batch(3, 64).obs)
    mean = agent.act_deterministic(state, obs)
    early = agent.act(state, obs, jax.random.key(1), jnp.int32(0))
    late = agent.act(state, obs, jax.random.key(1), jnp.int32(10_000))
    assert float(jnp.max(jnp.abs(mean))) < 1.0
    # The same noise scaled by std 1.0 then 0.1, before the clamp to (-1, 1).
    eps = np.asarray(jax.random.normal(jax.random.key(1), mean.shape))
    bound = 1 - CLAMP_EPS
    np.testing.assert_allclose(early, np.clip(np.asarray(mean) + eps, -bound, bound), atol=1e-5)
    np.testing.assert_allclose(late, np.clip(np.asarray(mean) + 0.1 * eps, -bound, bound), atol=1e-5)


def test_critic_out_f32_keeps_q_off_the_bfloat16_grid():
    """``drqv2.critic_out_f32``: a bf16 critic's Q of a few units (a lying walker's is about 5) comes out of the
    output layer's bfloat16 matmul on the bfloat16 grid (steps of 1/128 to 1/32 between 1 and 8), so 4,096 inputs give a
    couple of hundred values; with the output layer in float32 they stay distinct, within a grid step of the
    rounded ones, from the same parameters."""
    from rebel_jax.agents.networks import PixelCritic

    rng = np.random.default_rng(0)
    h = jnp.asarray(rng.normal(size=(4096, 100)), jnp.float32)
    action = jnp.asarray(rng.uniform(-1, 1, (4096, 6)), jnp.float32)
    rounded, kept = PixelCritic(50, 64, 2, "bf16"), PixelCritic(50, 64, 2, "bf16", out_f32=True)
    params = rounded.init(jax.random.PRNGKey(1), h[:1], action[:1])
    assert jax.tree.structure(params) == jax.tree.structure(kept.init(jax.random.PRNGKey(1), h[:1], action[:1]))
    head = params["params"]["DoubleCritic_0"]["VmapMLP_0"]["Dense_2"]
    head["kernel"] = 0.1 * head["kernel"] + 0.2  # the matmul itself a few units, as a trained critic's
    q16 = np.asarray(jax.jit(rounded.apply)(params, h, action)[0])
    q32 = np.asarray(jax.jit(kept.apply)(params, h, action)[0])
    assert q16.min() > 1.0 and q16.max() < 4.0  # where bfloat16's step is 1/128 to 1/64
    np.testing.assert_array_equal(np.asarray(jnp.asarray(q16, jnp.bfloat16), np.float32), q16)  # on the grid
    assert len(np.unique(q16)) < 256 and len(np.unique(q32)) > 4000
    np.testing.assert_allclose(q32, q16, atol=1 / 64)
    with pytest.raises(ConfigError, match="drqv2.critic_out_f32"):
        DrQV2Config(critic_out_f32="yes").validate()
    assert not DrQV2Config().critic_out_f32  # off by default: the pixel preference runs all rounded Q
