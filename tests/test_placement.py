"""``placement.per_device``: each device runs the one-device program on its block of seeds.

Runs in a subprocess with 2 forced CPU devices (the test process has one). The reference is the
same jitted function called on each block alone, on one device, so the comparison is exact.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import textwrap

TWO_DEVICES = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    from rebel_jax.train import placement

    assert jax.device_count() == 2

    def step(state, scale):
        # Seed-vmapped: a loop whose length depends on the seed, a zero-size leaf, an unbatched argument.
        def one(s):
            n = jax.lax.while_loop(lambda c: c[0] < s["x"][0], lambda c: (c[0] + 1, c[1] * 1.5), (0.0, s["x"]))
            return {"x": n[1] * scale + jnp.sin(s["x"]).sum(), "empty": s["empty"] + 1.0}
        return jax.vmap(one)(state), jnp.arange(state["x"].shape[0]) * scale

    sharding = placement.seed_sharding(4)
    state = {"x": jnp.arange(12.0).reshape(4, 3) / 3.0, "empty": jnp.zeros((4, 0))}
    program = placement.per_device(step, sharding, batched=(True, False), donate_argnums=(0,))
    sharded_in = placement.shard_seeds(state, sharding)
    # Under tracing it is the function itself: the same shapes, nothing placed.
    shapes = jax.eval_shape(program, sharded_in, 2.0)
    assert jax.tree.map(lambda s: s.shape, shapes) == jax.tree.map(lambda x: x.shape, step(state, 2.0))
    out, counts = program(sharded_in, jnp.float32(2.0))
    assert all(x.is_deleted() for x in jax.tree.leaves(sharded_in) if x.size), "the state was not donated"
    for x in jax.tree.leaves((out, counts)):
        assert x.sharding.is_equivalent_to(sharding, x.ndim), x.sharding
        assert [s.data.shape[0] for s in x.addressable_shards] == [2, 2]
    alone = jax.jit(step)
    first, c0 = alone(jax.tree.map(lambda x: x[:2], state), 2.0)
    second, c1 = alone(jax.tree.map(lambda x: x[2:], state), 2.0)
    np.testing.assert_array_equal(np.asarray(out["x"]), np.concatenate([first["x"], second["x"]]))
    np.testing.assert_array_equal(np.asarray(counts), np.concatenate([c0, c1]))  # each block counts from 0
    assert out["empty"].shape == (4, 0)
    # A NumPy state is placed first; a second call reuses the compiled programs.
    again, _ = program(jax.tree.map(np.asarray, state), 2.0)
    np.testing.assert_array_equal(np.asarray(again["x"]), np.asarray(out["x"]))
    print("ok")
    """
)


def test_each_device_runs_its_block_as_the_one_device_program():
    root = pathlib.Path(__file__).resolve().parents[1]
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    env = dict(os.environ, XLA_FLAGS=flags, PYTHONPATH=f"{root}/src")
    done = subprocess.run([sys.executable, "-c", TWO_DEVICES], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-3000:]


def test_padded_columns_round_up_to_the_devices_and_repeat_the_last_column():
    import jax.numpy as jnp
    import numpy as np

    from rebel_jax.train import placement

    assert [placement.padded_columns(c, 2) for c in (1, 2, 3, 4, 5)] == [2, 2, 4, 4, 6]
    assert [placement.padded_columns(5, d) for d in (1, 3, 4, 5, 8)] == [5, 6, 8, 5, 8]
    tree = {"key": jnp.arange(6).reshape(3, 2), "lam": jnp.array([0.0, 0.1, 0.2])}
    padded = placement.pad_columns(tree, 5)
    reference = {k: np.concatenate([np.asarray(v), np.repeat(np.asarray(v)[-1:], 2, axis=0)]) for k, v in tree.items()}
    for k in tree:  # a NumPy reference: the last row twice more
        np.testing.assert_array_equal(np.asarray(padded[k]), reference[k])
    assert placement.pad_columns(tree, 3) is not None and placement.pad_columns(tree, 3)["key"] is tree["key"]
