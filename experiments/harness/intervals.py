"""95% intervals of the success rates the experiments report (in percent)."""
from __future__ import annotations

import numpy as np


def wilson_interval(successes: float, n: float, z: float = 1.959964) -> list[float]:
    """95% Wilson score interval of a rate, in percent (n may be an effective, non-integer
    sample size)."""
    if n <= 0:
        return [0.0, 100.0]
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [100.0 * max(0.0, centre - half), 100.0 * min(1.0, centre + half)]


def clustered_interval(successes, trials, z: float = 1.959964) -> list[float]:
    """95% interval, in percent, of the pooled rate sum(successes) / sum(trials) when the
    trials of one cluster (the constraints of one episode) are not independent.

    successes, trials: (n,) per-cluster counts. Wilson's interval at Kish's effective sample
    size sum(trials) / deff, the design effect deff being the cluster-robust variance of the
    ratio, sum((s_i - p t_i)^2) / sum(t)^2, over the binomial one, p (1 - p) / sum(t), and at
    least 1. Where the rate is 0 or 100% the correlation cannot be estimated and deff is the
    mean cluster size (every cluster counted as one trial). Clusters of one trial give
    Wilson's interval."""
    s = np.asarray(successes, np.float64).ravel()
    t = np.asarray(trials, np.float64).ravel()
    if s.shape != t.shape or (s < 0).any() or (s > t).any():
        raise ValueError("clustered_interval: need 0 <= successes <= trials, one per cluster")
    s, t = s[t > 0], t[t > 0]
    total = t.sum()
    if total == 0:
        return [0.0, 100.0]
    p = s.sum() / total
    if p <= 0.0 or p >= 1.0:
        deff = total / len(t)
    else:
        deff = max(1.0, float(((s - p * t) ** 2).sum() / total) / (p * (1 - p)))
    n_eff = total / min(deff, total)
    return wilson_interval(p * n_eff, n_eff, z)


def rate_interval(rate: float, n: int) -> list[float]:
    """The 95% Wilson interval of a rate in percent measured over n trials."""
    return wilson_interval(int(round(rate * n / 100)), n)
