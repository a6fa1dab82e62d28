"""Where one seed's DrQ-v2 update spends its time: its parts timed alone (the pixel throughput target).

    python benchmarks/drqv2_parts.py --precision bf16        # 84x84, walker's batch 512 (n-step 1)
    python benchmarks/drqv2_parts.py --size 16 --batch-size 8 --repeats 2 --per-call 2   # a CPU check

One row per part and precision, the median milliseconds of one call (``ms``) over ``--repeats`` calls of a
jitted ``lax.scan`` of ``--per-call`` calls after a warm-up call:

- ``update``: the whole :meth:`DrQV2.update` of one seed (the trainer's, looped over seeds);
- ``critic_grad``: the critic loss and its gradient (encoder of ``obs`` with gradient, of ``next_obs``
  without, target critic, both critics), the first half of the update;
- ``shift``: the random shifts of ``obs`` and ``next_obs``;
- ``encoder_forward`` (``obs`` alone) and ``encoder_grad`` (its forward and the gradient of the features'
  sum with respect to the encoder's parameters);
- per convolution ``k`` of the encoder (1-4, at its input's shape in the update): ``conv{k}_forward``,
  ``conv{k}_input_grad`` (the gradient with respect to its input: the backward pass to the layer below;
  not needed for conv 1) and ``conv{k}_kernel_grad`` (with respect to its kernel, XLA's own
  convolution), and ``conv{k}_kernel_grad_patches``: the same kernel gradient as one matrix product of
  the layer's 3x3 input patches with the output gradient (``networks.conv_patch_kernel_grad``, the setting
  ``drqv2.kernel_grad patches``; tested against XLA's and a NumPy loop in ``tests/test_drqv2.py``).

Every call perturbs its input by the loop's carry so that XLA cannot hoist the work out of the loop; the
perturbation is one elementwise pass over the input. Rows merge into ``benchmarks/results/drqv2_parts.json``.
``REBEL_JAX_GIT_COMMIT`` names the commit where the tree was copied without its history.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib

import jax
import jax.numpy as jnp
from drqv2_update import FRAMES, WALKER_ACTIONS, random_batch
from timing import median_seconds, merge_rows, provenance

from rebel_jax.agents.drqv2 import DrQV2, DrQV2Config, random_shift, task_config
from rebel_jax.agents.networks import CONV_LAYOUT, conv_patch_kernel_grad, dense_kwargs

RESULTS = pathlib.Path(__file__).parent / "results" / "drqv2_parts.json"


def conv(x: jax.Array, kernel: jax.Array, stride: int, precision: str, patches: bool = False) -> jax.Array:
    """One encoder convolution (3x3, no padding) in the encoder's compute dtype, as ``nn.Conv`` runs it;
    with ``patches``, :func:`rebel_jax.agents.networks.conv_patch_kernel_grad` (``drqv2.kernel_grad patches``)."""
    kw = dense_kwargs(precision)
    x, kernel = x.astype(kw["dtype"]), kernel.astype(kw["dtype"])
    if patches:
        return conv_patch_kernel_grad(x, kernel, (stride, stride), "VALID", precision=kw["precision"])
    return jax.lax.conv_general_dilated(
        x, kernel, (stride, stride), "VALID", dimension_numbers=CONV_LAYOUT, precision=kw["precision"]
    )


def _looped(fn, per_call: int):
    """``(carry, key) -> carry``: ``per_call`` calls of ``fn(eps)``, each folding its output into ``carry``."""

    def run(carry, key):
        def body(carry, _):
            out = fn(carry * 1e-30)
            leaves = jax.tree.leaves(out)
            return carry + sum(jnp.sum(leaf).astype(jnp.float32) for leaf in leaves) * 0.0 + 1e-30, None

        return jax.lax.scan(body, carry, None, length=per_call)[0]

    return jax.jit(run)


def parts(cfg: DrQV2Config, size: int) -> dict:
    """Part name -> ``fn(eps)``, every input fixed and perturbed by the scalar ``eps``."""
    agent = DrQV2(cfg, (size, size, 3 * FRAMES), WALKER_ACTIONS)
    key_init, key_batch, key_update, key_next_shift = jax.random.split(jax.random.PRNGKey(0), 4)
    state = jax.jit(agent.init)(key_init)
    batch = random_batch(key_batch, (cfg.batch_size,), size, cfg.gamma)
    step = jnp.int32(10_000)
    nudge = lambda tree, eps: jax.tree.map(lambda p: p + eps.astype(p.dtype), tree)

    def update(eps):
        return agent.update(state.replace(critic_params=nudge(state.critic_params, eps)), batch, key_update, step)[0]

    def critic_grad(eps):
        params = {"encoder": nudge(state.encoder_params, eps), "critic": state.critic_params}
        context = dict(actor_params=state.actor_params, target_params=state.target_critic_params, std=jnp.float32(0.2))
        return jax.grad(agent.critic_loss, has_aux=True)(params, batch, key_update, **context)[0]

    def shift(eps):
        obs = (batch.obs.astype(jnp.float32) + eps).astype(jnp.uint8)
        return random_shift(key_update, obs, cfg.pad), random_shift(key_next_shift, batch.next_obs, cfg.pad)

    def encoder_forward(eps):
        return agent.encoder.apply(nudge(state.encoder_params, eps), batch.obs)

    def encoder_grad(eps):
        return jax.grad(lambda p: jnp.sum(agent.encoder.apply(p, batch.obs)))(nudge(state.encoder_params, eps))

    out = {
        "update": update,
        "critic_grad": critic_grad,
        "shift": shift,
        "encoder_forward": encoder_forward,
        "encoder_grad": encoder_grad,
    }
    # Each convolution's input in the update: the scaled frames, then the ReLU outputs of the layer below.
    kernels = [state.encoder_params["params"][f"Conv_{k}"]["kernel"] for k in range(4)]
    x = batch.obs.astype(jnp.float32) / 255.0 - 0.5
    for k, (kernel, stride) in enumerate(zip(kernels, (2, 1, 1, 1), strict=True), start=1):
        y = conv(x, kernel, stride, cfg.precision)
        grad_out = jnp.ones_like(y) / y.size

        def forward(eps, x=x, w=kernel, s=stride):
            return conv(x + eps, w, s, cfg.precision)

        def input_grad(eps, x=x, w=kernel, s=stride, g=grad_out):
            return jax.vjp(lambda x: conv(x, w, s, cfg.precision), x + eps)[1](g)

        def kernel_grad(eps, x=x, w=kernel, s=stride, g=grad_out):
            return jax.vjp(lambda w: conv(x + eps, w, s, cfg.precision), w)[1](g)

        def patches_grad(eps, x=x, w=kernel, s=stride, g=grad_out):
            return jax.vjp(lambda w: conv(x + eps, w, s, cfg.precision, patches=True), w)[1](g)

        out |= {f"conv{k}_forward": forward, f"conv{k}_kernel_grad": kernel_grad}
        out |= {f"conv{k}_kernel_grad_patches": patches_grad}
        if k > 1:
            out[f"conv{k}_input_grad"] = input_grad
        x = jax.nn.relu(y.astype(jnp.float32))
    return out


def rows(args):
    base = task_config("walker_walk", DrQV2Config(precision=args.precision))
    cfg = dataclasses.replace(base, batch_size=args.batch_size or base.batch_size)
    for name, fn in parts(cfg, args.size).items():
        if args.parts and name not in args.parts:
            continue
        sec = median_seconds(_looped(fn, args.per_call), jnp.float32(0.0), args.per_call, args.repeats)
        row = {
            **provenance(),
            "size": args.size,
            "batch_size": cfg.batch_size,
            "precision": cfg.precision,
            "part": name,
            "ms": sec * 1e3,
        }
        print(json.dumps(row), flush=True)
        yield row


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=84, help="image height and width")
    p.add_argument("--batch-size", type=int, default=0, help="transitions per update (0: walker's 512)")
    p.add_argument("--precision", default="bf16", choices=["tf32", "highest", "bf16"])
    p.add_argument("--parts", nargs="*", default=[], help="only these parts (default: all)")
    p.add_argument("--per-call", type=int, default=20, help="calls per timed jitted loop")
    p.add_argument("--repeats", type=int, default=5, help="timed loops per row")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    merge_rows(args.out, rows(args), ("device", "commit", "size", "batch_size", "precision", "part"))


if __name__ == "__main__":
    main()
