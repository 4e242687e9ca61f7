"""The eager reference of experiments.bench_planner: the grid world and Algorithm 1 driven the way
an eager implementation drives them, a Python loop over moves and, inside, over denoising steps
(one UNet forward per step on the active episodes, as a PyTorch loop calls its module; the DDIM
update, the in-painting, psi (Dijkstra with heapq) and the world step in numpy on the host,
episode by episode)."""
from __future__ import annotations

import heapq
import time

import jax
import numpy as np

MOVES = np.array([[-1, 0], [0, 1], [1, 0], [0, -1]])
EAGER_FORWARDS = ("jit", "op")


def _cell_tokens_np(grid):
    from envs.gridworld import grammar
    from envs.gridworld.episode import OBSTACLE_CELL

    tokens = np.where(grid == OBSTACLE_CELL, grammar.OBSTACLE_ID, grammar.EMPTY_ID)
    return np.where(grid > 0, grid - 1 + grammar.OBJECT_TOKEN_OFFSET, tokens)


def _fov_np(agent, size, radius):
    rows, cols = np.arange(size)[:, None], np.arange(size)[None, :]
    return (np.abs(rows - agent[0]) <= radius) & (np.abs(cols - agent[1]) <= radius)


class EagerWorld:
    """One episode of the grid world in numpy (the same rules as envs.gridworld.env)."""

    def __init__(self, episode, config):
        from envs.gridworld import grammar
        self.grid = np.asarray(episode.grid)
        self.agent = np.asarray(episode.agent).copy()
        self.target = np.asarray(episode.target)
        self.size, self.radius, self.max_steps = config.size, config.view_radius, \
            config.max_steps
        self.seen = _fov_np(self.agent, self.size, self.radius)
        self.visited = np.zeros((self.size, self.size), bool)
        self.visited[tuple(self.agent)] = True
        self.t = 0
        self.done = bool((self.agent == self.target).all())
        self.unseen_id = grammar.UNSEEN_ID
        self.tokens_all = _cell_tokens_np(self.grid)

    def condition(self):
        from envs.gridworld import grammar
        cells = np.where(self.seen, self.tokens_all, self.unseen_id)
        agent = np.zeros_like(self.seen)
        agent[tuple(self.agent)] = True
        feats = [cells == grammar.OBSTACLE_ID, agent, self.visited, cells != self.unseen_id]
        return np.stack([cells.astype(np.float32)] + [f.astype(np.float32) for f in feats], -1)

    def psi(self, plan, path_weight=2.0, avoid_cost=50.0):
        """Dijkstra from the cell psi heads for, over cells not known to be obstacles."""
        from envs.gridworld.episode import OBSTACLE_CELL
        known_obstacle = self.seen & (self.grid == OBSTACLE_CELL)
        enter = 1.0 + path_weight * (1.0 - (np.clip(plan[..., 0], -1, 1) + 1) / 2)
        goal_map = np.where(known_obstacle, -np.inf, plan[..., 1])
        goal = np.unravel_index(np.argmax(goal_map), goal_map.shape)
        heading = goal
        if plan.shape[-1] >= 3:
            sub = np.where(known_obstacle | self.visited, -np.inf, plan[..., 2])
            heading = np.unravel_index(np.argmax(sub), sub.shape)
            if heading != goal:
                enter = enter.copy()
                enter[goal] += avoid_cost
        dist = np.full((self.size, self.size), np.inf)
        dist[heading] = 0.0
        heap = [(0.0, heading)]
        while heap:
            d, (r, c) = heapq.heappop(heap)
            if d > dist[r, c]:
                continue
            for dr, dc in MOVES:
                nr, nc = r + dr, c + dc
                if 0 <= nr < self.size and 0 <= nc < self.size and not known_obstacle[nr, nc]:
                    nd = d + enter[r, c]  # from (nr, nc) the path enters (r, c)
                    if nd < dist[nr, nc]:
                        dist[nr, nc] = nd
                        heapq.heappush(heap, (nd, (nr, nc)))
        best, move = np.inf, 0
        for a, (dr, dc) in enumerate(MOVES):
            nr, nc = self.agent[0] + dr, self.agent[1] + dc
            if 0 <= nr < self.size and 0 <= nc < self.size and not known_obstacle[nr, nc]:
                value = dist[nr, nc] + enter[nr, nc]
                if value < best:
                    best, move = value, a
        return move

    def step(self, action):
        if self.done:
            return
        from envs.gridworld.episode import OBSTACLE_CELL
        nxt = self.agent + MOVES[action]
        inside = (0 <= nxt).all() and (nxt < self.size).all()
        if inside and self.grid[tuple(nxt)] != OBSTACLE_CELL:
            self.agent = nxt
        self.seen |= _fov_np(self.agent, self.size, self.radius)
        self.visited[tuple(self.agent)] = True
        self.t += 1
        self.done = bool((self.agent == self.target).all()) or self.t >= self.max_steps


def eager_rollout(denoiser, config, episodes, num_steps: int, max_moves: int | None, seed: int,
                  forward: str = "jit"):
    """Runs the episodes move by move in Python; returns (seconds, episode-moves, calls,
    episodes done). forward: "jit" (the UNet forward compiled once) or "op" (op by op)."""
    from diffplan.schedule import timestep_sequence

    if forward not in EAGER_FORWARDS:
        raise ValueError(f"forward must be one of {EAGER_FORWARDS}, got {forward!r}")
    forward = jax.jit(denoiser.apply_fn) if forward == "jit" else denoiser.apply_fn
    n = len(episodes.tokens)
    worlds = [EagerWorld(jax.tree.map(lambda x: np.asarray(x)[i], episodes), config)
              for i in range(n)]
    tokens = np.asarray(episodes.tokens)
    ab_all = np.asarray(denoiser.schedule.alphas_cumprod)
    ts = np.asarray(timestep_sequence(denoiser.schedule.num_train_steps, num_steps))
    g = denoiser.num_gen_channels
    rng = np.random.default_rng(seed)
    # Warm up the forward at the first move's shape outside the timed region (compilation of
    # the "jit" variant, per-op dispatch caches of "op"): an eager framework pays neither.
    cond_shape = worlds[0].condition().shape
    warm = np.zeros((n,) + cond_shape[:-1] + (cond_shape[-1] + denoiser.num_gen_channels,),
                    np.float32)
    jax.block_until_ready(forward(denoiser.params, warm, np.zeros(n, np.int32), tokens))
    start, moves, calls = time.perf_counter(), 0, 0
    for move in range(config.max_steps if max_moves is None else max_moves):
        active = [i for i, w in enumerate(worlds) if not w.done]
        if not active:
            break
        cond = np.stack([worlds[i].condition() for i in active])
        x = rng.standard_normal(cond.shape[:-1] + (g,)).astype(np.float32)
        for k, t in enumerate(ts):
            a_t = ab_all[t]
            a_prev = ab_all[ts[k + 1]] if k + 1 < len(ts) else 1.0
            xt = np.concatenate([cond, x], -1)
            out = np.asarray(forward(denoiser.params, xt, np.full(len(active), t, np.int32),
                                     tokens[active]))
            x0 = out if denoiser.prediction == "x0" else (x - np.sqrt(1 - a_t) * out) / np.sqrt(
                a_t)
            x0 = np.clip(x0, -1, 1)
            eps = (x - np.sqrt(a_t) * x0) / np.sqrt(1 - a_t)
            x = np.sqrt(a_prev) * x0 + np.sqrt(1 - a_prev) * eps
            calls += len(active)
        for j, i in enumerate(active):
            worlds[i].step(worlds[i].psi(x[j]))
        moves += len(active)
    return time.perf_counter() - start, moves, calls, sum(w.done for w in worlds)
