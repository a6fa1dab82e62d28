"""The pure-JAX camera next to MuJoCo's own renderer (dm_control's camera 0), on a CPU.

Usage:
  MUJOCO_GL=egl python benchmarks/render_fidelity.py [--tasks walker_walk cheetah_run] [--states 8] [--size 84]

For states every 10 control steps along a random-action dm_control trajectory, renders camera 0
with dm_control (MuJoCo's OpenGL renderer; EGL on a CPU needs Mesa, ``make gl``) and with
``rebel_jax.envs.render`` on our model, and reports the share of pixels whose geom id agrees with
MuJoCo's segmentation render and the mean absolute RGB difference (of 255), with shadows and
reflection on and off. Writes ``benchmarks/results/render_fidelity.json`` and, per task, a PNG of
the first four states (rows: ours | MuJoCo's | 4 x |difference|) to ``results/render_<task>.png``.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import pathlib  # noqa: E402
import sys  # noqa: E402

import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from dm_control import suite  # noqa: E402
from mujoco import mjx  # noqa: E402
from PIL import Image  # noqa: E402

from rebel_jax.envs import render  # noqa: E402
from rebel_jax.envs.dmc import mj_model  # noqa: E402

ROOT = pathlib.Path(__file__).parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "render_fidelity.json"


def compare(task: str, states: int, size: int, seed: int = 0) -> tuple[dict, np.ndarray]:
    domain, name = task.split("_")
    env = suite.load(domain, name, task_kwargs={"random": seed})
    env.reset()
    m = mj_model(task)
    d = mujoco.MjData(m)
    cams = {
        "shaded": render.make_camera(m, 0, size, size),
        "no_shadows_no_reflection": render.make_camera(m, 0, size, size, shadows=False, reflections=False),
    }
    fns = {k: jax.jit(c.render) for k, c in cams.items()}
    segment = jax.jit(cams["shaded"].segment)
    rng = np.random.default_rng(seed)
    agree, err, panels = [], {k: [] for k in cams}, []
    for _ in range(states):
        for _ in range(10):
            env.step(rng.uniform(-1, 1, 6))
        physics = env.physics
        ref = physics.render(size, size, camera_id=0).astype(np.int16)
        ref_seg = physics.render(size, size, camera_id=0, segmentation=True)[..., 0]
        d.qpos[:] = physics.data.qpos
        mujoco.mj_forward(m, d)
        dx = mjx.put_data(m, d)
        agree.append(float((np.asarray(segment(dx)[0]) == ref_seg).mean()))
        for k, fn in fns.items():
            ours = np.asarray(fn(dx)).astype(np.int16)
            err[k].append(float(np.abs(ours - ref).mean()))
            if k == "shaded" and len(panels) < 4:
                diff = np.clip(4 * np.abs(ours - ref), 0, 255)
                panels.append(np.concatenate([ours, ref, diff], 1).astype(np.uint8))
    summary = {
        "task": task,
        "size": size,
        "states": states,
        "geom_id_agreement_min": min(agree),
        "geom_id_agreement_mean": float(np.mean(agree)),
        **{f"rgb_mean_abs_diff_{k}": float(np.mean(v)) for k, v in err.items()},
        "rgb_mean_abs_diff_shaded_max": max(err["shaded"]),
    }
    return summary, np.concatenate(panels, 0)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["walker_walk", "cheetah_run"])
    parser.add_argument("--states", type=int, default=8)
    parser.add_argument("--size", type=int, default=84)
    args = parser.parse_args(argv)
    rows = []
    for task in args.tasks:
        summary, image = compare(task, args.states, args.size)
        summary.update(date=datetime.date.today().isoformat(), command=" ".join(["python"] + sys.argv))
        print(json.dumps(summary))
        rows.append(summary)
        png = ROOT / "results" / f"render_{task}.png"
        Image.fromarray(image).resize((image.shape[1] * 3, image.shape[0] * 3), Image.NEAREST).save(png)
    RESULTS.write_text(json.dumps({"rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
