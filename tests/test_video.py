"""Video files and the run-directory config round trip of ``rebel_jax.video``."""

from __future__ import annotations

import dataclasses
import json

import imageio.v3 as iio
import numpy as np
import pytest

from rebel_jax import video
from rebel_jax.config import PRESETS


def test_gif_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    # Few distinct colours, so that the GIF palette keeps them exactly.
    palette = rng.integers(0, 256, (8, 3), dtype=np.uint8)
    frames = palette[rng.integers(0, 8, (5, 12, 10))]
    path = video.write(tmp_path / "clip.gif", frames, fps=25)
    back = iio.imread(path, index=None)
    assert back.shape[:3] == (5, 12, 10)
    np.testing.assert_array_equal(back[..., :3], frames)


def test_bad_frames_and_formats_raise(tmp_path):
    frames = np.zeros((2, 4, 4, 3), np.uint8)
    with pytest.raises(ValueError, match="uint8"):
        video.write(tmp_path / "a.gif", frames.astype(np.float32), fps=10)
    with pytest.raises(ValueError, match="T >= 1"):
        video.write(tmp_path / "a.gif", frames[:0], fps=10)
    with pytest.raises(ValueError, match=".avi"):
        video.write(tmp_path / "a.avi", frames, fps=10)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_config_read_back_from_a_run_directory_equals_the_original(preset):
    cfg = PRESETS[preset]
    cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, task="cheetah_run"))
    text = json.dumps(dataclasses.asdict(cfg))  # what cli._write_meta writes as config.json
    assert video._from_dict(type(cfg), json.loads(text)) == cfg
