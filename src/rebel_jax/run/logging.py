"""Host-side sinks for round metrics: JSONL, TensorBoard and a progress bar.

Every JSON file a run writes is strict JSON: NaN and infinity are written as ``null``
(:func:`strict`), and each record carries a ``status``.
"""

from __future__ import annotations

import json
import math
import os
import pathlib

import numpy as np
from tqdm import tqdm


def _jsonable(x):
    """A number or (nested) list with None for NaN and infinity."""
    arr = np.asarray(x)
    if arr.ndim == 0:
        v = arr.item()
        return None if isinstance(v, float) and not math.isfinite(v) else v
    return [_jsonable(v) for v in arr]


def strict(obj):
    """``obj`` with every array, NumPy scalar, NaN and infinity made strict-JSON (non-finite -> None)."""
    if isinstance(obj, dict):
        return {str(k): strict(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [strict(v) for v in obj]
    if isinstance(obj, np.ndarray | np.generic | float):
        return _jsonable(obj)
    return obj


def dumps(obj, **kwargs) -> str:
    """Strict JSON text of ``obj`` (see :func:`strict`)."""
    return json.dumps(strict(obj), allow_nan=False, **kwargs)


def write_json(path: pathlib.Path, obj, strict_json: bool = True) -> None:
    """Writes ``obj`` as JSON, atomically (a kill leaves the old file or the new one, never half of one).

    ``strict_json``: NaN and infinity as null (:func:`dumps`); False keeps them as ``NaN`` /
    ``Infinity`` (for config.json, where ``teacher.beta = inf`` is a value, not a failure).
    """
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(dumps(obj, indent=1) if strict_json else json.dumps(obj, indent=1))
    os.replace(tmp, path)


class RunLogger:
    """Writes one JSONL record and one TensorBoard point per round, and drives a progress bar.

    Args:
      run_dir: the run's directory (``metrics.jsonl`` and ``tb/`` go there).
      total_steps: environment steps per seed of the whole run (for the bar and the ETA).
      start_steps: steps already done (when resuming).
      progress: show the tqdm bar; without it, print one plain line per round (for logs, where a bar's carriage
        returns would pile up).
      tensorboard: write TensorBoard event files.
      names: a name for each column (seed), used to report divergence; default ``seed i``.
    """

    def __init__(
        self,
        run_dir: pathlib.Path,
        total_steps: int,
        start_steps: int = 0,
        progress=True,
        tensorboard=True,
        names: list[str] | None = None,
    ):
        self.path = run_dir / "metrics.jsonl"
        self.jsonl = open(self.path, "a")  # noqa: SIM115 - closed in close()
        self.tb = None
        if tensorboard:
            from tensorboardX import SummaryWriter

            self.tb = SummaryWriter(str(run_dir / "tb"))
        self.names = names
        self.progress, self.total_steps = progress, total_steps
        self.bar = tqdm(total=total_steps, initial=start_steps, unit="step", disable=not progress, dynamic_ncols=True)

    def write(self, env_steps: int, metrics: dict[str, np.ndarray], extra: dict[str, float]) -> None:
        """Logs per-seed ``metrics`` (arrays over seeds) and scalar ``extra`` at ``env_steps``.

        ``metrics["diverged"]`` (per seed, non-zero: NaN or infinity in its losses, parameters
        or returns; see ``Trainer.round``) sets the record's ``status`` to ``"diverged"`` and
        every ``*_mean`` to null, as a mean over the other seeds would pass for the run's.
        Otherwise ``*_mean`` is the mean over the seeds whose value is defined (a session metric
        is NaN for a seed without a session, a return before the first episode ends).
        """
        metrics = dict(metrics)
        diverged = np.asarray(metrics.pop("diverged", np.zeros(0)), float).reshape(-1) > 0
        record = {"env_steps": env_steps, **extra, "status": "diverged" if diverged.any() else "ok"}
        for k, v in metrics.items():
            record[k] = _jsonable(v)
            defined = np.any(np.isfinite(v)) and not diverged.any()
            record[k + "_mean"] = _jsonable(np.nanmean(v)) if defined else None
        if diverged.size:
            record["diverged"] = diverged.tolist()
        try:
            self.jsonl.write(dumps(record) + "\n")
            self.jsonl.flush()
        except OSError as err:  # disk full: name the file
            raise OSError(err.errno, err.strerror, str(self.path)) from err
        if self.tb is not None:
            for k, v in record.items():
                if isinstance(v, int | float) and not isinstance(v, bool) and k != "env_steps":
                    self.tb.add_scalar(k.removesuffix("_mean"), v, env_steps)
        postfix = {"steps/s": f"{extra.get('env_steps_per_s', 0):,.0f}"}
        if record.get("eval_return_mean") is not None:
            postfix["eval"] = f"{record['eval_return_mean']:.1f}"
        if record.get("labels_used_mean") is not None:
            postfix["labels"] = f"{record['labels_used_mean']:.0f}"
        if diverged.any():
            names = self.names or [f"seed {i}" for i in range(diverged.size)]
            postfix["DIVERGED"] = ", ".join(names[i] for i in np.flatnonzero(diverged))
        self.bar.set_postfix(postfix, refresh=False)
        self.bar.update(env_steps - self.bar.n)
        if not self.progress:
            fields = "  ".join(f"{k} {v}" for k, v in postfix.items())
            print(f"{env_steps:,}/{self.total_steps:,} steps  {fields}", flush=True)

    def close(self) -> None:
        self.bar.close()
        if self.tb is not None:
            self.tb.close()
        try:
            self.jsonl.close()  # writes what a failed write left buffered, and closes the file whatever happens
        except OSError as err:
            raise OSError(err.errno, err.strerror, str(self.path)) from err
