"""``probe_point_pixels``: the point-mass probe seen as tiny images, for tests of the pixel trainer.

Not a dm_control task: :class:`rebel_jax.envs.PixelEnv`'s action repeat and frame stack around
:class:`~rebel_jax.envs.probe.PointProbe`, with the MuJoCo camera replaced by a pure-JAX drawing
of the point (a Gaussian spot in the red channel, the goal's spot in green). It compiles in
seconds, so the DrQ-v2 trainer's tests need no MJX model.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rebel_jax.envs.pixels import PixelEnv
from rebel_jax.envs.probe import BOUND, PointProbe, PointState


class PointCamera:
    """Draws a :class:`PointState` as a ``size x size`` RGB uint8 image (the camera interface PixelEnv uses).

    Args:
      size: image height and width in pixels.
    """

    def __init__(self, size: int):
        self.height = self.width = size

    def render(self, p: PointState) -> jax.Array:
        """(size, size, 3) uint8: the point's spot (red) and the goal's (green) on black."""
        centres = (jnp.arange(self.height) + 0.5) / self.height * 2 * BOUND - BOUND  # pixel centres in world units
        y, x = jnp.meshgrid(-centres, centres, indexing="ij")  # image rows go down, world y up
        width = 2 * BOUND / self.height

        def spot(at):
            return jnp.exp(-((x - at[0]) ** 2 + (y - at[1]) ** 2) / (2 * width**2))

        image = jnp.stack([spot(p.pos), spot(jnp.zeros(2)), jnp.zeros_like(x)], axis=-1)
        return jnp.round(255 * image).astype(jnp.uint8)


class PixelProbe(PixelEnv):
    """``probe_point`` observed as ``frames`` stacked ``size x size`` images, with action repeat.

    Args:
      episode_length: environment frames per episode (agent steps: ``ceil(episode_length / action_repeat)``).
      action_repeat, frames: as :class:`PixelEnv`.
      size: image height and width.
    """

    def __init__(self, episode_length: int = 1000, action_repeat: int = 2, frames: int = 3, size: int = 16):
        if action_repeat < 1 or frames < 1:
            raise ValueError(f"action_repeat and frames must be >= 1; got {action_repeat}, {frames}")
        self.env, self.action_repeat, self.frames = PointProbe(episode_length), action_repeat, frames
        self.camera = PointCamera(size)

    @property
    def mj_model(self):
        raise AttributeError("probe_point_pixels has no MuJoCo model")
