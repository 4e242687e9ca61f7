"""Metrics any world can use, in plain numpy (what a world computes from its own arrays lives in
``envs/<world>/metrics.py``).

- precision / recall / F1 of boolean maps, pooled over episodes;
- SPL (Anderson et al. 2018): success weighted by path length;
- Wilson score intervals of rates, and intervals of rates over clustered trials.
"""
from __future__ import annotations

import numpy as np


def precision_recall_f1(predicted, expert):
    """Pooled precision, recall, F1 in percent of bool maps predicted vs expert (N, H, W)."""
    predicted = np.asarray(predicted, bool)
    expert = np.asarray(expert, bool)
    tp = float(np.sum(predicted & expert))
    n_pred = float(np.sum(predicted))
    n_true = float(np.sum(expert))
    precision = 100.0 * tp / n_pred if n_pred else 0.0
    recall = 100.0 * tp / n_true if n_true else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return precision, recall, f1
