"""The Agent interface: what the trainer asks of SAC (state tasks) and DrQ-v2 (pixel tasks).

The trainer drives either agent through these calls only (as brax's SAC trainer drives its networks through one
generic gradient step, with acting and replay shared): ``init`` a state, ``act`` (exploration) and
``mean_action`` (evaluation) on batched observations, ``update`` on a minibatch, ``reset_critic`` after PEBBLE's
unsupervised phase, ``policy`` (what a frozen evaluation episode follows) and the update ``schedule``. Every
call is pure, jittable and vmappable. :class:`rebel_jax.agents.sac.SAC` and :class:`rebel_jax.agents.drqv2.DrQV2`
implement it.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import flax.struct
import jax


@flax.struct.dataclass(frozen=True)
class UpdateSchedule:
    """When an agent updates, in vector steps ``t`` of ``num_envs`` environments.

    Attributes:
      per_step: updates at a vector step that updates.
      period: vector steps between two such steps (1: every step).
      counts_current: whether the step's own transitions count toward ``train.seed_steps`` (B-Pref's SAC updates
        once ``(t + 1) * num_envs`` steps are taken; DrQ-v2 once ``t * num_envs`` were taken before the step).
    """

    per_step: int = flax.struct.field(pytree_node=False)
    period: int = flax.struct.field(pytree_node=False)
    counts_current: bool = flax.struct.field(pytree_node=False)

    def learning(self, t: jax.Array, num_envs: int, seed_steps: int) -> jax.Array:
        """Whether vector step ``t`` (unbatched) runs updates: past the seed steps, on the period."""
        taken = (t + 1) * num_envs if self.counts_current else t * num_envs
        due = taken >= seed_steps
        return due if self.period == 1 else due & (t % self.period == 0)


@runtime_checkable
class Agent(Protocol):
    """A learner of the scanned round: SAC on state vectors or DrQ-v2 on frame stacks.

    Attributes:
      metric_names: the keys of :meth:`update`'s metrics (zeros are logged for steps without updates).
      sample_args: the keyword arguments of the replay's ``sample`` beyond the batch size (DrQ-v2's ``nstep`` and
        ``gamma``; none for SAC).
      batch_size: transitions per update.
    """

    metric_names: tuple[str, ...]
    sample_args: dict[str, Any]
    batch_size: int

    def init(self, key: jax.Array) -> Any:
        """A fresh agent state."""
        ...

    def act(self, state: Any, obs: jax.Array, key: jax.Array, step: jax.Array) -> jax.Array:
        """Exploration actions at ``obs`` (..., obs shape); ``step`` the agent steps taken (DrQ-v2's noise schedule)."""
        ...

    def policy(self, state: Any) -> Any:
        """The parameters :meth:`mean_action` reads: what a frozen evaluation episode follows."""
        ...

    def mean_action(self, policy: Any, obs: jax.Array) -> jax.Array:
        """The deterministic action of ``policy`` (:meth:`policy`) at ``obs``."""
        ...

    def update(self, state: Any, batch: Any, key: jax.Array, step: jax.Array) -> tuple[Any, dict[str, jax.Array]]:
        """One gradient update on ``batch``; returns the new state and :attr:`metric_names` metrics."""
        ...

    def reset_critic(self, state: Any, key: jax.Array) -> Any:
        """A fresh critic (and target and optimiser), the rest kept."""
        ...

    def schedule(self, num_envs: int) -> UpdateSchedule:
        """When the agent updates, with ``num_envs`` training environments."""
        ...
