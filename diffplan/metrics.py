"""Metrics any world can use, in plain numpy (what a world computes from its own arrays lives in
``envs/<world>/metrics.py``).

- precision / recall / F1 of boolean maps, pooled over episodes;
- SPL (Anderson et al. 2018): success weighted by path length (moves in the grid world,
  placements in the Kuka world).
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


def spl(success, agent_moves, expert_moves) -> float:
    """Success weighted by path length in [0, 1]: mean of S_i * l_i / max(p_i, l_i).
    success bool (N,); agent_moves p int (N,); expert_moves l int (N,) (>= 0; an episode with
    l = 0 counts 1 if it succeeded)."""
    success = np.asarray(success, bool)
    p = np.asarray(agent_moves, np.float64)
    l = np.asarray(expert_moves, np.float64)
    ratio = np.where(l > 0, l / np.maximum(np.maximum(p, l), 1e-9), 1.0)
    return float(np.mean(np.where(success, ratio, 0.0)))
