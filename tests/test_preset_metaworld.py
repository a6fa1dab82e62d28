"""The ``paper_metaworld`` preset against B-Pref's Meta-World command (rll-research/BPref@f3ece2e,
``scripts/button_press/10000/oracle/run_PEBBLE.sh:2``), flag by flag, and the CLI's choice of it for a Meta-World
task."""

from __future__ import annotations

import dataclasses
import math

import pytest

from rebel_jax.config import PRESETS, ConfigError, EnvConfig
from rebel_jax.envs import metaworld
from rebel_jax.run.cli_args import default_preset

BPREF_PEBBLE_METAWORLD = (
    "python train_PEBBLE.py env=metaworld_button-press-v2 seed=$seed agent.params.actor_lr=0.0003 "
    "agent.params.critic_lr=0.0003 gradient_update=1 activation=tanh num_unsup_steps=9000 num_train_steps=1000000 "
    "agent.params.batch_size=512 double_q_critic.params.hidden_dim=256 double_q_critic.params.hidden_depth=3 "
    "diag_gaussian_actor.params.hidden_dim=256 diag_gaussian_actor.params.hidden_depth=3 reward_update=10  "
    "num_interact=5000 max_feedback=10000 reward_batch=50 reward_update=10 feed_type=$1 teacher_beta=-1 "
    "teacher_gamma=1 teacher_eps_mistake=0 teacher_eps_skip=0 teacher_eps_equal=0"
)
"""B-Pref's command line, as its script writes it."""

FIELDS = {
    "agent.params.actor_lr": lambda c: c.sac.actor_lr,
    "agent.params.critic_lr": lambda c: c.sac.critic_lr,
    "gradient_update": lambda c: c.sac.utd,
    "num_unsup_steps": lambda c: c.pretrain.steps,
    "num_train_steps": lambda c: c.train.total_steps,
    "agent.params.batch_size": lambda c: c.sac.batch_size,
    "double_q_critic.params.hidden_dim": lambda c: c.sac.hidden,
    "double_q_critic.params.hidden_depth": lambda c: c.sac.depth,
    "diag_gaussian_actor.params.hidden_dim": lambda c: c.sac.hidden,
    "diag_gaussian_actor.params.hidden_depth": lambda c: c.sac.depth,
    "reward_update": lambda c: c.reward.max_epochs,
    "num_interact": lambda c: c.feedback.interval,
    "max_feedback": lambda c: c.feedback.labels,
    "reward_batch": lambda c: c.feedback.queries,
    "teacher_eps_mistake": lambda c: c.teacher.eps_mistake,
    "teacher_eps_skip": lambda c: c.teacher.eps_skip,
    "teacher_eps_equal": lambda c: c.teacher.eps_equal,
    "teacher_gamma": lambda c: c.teacher.gamma,
    # teacher_beta <= 0 is B-Pref's rational teacher (rll-research/BPref@f3ece2e:reward_model.py, get_label's
    # ``if self.teacher_beta > 0``), our beta = inf.
    "teacher_beta": lambda c: -1.0 if math.isinf(c.teacher.beta) else c.teacher.beta,
}
"""B-Pref's setting -> the preset's field that holds it."""


def bpref_settings(command: str) -> dict[str, float]:
    """The numeric ``key=value`` settings of a B-Pref command line."""
    pairs = (word.split("=", 1) for word in command.split() if "=" in word)
    out = {}
    for key, value in pairs:
        try:
            out[key] = float(value)
        except ValueError:
            continue
    return out


@pytest.mark.parametrize("key", sorted(FIELDS))
def test_paper_metaworld_is_bprefs_command(key):
    cfg = PRESETS["paper_metaworld"]
    cfg.validate()
    assert float(FIELDS[key](cfg)) == pytest.approx(bpref_settings(BPREF_PEBBLE_METAWORLD)[key])


def test_every_numeric_setting_of_the_command_is_checked():
    assert set(bpref_settings(BPREF_PEBBLE_METAWORLD)) - {"seed"} == set(FIELDS)


def test_paper_metaworld_runs_meta_world_s_episodes():
    # B-Pref's make_metaworld_env wraps the env in TimeLimit(..., env.max_path_length), 500 steps.
    assert PRESETS["paper_metaworld"].env.episode_length == metaworld.EPISODE_LENGTH == 500


def test_a_metaworld_task_defaults_to_the_metaworld_preset():
    assert default_preset("metaworld_drawer-open") == "paper_metaworld"
    assert default_preset("walker_walk") == "paper"


def test_a_meta_world_episode_longer_than_meta_world_s_is_refused():
    with pytest.raises(ConfigError, match="Meta-World ends its episodes at 500 steps"):
        dataclasses.replace(PRESETS["paper"], env=EnvConfig(task="metaworld_drawer-open")).validate()
