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
import os
import resource
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.bench.common import LEGENDS
from experiments.bench.eager import EAGER_FORWARDS, eager_rollout
from experiments.harness.tables import legend

PLANNER_ROWS = (("jitted", "jax.jit(diffplan.rollout), one call"),
                ("eager-jit / eager-op", "a Python loop over moves and steps, the UNet forward "
                                         "jitted / op by op"),
                ("bound", "the bare jitted UNet forward: the ceiling"))
"""What the rows are (the table's legend)."""

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2


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
    from experiments.harness import cli
    from experiments.gridworld.eval import eval_episodes
    from experiments.gridworld.spec import SPECS
    from experiments.harness.core import planner_keys

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
    rows = []
    for b in sorted(sizes):
        eps = jax.tree.map(lambda x: x[:b], episodes_all)
        keys = planner_keys(args.seed, np.arange(b))
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
    print(legend(LEGENDS["planner"]) + "\n" + legend(PLANNER_ROWS, "rows"))
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
