"""The README's Python API example runs as written, and ``api.make_train`` is the command line's run.

``make_train`` scans the trainer's ``round`` over the rounds inside one program; the command line calls the
jitted round once per round. Both are the same computation, so their metrics agree to float tolerance.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_preference_train import MICRO_PEBBLE

from rebel_jax import api, train

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def _python_api_example() -> str:
    section = README.read_text().split("## Python API", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(blocks) == 1, "the README's Python API section has one python block"
    return blocks[0]


def test_the_readme_example_runs_and_prints_each_seeds_returns_and_labels():
    example = _python_api_example()
    assert len(example.strip().splitlines()) <= 15
    printed = io.StringIO()
    scope: dict = {}
    with contextlib.redirect_stdout(printed):
        exec(compile(example, str(README), "exec"), scope)  # noqa: S102 - the README's own code
    cfg, metrics = scope["cfg"], scope["metrics"]
    assert metrics["eval_return"].shape == (2, cfg.train.num_rounds)
    assert np.all(np.asarray(metrics["labels_used"])[:, -1] > 0)
    assert str(np.asarray(metrics["labels_used"])[:, -1]) in printed.getvalue()


@pytest.mark.heavy  # make test-heavy: two more compiles of the run; the test above covers make_train's program
def test_make_train_equals_the_round_by_round_run():
    cfg = dataclasses.replace(MICRO_PEBBLE, train=dataclasses.replace(MICRO_PEBBLE.train, total_steps=120))
    keys = train.seed_keys(3, 2)
    _, scanned = jax.jit(jax.vmap(api.make_train(cfg)))(keys)
    init, round_fn, _ = train.compiled(api.make_trainer(cfg))
    state = init(keys)
    for r in range(cfg.train.num_rounds):
        state, metrics = round_fn(state, jnp.int32(r))
        for name in ("eval_return", "train_return", "critic_loss", "labels_used"):
            np.testing.assert_allclose(scanned[name][:, r], metrics[name], rtol=1e-4, atol=1e-5, err_msg=name)
