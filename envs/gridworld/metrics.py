"""Grid-world metrics (docs/DESIGN.md), computed on what the agent executed, in plain numpy.

They take only the arrays written to a trajectories file (contract 2), so anyone can recompute
every number from what the agent actually did.

- SR: percent of episodes whose agent ends on the target cell (within the move budget).
- SR_ordered: percent of episodes that reached the reference before the target (an episode ends
  on the target, so: success and the reference cell occurs in the executed trajectory).
- GD: Euclidean distance from the final agent cell to the target, averaged over episodes.
- path precision / recall / F1: executed cells vs expert-path cells (true positive = an executed
  cell on the expert path), pooled over episodes, in percent.
- plan metrics: the same precision / recall / F1 on the first predicted path map (path channel
  > 0), the paper's one-shot plan numbers.
- SPL: success weighted by path length (Anderson et al. 2018), mean over episodes of
  S_i * l_i / max(p_i, l_i), in [0, 1]: l_i the expert's moves (the shortest path with the
  whole map known, via the reference where there is one), p_i the agent's moves (collisions
  included: a bump costs a move), S_i success (SR_ordered's where there is a reference).
- per phrasing: SR (and SR_ordered) over the episodes of each instruction template.
"""
from __future__ import annotations

import numpy as np

from diffplan.metrics import precision_recall_f1, spl


def executed_cells(positions, steps, size: int):
    """bool (N, size, size): cells the agent stood on. positions int (N, T+1, 2), steps int (N,)."""
    positions = np.asarray(positions)
    steps = np.asarray(steps)
    n, t1, _ = positions.shape
    valid = np.arange(t1)[None, :] <= steps[:, None]
    mask = np.zeros((n, size, size), bool)
    ep = np.broadcast_to(np.arange(n)[:, None], (n, t1))
    mask[ep[valid], positions[..., 0][valid], positions[..., 1][valid]] = True
    return mask


def final_positions(positions, steps):
    """int (N, 2): the agent's cell after its last move."""
    positions = np.asarray(positions)
    return positions[np.arange(len(positions)), np.asarray(steps)]


def trajectory_metrics(positions, steps, target, expert_path, reference=None,
                       expert_length=None):
    """Metrics of executed trajectories (see module docstring).

    Args: positions int (N, T+1, 2); steps int (N,); target int (N, 2); expert_path bool
    (N, H, W); reference int (N, 2) with (-1, -1) where none, or None; expert_length int (N,)
    the expert's moves, or None.
    Returns a dict: SR, GD, path_precision, path_recall, path_f1, mean_steps (and SR_ordered
    when references are given, SPL when expert lengths are).
    """
    positions = np.asarray(positions)
    steps = np.asarray(steps)
    target = np.asarray(target)
    size = np.asarray(expert_path).shape[-1]
    final = final_positions(positions, steps)
    success = np.all(final == target, axis=-1)
    gd = np.sqrt(np.sum((final - target).astype(np.float64) ** 2, axis=-1))
    precision, recall, f1 = precision_recall_f1(executed_cells(positions, steps, size),
                                                expert_path)
    out = {
        "SR": 100.0 * float(np.mean(success)),
        "GD": float(np.mean(gd)),
        "path_precision": precision,
        "path_recall": recall,
        "path_f1": f1,
        "mean_steps": float(np.mean(steps)),
    }
    if reference is not None:
        reference = np.asarray(reference)
        has_ref = np.all(reference >= 0, axis=-1)
        t1 = positions.shape[1]
        valid = np.arange(t1)[None, :] <= steps[:, None]
        on_ref = np.all(positions == reference[:, None, :], axis=-1) & valid
        ordered = success & (np.any(on_ref, axis=1) | ~has_ref)
        out["SR_ordered"] = 100.0 * float(np.mean(ordered))
        success = ordered
    if expert_length is not None:
        out["SPL"] = spl(success, steps, expert_length)
    return out


def plan_metrics(first_plan_path, expert_path):
    """Precision / recall / F1 (percent) of the first predicted path map (float (N, H, W), a
    cell is on the path where the value > 0) against the expert path."""
    precision, recall, f1 = precision_recall_f1(np.asarray(first_plan_path) > 0, expert_path)
    return {"plan_precision": precision, "plan_recall": recall, "plan_f1": f1}


def per_phrasing_metrics(positions, steps, episodes, has_reference: bool) -> list[dict]:
    """SR (and SR_ordered) over the episodes of each instruction template that occurs, so that
    one phrasing the planner misreads shows instead of being averaged away.

    Args: positions int (N, T+1, 2) and steps int (N,) as in :func:`trajectory_metrics`;
    episodes an Episode batch (N,) (its template, target, reference, expert_path).
    Returns [{"template": int, "phrasing": str (slots as {ref} / {target} / {dir}),
    "episodes": int, "SR": float (and "SR_ordered" with a reference)}] by template index.
    """
    from envs.gridworld import grammar

    positions, steps = np.asarray(positions), np.asarray(steps)
    templates = np.asarray(episodes.template)
    rows = []
    for t in np.unique(templates):
        keep = templates == t
        part = trajectory_metrics(positions[keep], steps[keep], np.asarray(episodes.target)[keep],
                                  np.asarray(episodes.expert_path)[keep],
                                  np.asarray(episodes.reference)[keep] if has_reference
                                  else None)
        rows.append({"template": int(t),
                     "phrasing": grammar.all_phrasings(has_reference)[int(t)],
                     "episodes": int(keep.sum()),
                     **{k: part[k] for k in ("SR", "SR_ordered") if k in part}})
    return rows
