"""The simulation behind notes/bpref_audit.md: B-Pref's running std of the kNN reward against the exact one.

Streams 9,000 batches of 1,024 gamma-distributed "distances" (coefficient of variation 0.3) whose
mean drifts geometrically over the phase, and prints the ratio of B-Pref's ``TorchRunningMeanStd``
std (BPref f3ece2e ``utils.py:211-247``, as written) to the exact running std at a few updates.
Run: ``python notes/running_std_sim.py`` (NumPy only, a few seconds).
"""

import numpy as np


def bpref(stats, x):
    mean, var, count = stats
    batch_mean, batch_var, batch_count = x.mean(), x.var(ddof=1), x.size
    delta, total = batch_mean - mean, count + batch_count
    m2 = var * count + batch_var * batch_count + delta**2 * count * batch_count / total
    return mean + delta + batch_count / total, m2 / total, total  # utils.py:240 as written


def exact(stats, x):
    mean, var, count = stats
    batch_mean, batch_var, batch_count = x.mean(), x.var(), x.size
    delta, total = batch_mean - mean, count + batch_count
    m2 = var * count + batch_var * batch_count + delta**2 * count * batch_count / total
    return mean + delta * batch_count / total, m2 / total, total


def main(updates=9000, batch=1024, cv=0.3):
    rng = np.random.default_rng(0)
    cases = [("shrink 2x", 4.0, 2.0), ("shrink 1.25x", 2.5, 2.0), ("flat", 2.0, 2.0), ("grow 1.5x", 2.0, 3.0)]
    for name, start, end in cases:
        ours, theirs, out = (0.0, 1.0, 0.0), (0.0, 1.0, 1e-4), []
        for i in range(updates):
            mean = start * (end / start) ** (i / updates)
            x = rng.gamma(1 / cv**2, mean * cv**2, size=batch)
            theirs, ours = bpref(theirs, x), exact(ours, x)
            if i + 1 in (1, 2, 10, 100, 1000, 4500, 9000):
                out.append(f"{i + 1}: {np.sqrt(theirs[1] / ours[1]):.3f}")
        print(f"{name:13s} std_bpref / std_exact at update", ", ".join(out))


if __name__ == "__main__":
    main()
