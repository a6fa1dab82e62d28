"""``env.impl='warp'``: MuJoCo Warp's physics step (through MJX) against dm_control.

The reference is dm_control 1.0.50's own environment (float64 MuJoCo). From the states of a dm_control episode
under uniformly random actions, one control step of our task with the Warp step must land where dm_control's
does, to the tolerances the JAX step meets (tests/test_envs_dm_control.py, tests/test_envs_quadruped.py). These
need warp-lang (``pip install -e '.[warp]'``), which ``make test-heavy`` installs and ``make test`` leaves out (its
import costs every process that imports mujoco.mjx about 3 s); the errors for a bad or missing impl run in both.
"""

from __future__ import annotations

import importlib.util

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_envs_quadruped import _batch  # MJX data holding dm_control's physics states

from rebel_jax.envs import dmc, make_env
from rebel_jax.run import loop
from rebel_jax.run.cli import parse

suite = pytest.importorskip("dm_control.suite")

B = 16

needs_warp = pytest.mark.skipif(importlib.util.find_spec("warp") is None, reason="needs warp-lang")
warp_step = [pytest.mark.heavy, needs_warp]


def _trajectory(task: str, seed: int = 0, skip: int = 0, n: int = B) -> dict[str, np.ndarray]:
    """``n`` states of a dm_control episode after its first ``skip`` steps (qpos, qvel, act, warm start, contacts),
    each one's action in [-1, 1], and the next observation and reward (random actions throughout)."""
    domain, name = task.split("_", 1)
    env, rng = suite.load(domain, name, task_kwargs={"random": seed}), np.random.default_rng(seed)
    env.reset()
    m, d = env.physics.model, env.physics.data
    low, high = m.actuator_ctrlrange.T
    for _ in range(skip):
        env.step(rng.uniform(low, high))
    out = {k: [] for k in ("qpos", "qvel", "act", "warm", "ncon", "action", "obs", "reward")}
    for _ in range(n):
        for key, value in (("qpos", d.qpos), ("qvel", d.qvel), ("act", d.act), ("warm", d.qacc_warmstart)):
            out[key].append(value.copy())
        out["ncon"].append(d.ncon)
        action = rng.uniform(-1, 1, m.nu).astype(np.float32)
        ts = env.step(low + (action.astype(np.float64) + 1) / 2 * (high - low))
        out["action"].append(action)
        out["obs"].append(np.concatenate([np.atleast_1d(v) for v in ts.observation.values()]))
        out["reward"].append(ts.reward)
    return {k: np.array(v) for k, v in out.items()}


def _one_step(task: str, solver: str, impl: str, ref: dict[str, np.ndarray], worlds: int | None = None):
    """One control step of ``impl`` from the reference's states and actions (a contact buffer for ``worlds``
    environments, default all of them): observations and rewards."""
    n = len(ref["action"])
    env = make_env(task, solver, impl=impl, worlds=worlds or n)
    start = jax.vmap(env.observe)(_batch(env, ref), jnp.zeros(n, jnp.int32), jnp.zeros(n))
    nxt = jax.jit(jax.vmap(env.step))(start, jnp.asarray(ref["action"], jnp.float32))
    return np.asarray(nxt.obs), np.asarray(nxt.reward)


@pytest.mark.parametrize(
    "task,max_tol",
    [
        pytest.param("walker_walk", 2e-4, marks=warp_step),
        pytest.param("cheetah_run", 2e-4, marks=warp_step),
        pytest.param("quadruped_walk", 3e-3, marks=warp_step),
    ],
)
def test_one_warp_control_step_matches_dm_control(task, max_tol):
    """With dm_control's solver settings (100 Newton, 50 line-search iterations) the Warp step lands where
    dm_control's does to float32 precision. Errors relative to max(1, |value|); measured (2-core CPU, 16 states):
    walker mean 4.7e-7 and largest 2.5e-5, cheetah 3.9e-7 and 1.1e-5, quadruped 4.1e-6 and 8.5e-4 (the JAX step:
    4.2e-7 and 1.5e-5, 3.6e-7 and 9.6e-6 on the same states)."""
    ref = _trajectory(task)
    obs, reward = _one_step(task, "dm_control", "warp", ref)
    rel = np.abs(obs - ref["obs"]) / np.maximum(1.0, np.abs(ref["obs"]))
    assert rel.mean() < 1e-5 and rel.max() < max_tol, (rel.mean(), rel.max())
    assert np.abs(reward - ref["reward"]).max() < 1e-5


@pytest.mark.heavy
@needs_warp
def test_a_batch_with_more_contacts_than_one_world_holds_keeps_them_all():
    """MuJoCo Warp keeps the contacts of all the worlds of one vmapped step in one buffer; sized for one world
    (48 rows for the walker) it drops the rest, and the step goes wrong. 64 walker states after 300 random steps
    hold more contacts than one world's buffer; with ``worlds=64`` the step still lands on dm_control's."""
    ref = _trajectory("walker_walk", skip=300, n=64)
    one_world = make_env("walker_walk", impl="warp", worlds=1)._warp_data0._impl.naconmax
    assert ref["ncon"].sum() > one_world, (ref["ncon"].sum(), one_world)  # a buffer for one world overflows
    rel = [
        np.abs(_one_step("walker_walk", "dm_control", "warp", ref, worlds)[0] - ref["obs"])
        / np.maximum(1.0, np.abs(ref["obs"]))
        for worlds in (64, 1)
    ]
    assert rel[0].mean() < 1e-5 and rel[0].max() < 2e-4, (rel[0].mean(), rel[0].max())
    assert rel[1].max() > 1e-2, rel[1].max()  # what the sized buffer prevents


@needs_warp
def test_the_trainer_sizes_the_contact_buffer_for_every_environment_of_a_device():
    """A device's vmapped step runs ``columns x (num_envs + eval_episodes)`` environments, the final evaluation
    ``columns x 2 x eval_episodes``; the trainer's Warp data holds one world's contact rows for each of the more."""
    from rebel_jax.config import Config, EnvConfig, TrainConfig
    from rebel_jax.train import Trainer

    cfg = Config(
        env=EnvConfig(task="walker_walk", num_envs=2, episode_length=20, impl="warp"),
        train=TrainConfig(total_steps=80, seed_steps=20, steps_per_round=40, eval_every=40, eval_episodes=3),
    )
    one_world = make_env("walker_walk", impl="warp", worlds=1)._warp_data0._impl.naconmax
    for columns in (1, 4):
        assert Trainer(cfg, columns=columns).env._warp_data0._impl.naconmax == columns * max(2 + 3, 2 * 3) * one_world


@needs_warp
def test_the_policy_and_random_actions_evaluated_in_one_batch_equal_each_evaluated_alone():
    """A finished run evaluates both in one program, on twice the environments of one evaluation (here more than
    a round's): with Warp's step the returns are those of the two evaluations apart, to float rounding."""
    from rebel_jax.config import Config, EnvConfig, SACConfig, TrainConfig
    from rebel_jax.train import Trainer, compiled, seed_keys

    cfg = Config(
        env=EnvConfig(task="walker_walk", num_envs=1, episode_length=20, impl="warp"),
        sac=SACConfig(hidden=16, batch_size=16),
        train=TrainConfig(total_steps=20, seed_steps=20, steps_per_round=20, eval_every=20, eval_episodes=2),
    )
    trainer = Trainer(cfg, columns=2)
    _, _, evaluate = compiled(trainer)
    keys = seed_keys(0, 2)
    params = jax.vmap(trainer.agent.init)(keys).actor_params
    apart = np.stack([np.asarray(evaluate(params, keys, flag)) for flag in (False, True)], axis=1)
    np.testing.assert_allclose(np.asarray(evaluate(params, keys, (False, True))), apart, rtol=1e-4, atol=1e-4)
    assert not np.allclose(apart[:, 0], apart[:, 1])


@pytest.mark.heavy
@needs_warp
def test_under_the_default_solver_the_warp_step_is_as_close_to_dm_control_as_the_jax_step():
    """The default solver stops after 4 Newton iterations: on the walker's contact-rich steps the JAX step then
    errs by up to 0.18 (relative; mean 1.1e-3) against dm_control's converged step, and the Warp step, whose
    iterations follow MuJoCo's own solver, by up to 0.017 (mean 8.4e-5; 2-core CPU, 16 states)."""
    ref = _trajectory("walker_walk")
    scale = np.maximum(1.0, np.abs(ref["obs"]))
    warp, jax_ = (
        np.abs(_one_step("walker_walk", "default", impl, ref)[0] - ref["obs"]) / scale for impl in ("warp", "jax")
    )
    assert warp.mean() <= jax_.mean() and warp.max() <= jax_.max(), (warp.mean(), warp.max(), jax_.mean(), jax_.max())


def test_a_bad_or_missing_impl_is_one_line(monkeypatch, capsys):
    with pytest.raises(ValueError, match="unknown physics impl 'cuda'; one of jax, warp"):
        make_env("walker_walk", impl="cuda")
    with pytest.raises(ValueError, match="^worlds must be >= 1; got 0$"):
        make_env("walker_walk", worlds=0)
    monkeypatch.setattr(dmc.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ValueError, match=r"needs the warp-lang package: pip install -e '\.\[warp\]'"):
        make_env("walker_walk", impl="warp")
    # The command line refuses it in one line, before anything is written (exit status 2).
    with pytest.raises(SystemExit) as end:
        parse(["sac", "--preset", "tiny", "--task", "walker_walk", "--impl", "warp", "--run-dir", "unused"])
    err = capsys.readouterr().err.strip()
    assert end.value.code == 2 and "needs the warp-lang package" in err and len(err.splitlines()) == 1, err


@pytest.mark.heavy
@needs_warp
def test_a_run_with_the_warp_step_starts_as_the_jax_run_does():
    """A walker run's first transitions with ``--impl warp`` are the JAX run's up to the step's rounding: the same
    reset (in JAX either way), the same random actions from the same keys, next observations within 1e-3
    (relative to max(1, |value|)) after one control step; after 2 rounds both replays hold finite values."""
    from rebel_jax.config import Config, EnvConfig, SACConfig, TrainConfig
    from rebel_jax.train import Trainer, compiled, seed_keys

    def buffer(impl: str):
        cfg = Config(
            env=EnvConfig(task="walker_walk", num_envs=2, episode_length=20, impl=impl),
            sac=SACConfig(hidden=16, batch_size=16, utd=0.5),
            train=TrainConfig(total_steps=80, seed_steps=20, steps_per_round=40, eval_every=40, eval_episodes=1),
        )
        init, round_fn, _ = compiled(Trainer(cfg))
        state = init(seed_keys(0, 1))
        for r in range(2):
            state, _ = round_fn(state, jnp.int32(r))
        return jax.device_get(state.buffer)

    warp, jax_ = buffer("warp"), buffer("jax")
    np.testing.assert_array_equal(warp.obs[0, 0], jax_.obs[0, 0])
    np.testing.assert_array_equal(warp.action[0, 0], jax_.action[0, 0])
    first = np.abs(warp.next_obs[0, 0] - jax_.next_obs[0, 0]) / np.maximum(1.0, np.abs(jax_.next_obs[0, 0]))
    assert first.max() < 1e-3, first.max()
    assert all(np.isfinite(b.next_obs).all() for b in (warp, jax_))


@pytest.mark.heavy
@needs_warp
def test_a_warp_run_compiled_beside_its_kernel_build_learns_as_one_compiled_at_its_first_round(
    tmp_path, monkeypatch, capsys
):
    """With ``--impl warp`` the command builds Warp's kernels in a thread while the round compiles ahead of its
    first call (``loop._compiled_beside_kernels``). Its logged metrics must equal, bit for bit on the CPU, those of
    the same command whose round compiles at its first call, as with the JAX step."""
    import json

    from rebel_jax.run import cli

    flags = ["sac", "--preset", "tiny", "--task", "walker_walk", "--impl", "warp", "--seeds", "1",
             "--num-envs", "2", "--episode-length", "20", "--total-steps", "80", "--seed-steps", "20",
             "--steps-per-round", "40", "--eval-every", "40", "--eval-episodes", "1", "--sac.hidden", "16",
             "--sac.batch-size", "16", "--no-progress", "--no-tensorboard", "--video-steps", "0",
             "--checkpoint-every", "0", "--no-compile-cache"]  # fmt: skip

    def logged(run_dir):
        cli.main([*flags, "--run-dir", str(run_dir)])
        rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
        return [{k: v for k, v in row.items() if k not in ("seconds", "env_steps_per_s")} for row in rows]

    ahead = logged(tmp_path / "ahead")
    assert "0/80 steps: round 1 of 2\n" in capsys.readouterr().out  # compiled before the first round's line
    monkeypatch.setattr(loop, "_compiled_beside_kernels", lambda trainer, round_fn, shapes, one: (round_fn, 0.0))
    at_first_call = logged(tmp_path / "at_first_call")
    assert len(ahead) == 2
    assert ahead == at_first_call


def test_unroll_substeps_unrolls_the_control_step_s_substep_loop():
    """``env.unroll_substeps`` (which the trainer passes on) traces the control step's physics substeps as one
    loop unrolled ``n_substeps`` times, and the plain step as a loop: read from the step's jaxpr, nothing compiled.
    That the two land in the same place is the heavy test below (its compile takes about a minute on 2 cores)."""
    from rebel_jax.config import Config, EnvConfig
    from rebel_jax.train import Trainer

    cfg = Config(env=EnvConfig(task="walker_walk", num_envs=1, episode_length=20, unroll_substeps=True))
    assert Trainer(cfg).env.unroll_substeps
    texts = []
    for unroll in (False, True):
        env = make_env("walker_walk", episode_length=20, unroll_substeps=unroll)
        state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))  # shapes only: an eager reset takes seconds
        action = jax.ShapeDtypeStruct((env.action_size,), jnp.float32)
        texts.append(str(jax.make_jaxpr(env.step)(state, action)))
    substeps = f"unroll={make_env('walker_walk').spec.n_substeps}"
    assert substeps not in texts[0] and substeps in texts[1]


@pytest.mark.heavy
@pytest.mark.parametrize("impl", ["jax", pytest.param("warp", marks=needs_warp)])
def test_a_control_step_with_its_substeps_unrolled_lands_where_the_loop_does(impl):
    """``env.unroll_substeps`` (which the trainer passes on): the same 10 physics substeps compiled without their
    loop give the looped control step's observation and reward to float32 rounding, from 4 random walker states.
    ``make test`` checks the unrolling itself (the test above)."""
    from rebel_jax.config import Config, EnvConfig
    from rebel_jax.train import Trainer

    cfg = Config(env=EnvConfig(task="walker_walk", num_envs=1, episode_length=20, impl=impl, unroll_substeps=True))
    assert Trainer(cfg).env.unroll_substeps
    envs = [make_env("walker_walk", episode_length=20, unroll_substeps=u, impl=impl, worlds=4) for u in (False, True)]
    keys = jax.random.split(jax.random.PRNGKey(5), 4)
    actions = jax.random.uniform(jax.random.PRNGKey(6), (4, envs[0].action_size), minval=-1.0, maxval=1.0)
    looped, unrolled = (jax.jit(jax.vmap(lambda k, a, e=e: e.step(e.reset(k), a)))(keys, actions) for e in envs)
    np.testing.assert_allclose(unrolled.obs, looped.obs, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(unrolled.reward, looped.reward, rtol=1e-4, atol=1e-4)
    assert not np.allclose(looped.obs[0], looped.obs[1])  # four different states
