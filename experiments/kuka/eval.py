"""The Kuka world's evaluation: seeded episodes of a Table 2 column, the planner (diffplan.rollout
on ``envs.kuka.task.KukaTask``) or the scripted expert run on them under MJX physics, success on
the final physical block poses (contract 4), the column's results row pooled over seeds, and
the states file (the table: experiments.kuka.tables).

Episode i of seed S is ``generate(fold_in(PRNGKey(S), i), spec)`` in every column (so the
columns share their initial layouts); the planner's keys: experiments.harness.core.planner_keys.
"""
from __future__ import annotations

import functools
import os

import jax
import numpy as np

from envs.kuka.env import SETTLE_SECONDS
from experiments.harness.core import per_seed_values, planner_keys, rollout_fn, seeded_episodes
from experiments.harness.intervals import clustered_interval


def generate_episodes(spec, n: int, seed: int, batch: int):
    """Episodes 0..n-1 of a seed (numpy Episode with a leading (n,) axis), in calls of batch."""
    from envs.kuka.episode import generate

    return seeded_episodes(generate, spec, n, seed, batch)


def _physical(states) -> dict:
    """The final physical state of a batch of env.States as numpy arrays."""
    from envs.kuka import physics

    return {"block_pos": jax.vmap(physics.block_pos)(states.data),
            "block_quat": jax.vmap(physics.block_quat)(states.data),
            "held": jax.vmap(physics.held)(states.data),
            "placements": states.t, "done": states.done}


def at_rest(states, settle: float) -> dict:
    """The final physical state after ``settle`` simulated seconds at rest (env.settle; 0: as
    released), with the poses as released kept as released_pos / released_held."""
    from envs.kuka import env

    released = _physical(states)
    if settle > 0:
        states = env.settle_batch(states, np.float32(settle))
    out = _physical(states)
    return dict(out, released_pos=released["block_pos"], released_held=released["held"])


def batches(episodes, batch: int, bar, run_batch) -> dict:
    """run_batch(idx, chunk) -> dict of arrays over every episode, in calls of `batch` (the
    last padded with copies of its last episode, dropped afterwards); concatenated numpy (the
    outputs gathered from every process's devices when split over them)."""
    from diffplan.distributed import gather

    n = episodes.block_xy.shape[0]
    outs = []
    for lo in range(0, n, batch):
        idx = np.arange(lo, min(n, lo + batch))
        idx = np.concatenate([idx, np.full(batch - len(idx), idx[-1])])
        out = gather(run_batch(idx, jax.tree.map(lambda x: x[idx], episodes)))
        keep = min(batch, n - lo)
        outs.append({k: np.asarray(v)[:keep] for k, v in out.items()})
        if bar is not None:
            bar.update(keep)
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


def run_expert(episodes, batch: int, bar=None, settle: float = SETTLE_SECONDS):
    """The scripted expert on every episode, in calls of `batch` (the last padded), the blocks
    then left to settle for ``settle`` simulated seconds.

    Returns dict of numpy arrays: block_pos (n, 4, 3), block_quat (n, 4, 4), held (n, 4) at
    rest; released_pos (n, 4, 3), released_held (n, 4) as the last placement left them;
    placements (n,), done (n,), frames (n, MAX_STEPS, F, nq)."""
    from envs.kuka import env, expert

    def run_batch(idx, chunk):
        states, frames = expert.run_expert(env.reset_batch(chunk))
        return dict(at_rest(states, settle), frames=frames)

    return batches(episodes, batch, bar, run_batch)


def run_planner(task, planner, episodes, seed: int, batch: int, bar=None, run=None,
                settle: float = SETTLE_SECONDS, reader=None):
    """The planner on every episode with diffplan.rollout, in calls of `batch` episodes (the
    last padded to the compiled size), the blocks then left to settle for ``settle`` simulated
    seconds. Returns the final physical states (as :func:`run_expert`, without frames) plus
    denoiser_calls, num_plans and unread (n,). run: the jitted (planner, keys, episodes, token)
    -> Rollout (default harness.rollout_fn(task, mesh=the devices' mesh)). With several
    devices (of one process or of all, diffplan.distributed) a call holds `batch` episodes per
    device, each device rolling out and settling its own. reader: (ReaderConfig, params) of a reader
    that restates each instruction canonically first (envs.kuka.reader.read_episodes; unread:
    the episodes whose instruction it could not restate, not acted on).

    Not the slot pool (diffplan.rollout_stream): its jitted program, with a physics reset and
    a pick-and-place in one loop body, needed more than 7 GB of memory to compile here (the
    batched rollout ~4.8 GB); a batch ends with its slowest episode, at most 6 placements."""
    from diffplan.sharding import PerDevice, data_mesh
    from envs.kuka.reader import read_episodes

    mesh = data_mesh()
    run = rollout_fn(task, mesh=mesh) if run is None else run
    settled = functools.partial(at_rest, settle=settle)
    if mesh.size > 1:
        settled = PerDevice(settled, mesh, replicated_argnums=())

    def run_batch(idx, chunk):
        chunk, unread = read_episodes(reader, chunk)
        out = run(planner, planner_keys(seed, idx), chunk, 0)
        return dict(settled(out.final_state), denoiser_calls=out.denoiser_calls,
                    num_plans=out.num_plans, unread=unread)

    return batches(episodes, batch * mesh.size, bar, run_batch)


def constraint_success(episodes, final, pos_key: str = "block_pos", held_key: str = "held"):
    """(strict, diffuser) bool (n, 3): each instructed constraint holds at the end (padding
    rows False), by contract 4's check and by Diffuser's (the poses final[pos_key],
    final[held_key]); none in an episode a reader could not read (final["unread"])."""
    from envs.kuka import metrics

    pos, held = final[pos_key], final[held_key]
    constraints = np.asarray(episodes.constraints)
    out = []
    for check in (metrics.on_matrix, metrics.diffuser_on_matrix):
        out.append(np.asarray(jax.vmap(lambda p, h, c: metrics.satisfied(check(p, h), c))(
            pos, held, constraints)))
    return tuple(ok & ~np.asarray(final.get("unread", False), bool)[..., None] for ok in out)


def episode_counts(episodes, final):
    """(successes, constraints) int (n,): each episode's instructed constraints that hold
    (strict, contract 4) and its number of instructed constraints (the clusters of
    :func:`add_intervals`)."""
    strict, _ = constraint_success(episodes, final)
    valid = np.asarray(episodes.constraints)[..., 0] >= 0
    return (strict & valid).sum(-1), valid.sum(-1)


def _towers(final):
    """bool (n,): the four blocks stand in one tower (metrics.single_tower) in final."""
    from envs.kuka import metrics

    return np.asarray(jax.vmap(metrics.single_tower)(final["block_pos"], final["held"]))


def placement_spl(episodes, final, strict, tower) -> float:
    """SPL over placements (diffplan.metrics.spl): S_i the episode's success (every instructed
    constraint holds, strict (n, 3), and, for stacking, one tower of four, tower (n,)), l_i
    the placements needed (the expert's goal relations: every block starts on the floor), p_i
    the placements used."""
    from diffplan.metrics import spl

    valid = np.asarray(episodes.constraints)[..., 0] >= 0
    success = (strict | ~valid).all(-1) & (tower | ~np.asarray(episodes.tower, bool))
    needed = (np.asarray(episodes.goal)[..., 0] >= 0).sum(-1)
    return spl(success, final["placements"], needed)


def column_metrics(method: str, column: str, episodes, final, seconds: float) -> dict:
    """A results row from the final physical states (numpy). settle_changed: the instructed
    constraints whose strict success changed while the blocks settled (0 without released
    poses); unread_episodes: the episodes a reader could not read (each one failed)."""
    from envs.kuka import metrics

    strict, loose = constraint_success(episodes, final)
    valid = np.asarray(episodes.constraints)[..., 0] >= 0
    tower = _towers(final)
    is_stacking = bool(np.asarray(episodes.tower).all())
    changed = 0
    if "released_pos" in final:
        released, _ = constraint_success(episodes, final, "released_pos", "released_held")
        changed = int(((released != strict) & valid).sum())
    row = {
        "method": method, "column": column, "episodes": int(len(valid)),
        "constraints": int(valid.sum()),
        "SR": 100.0 * strict.sum() / valid.sum(),
        "SR_diffuser": 100.0 * loose.sum() / valid.sum(),
        "all_constraints": 100.0 * np.mean((strict | ~valid).all(-1)),
        "tower": 100.0 * tower.mean() if is_stacking else None,
        "placements_per_episode": float(np.mean(final["placements"])),
        "SPL": placement_spl(episodes, final, strict, tower),
        "settle_changed": changed, "unread_episodes": int(np.sum(final.get("unread", 0))),
        "seconds": float(seconds),
    }
    phrasings = metrics.per_phrasing_metrics(episodes.tokens, episodes.constraints, strict)
    if len(phrasings) > 1:
        row["per_phrasing"] = phrasings
    if "denoiser_calls" in final:
        row["denoiser_calls_per_episode"] = float(np.mean(final["denoiser_calls"]))
        row["plans_per_episode"] = float(np.mean(final["num_plans"]))
    return row


def add_intervals(row: dict, counts, per_seed: dict | None = None) -> None:
    """Adds SR_ci95 (the 95% interval of the pooled constraint success rate over episodes, the
    constraints of one episode one cluster: intervals.clustered_interval of counts, the
    (successes, constraints) of :func:`episode_counts`) and, given the per-seed rows, per-seed
    SR and SPL to a row."""
    row["SR_ci95"] = clustered_interval(*counts)
    if per_seed is not None:
        row["per_seed"] = per_seed_values(per_seed, ("SR", "SR_diffuser", "SPL", "seconds"))


def pooled_row(method: str, rows, seconds: float) -> dict:
    """The main row: every column's constraints pooled (the contract-4 SR of the states file)."""
    total = sum(r["constraints"] for r in rows)
    episodes = sum(r["episodes"] for r in rows)

    def mean(key, weight):
        values = [(r[key], r[weight]) for r in rows if r.get(key) is not None]
        if not values:
            return None
        return sum(v * w for v, w in values) / sum(w for _, w in values)

    row = {"method": method, "column": "all", "episodes": episodes, "constraints": total,
           "SR": mean("SR", "constraints"), "SR_diffuser": mean("SR_diffuser", "constraints"),
           "all_constraints": mean("all_constraints", "episodes"),
           "tower": mean("tower", "episodes"),
           "placements_per_episode": mean("placements_per_episode", "episodes"),
           "SPL": mean("SPL", "episodes"),
           **{k: sum(r.get(k, 0) for r in rows) for k in ("settle_changed", "unread_episodes")},
           "seconds": float(seconds)}
    if any("denoiser_calls_per_episode" in r for r in rows):
        row["denoiser_calls_per_episode"] = mean("denoiser_calls_per_episode", "episodes")
    return row


def write_states(path: str, parts) -> None:
    """Contract 4: the final physics state of every episode (parts: (episodes, final) pairs)."""
    from envs.kuka import scene
    from envs.kuka.sentences import episode_texts

    arrays = {
        "block_pos": np.concatenate([f["block_pos"] for _, f in parts]).astype(np.float32),
        "block_quat": np.concatenate([f["block_quat"] for _, f in parts]).astype(np.float32),
        "held": np.concatenate([f["held"] for _, f in parts]).astype(bool),
        "block_half_size": np.asarray(scene.BLOCK_HALF_SIZE, np.float32),
        "constraints": np.concatenate([np.asarray(e.constraints) for e, _ in parts]).astype(
            np.int32),
        # Rendered from the phrasings: the tokens of a natural-language episode are canonical.
        "instruction": np.array([t for e, _ in parts for t in episode_texts(e)]),
    }
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(path, **arrays)
