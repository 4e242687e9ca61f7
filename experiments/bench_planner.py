"""Planner throughput: the jitted, vmapped rollout (Algorithm 1 under one jit) against the same
model and algorithm driven the way an eager implementation drives it.

    python -m experiments.bench_planner [--batch-sizes 1,64,256] [--json bench_planner.json]

Rows, all with the same denoiser (the shipped checkpoint by default), P-MO2G episodes of one
seed, paper-style on-the-fly planning (--num-steps DDIM steps from noise before every move):
  * jitted: ``jax.jit(diffplan.rollout)`` over B episodes in one call (one lax.while_loop over
    moves, the sampler's lax.scan over steps, psi and the world step inside): episodes/s,
    denoiser calls/s, compile seconds (lowering + XLA compilation, persistent cache off), and
    the process's peak resident memory after the row (ru_maxrss; rows run by increasing B, so
    it is the peak up to that batch).
  * eager: a Python loop over moves and, inside, over denoising steps: one UNet forward per
    step on the active episodes (as a PyTorch loop calls its module), the DDIM update, the
    in-painting, psi (Dijkstra with heapq) and the world step in numpy on the host, episode by
    episode. Two variants (--eager-forward): "jit", the UNet forward compiled by XLA once
    (the strongest eager loop: the same fused kernels as the jitted rollout), and "op", the
    flax module applied op by op as an eager framework runs it (no jax.jit anywhere). For
    B > --eager-full episodes it runs --eager-moves moves and extrapolates episodes/s from the
    measured seconds per episode-move and the mean episode length of the jitted run (said in
    the row's "note"; the first moves have every episode active, so this favours the eager
    loop).
  * forward-bound: the bare jitted UNet forward at the rollout's sub-batch size, timed alone:
    denoiser calls/s it sustains, and the episodes/s a rollout spending the jitted row's
    calls per episode would reach if it did nothing but those forwards (a ceiling for any
    implementation of this algorithm with this model on this machine).
  * speedup: jitted / eager episodes/s at each batch size, measured in the same run;
    "of bound": jitted episodes/s over the forward-bound's.

JSON: {"experiment": "bench_planner", "episodes", "seed", "rows": [...], "device",
"jax_version"}; a table on stdout.
"""
from __future__ import annotations

import argparse
import heapq
import os
import resource
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MOVES = np.array([[-1, 0], [0, 1], [1, 0], [0, -1]])
EAGER_FORWARDS = ("jit", "op")


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2


# ------------------------------------------------------------------ the eager reference

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


# ------------------------------------------------------------------ the jitted rollout

def jitted_rollout(planner, task, episodes, keys, chunk=None):
    """(compile seconds, run seconds, Rollout) of one jitted call over the episodes (chunk:
    the denoiser sub-batch, see diffplan.rollout)."""
    from diffplan.rollouts import rollout

    fn = jax.jit(lambda p, k, e: rollout(task, p, k, e, chunk=chunk))
    t0 = time.perf_counter()
    compiled = fn.lower(planner, keys, episodes).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(planner, keys, episodes))
    return compile_s, time.perf_counter() - t0, out


def forward_calls_per_second(denoiser, plan_shape, batch: int, repeats: int = 5) -> float:
    """Denoiser calls/s of the bare jitted UNet forward at this batch on plans of plan_shape
    (H, W, G) (median of repeats)."""
    from diffplan.planner import MIN_SUB_BATCH

    b = max(batch, MIN_SUB_BATCH)
    h, w = plan_shape[:2]
    x = jnp.zeros((b, h, w, denoiser.num_cond_channels + denoiser.num_gen_channels))
    t = jnp.full((b,), denoiser.schedule.num_train_steps // 2, jnp.int32)
    tokens = jnp.zeros((b, denoiser.model_config.max_tokens), jnp.int32)
    fn = jax.jit(denoiser.apply_fn)
    jax.block_until_ready(fn(denoiser.params, x, t, tokens))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(denoiser.params, x, t, tokens))
        times.append(time.perf_counter() - t0)
    # Rows computed for padding below MIN_SUB_BATCH are not calls.
    return batch / float(np.median(times))


def format_table(rows) -> str:
    """Rows as text; "jitted/this": the jitted row's episodes/s over this row's (for the bound
    row: the fraction of the ceiling the jitted rollout reaches)."""
    head = (f"{'rollout':<9} {'batch':>5} {'episodes/s':>11} {'calls/s':>10} {'compile s':>10} "
            f"{'peak GB':>8} {'jitted/this':>11}  note")
    lines = [head, "-" * len(head)]
    for r in rows:
        def f(key, fmt):
            v = r.get(key)
            return fmt.format(v) if v is not None else "-".rjust(len(fmt.format(0)))
        ratio = None if r["method"] == "jitted" else (
            r.get("of_bound") if r["method"] == "bound" else r.get("speedup"))
        ratio_s = "-".rjust(11) if ratio is None else f"{ratio:>10.2f}x"
        lines.append(f"{r['method']:<9} {r['batch']:>5} {f('episodes_per_second', '{:>11.2f}')} "
                     f"{f('calls_per_second', '{:>10.0f}')} {f('compile_seconds', '{:>10.1f}')} "
                     f"{f('peak_rss_gb', '{:>8.2f}')} {ratio_s}  {r.get('note', '')}")
    return "\n".join(lines)


def build_parser():
    p = argparse.ArgumentParser(prog="python -m experiments.bench_planner",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=os.path.join(REPO, "checkpoints", "compile_gridworld"),
                   help="the denoiser (default: the shipped one)")
    p.add_argument("--batch-sizes", default="1,64,256", help="comma-separated batch sizes")
    p.add_argument("--num-steps", type=int, default=10,
                   help="DDIM steps per plan (paper-style on-the-fly; default 10)")
    p.add_argument("--seed", type=int, default=3000, help="episode seed (default 3000)")
    p.add_argument("--eager-full", type=int, default=8,
                   help="run the eager loop to the end for batches up to this size (default 8)")
    p.add_argument("--eager-moves", type=int, default=3,
                   help="moves of the eager loop for larger batches (default 3)")
    p.add_argument("--eager-forward", default="jit,op",
                   help="comma-separated eager variants: 'jit' (the UNet forward compiled "
                        "once) and/or 'op' (op by op, no jax.jit) (default jit,op)")
    p.add_argument("--chunk", type=int, default=None,
                   help="denoiser sub-batch of the jitted rollout (default: the library's, "
                        "diffplan.rollouts.default_chunk: max(32, B // 8))")
    p.add_argument("--json", metavar="PATH", help="write the rows as JSON")
    return p


def main(argv=None) -> int:
    from diffplan import Planner, PlannerConfig, load_denoiser
    from diffplan.jax_cache import enable_compilation_cache
    from diffplan.rollouts import default_chunk
    from experiments import cli
    from experiments.compile_common import ROLLOUT_STREAM, SPECS, eval_episodes

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        sizes = [int(x) for x in args.batch_sizes.split(",") if x.strip()]
    except ValueError:
        parser.error(f"--batch-sizes must be comma-separated integers, got {args.batch_sizes!r}")
    if not sizes or min(sizes) < 1:
        parser.error("--batch-sizes must be >= 1")
    cli.check_at_least(parser, "--num-steps", args.num_steps, 1)
    cli.check_at_least(parser, "--eager-moves", args.eager_moves, 1)
    cli.check_at_least(parser, "--chunk", args.chunk, 1)
    forwards = [f.strip() for f in args.eager_forward.split(",") if f.strip()]
    bad = [f for f in forwards if f not in EAGER_FORWARDS]
    if bad or not forwards:
        parser.error(f"--eager-forward must be comma-separated of {EAGER_FORWARDS}, got "
                     f"{args.eager_forward!r}")
    cli.check_output_file(parser, "--json", args.json)
    try:
        den = load_denoiser(args.checkpoint)
    except (FileNotFoundError, ValueError) as e:
        parser.error(f"--checkpoint: {e}")
    enable_compilation_cache()
    # Compile times are measured, so the persistent cache must not serve the rollout.
    jax.config.update("jax_enable_compilation_cache", False)
    spec = SPECS["p_mo2g"]
    task = spec.task(den.num_gen_channels)
    config = PlannerConfig(mode="on_the_fly", num_steps=args.num_steps)
    planner = Planner(den, config)
    episodes_all = eval_episodes(spec.grid_config(), max(sizes), args.seed)
    root = jax.random.fold_in(jax.random.PRNGKey(args.seed), ROLLOUT_STREAM)
    rows = []
    for b in sorted(sizes):
        eps = jax.tree.map(lambda x: x[:b], episodes_all)
        keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(b))
        compile_s, run_s, out = jitted_rollout(planner, task, eps, keys, args.chunk)
        steps = np.asarray(out.steps)
        calls = int(np.sum(np.asarray(out.denoiser_calls)))
        jit_row = {"method": "jitted", "batch": b, "episodes_per_second": b / run_s,
                   "calls_per_second": calls / run_s, "compile_seconds": compile_s,
                   "run_seconds": run_s, "peak_rss_gb": _peak_rss_gb(),
                   "mean_moves": float(steps.mean()), "max_moves": int(steps.max()),
                   "calls_per_episode": calls / b,
                   "success": float(np.mean(np.asarray(out.final_state.success)))}
        sub_batch = min(b, args.chunk or default_chunk(b))
        bound_cps = forward_calls_per_second(den, planner.plan_shape, sub_batch)
        bound_row = {"method": "bound", "batch": b, "calls_per_second": bound_cps,
                     "episodes_per_second": bound_cps / (calls / b),
                     "note": f"bare jitted forward at batch {sub_batch}, "
                             f"{calls / b:.1f} calls/episode"}
        jit_row["of_bound"] = bound_row["of_bound"] = (jit_row["episodes_per_second"]
                                                       / bound_row["episodes_per_second"])
        group = [jit_row, bound_row]
        full = b <= args.eager_full
        for forward in forwards:
            seconds, moves, e_calls, done = eager_rollout(
                den, spec.grid_config(), eps, args.num_steps, None if full else args.eager_moves,
                args.seed, forward)
            if full:
                eager_eps = b / seconds
                note = "all moves"
            else:
                # seconds per episode-move, times the mean episode length of the jitted run.
                eager_eps = 1.0 / (seconds / moves * float(steps.mean()))
                note = (f"{args.eager_moves} moves measured, extrapolated with "
                        f"{steps.mean():.1f} moves/episode")
            eager_row = {"method": f"eager-{forward}", "batch": b,
                         "episodes_per_second": eager_eps, "calls_per_second": e_calls / seconds,
                         "run_seconds": seconds, "measured_episode_moves": moves,
                         "speedup": jit_row["episodes_per_second"] / eager_eps,
                         "note": f"forward {'compiled once' if forward == 'jit' else 'op by op'}"
                                 f"; {note}"}
            group.append(eager_row)
        # Kept for readers of earlier JSON: the jitted row's speed-up over the first variant.
        jit_row["speedup"] = group[2]["speedup"]
        rows += group
        print("\n".join(format_table(group).splitlines()[2:]), file=sys.stderr)
    print(format_table(rows))
    result = {"experiment": "bench_planner", "episodes": max(sizes), "seed": args.seed,
              "num_steps": args.num_steps, "chunk": args.chunk,
              "eager_forwards": forwards, "checkpoint": os.path.relpath(args.checkpoint, REPO),
              "rows": rows, "device": str(jax.devices()[0]), "jax_version": jax.__version__,
              "cpu_count": os.cpu_count()}
    if args.json:
        cli.write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
