"""Host-side sinks for round metrics: JSONL, TensorBoard and a progress bar."""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
from tqdm import tqdm


def _jsonable(x):
    arr = np.asarray(x)
    if arr.ndim == 0:
        v = arr.item()
        return None if isinstance(v, float) and math.isnan(v) else v
    return [_jsonable(v) for v in arr]


class RunLogger:
    """Writes one JSONL record and one TensorBoard point per round, and drives a progress bar.

    Args:
      run_dir: the run's directory (``metrics.jsonl`` and ``tb/`` go there).
      total_steps: environment steps per seed of the whole run (for the bar and the ETA).
      start_steps: steps already done (when resuming).
      progress: show the tqdm bar.
      tensorboard: write TensorBoard event files.
    """

    def __init__(self, run_dir: pathlib.Path, total_steps: int, start_steps: int = 0, progress=True, tensorboard=True):
        self.jsonl = open(run_dir / "metrics.jsonl", "a")  # noqa: SIM115 - closed in close()
        self.tb = None
        if tensorboard:
            from tensorboardX import SummaryWriter

            self.tb = SummaryWriter(str(run_dir / "tb"))
        self.bar = tqdm(total=total_steps, initial=start_steps, unit="step", disable=not progress, dynamic_ncols=True)

    def write(self, env_steps: int, metrics: dict[str, np.ndarray], extra: dict[str, float]) -> None:
        """Logs per-seed ``metrics`` (arrays over seeds) and scalar ``extra`` at ``env_steps``."""
        record = {"env_steps": env_steps, **extra}
        for k, v in metrics.items():
            record[k] = _jsonable(v)
            record[k + "_mean"] = _jsonable(np.nanmean(v)) if np.any(np.isfinite(v)) else None
        self.jsonl.write(json.dumps(record) + "\n")
        self.jsonl.flush()
        if self.tb is not None:
            for k, v in record.items():
                if isinstance(v, int | float) and k != "env_steps":
                    self.tb.add_scalar(k.removesuffix("_mean"), v, env_steps)
        postfix = {"steps/s": f"{extra.get('env_steps_per_s', 0):,.0f}"}
        if record.get("eval_return_mean") is not None:
            postfix["eval"] = f"{record['eval_return_mean']:.1f}"
        if record.get("labels_used_mean") is not None:
            postfix["labels"] = f"{record['labels_used_mean']:.0f}"
        self.bar.set_postfix(postfix, refresh=False)
        self.bar.update(env_steps - self.bar.n)

    def close(self) -> None:
        self.bar.close()
        self.jsonl.close()
        if self.tb is not None:
            self.tb.close()
