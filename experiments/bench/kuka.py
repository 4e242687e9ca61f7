"""Kuka world throughput: MJX physics steps beside C MuJoCo, and seconds per pick-and-place.

    python -m experiments.bench_kuka [--json bench_kuka.json]

Measures on the default JAX device, with the scene's one model (the arm and four blocks, every
contact pair it allows):
  * MJX steps: jit(vmap(physics.simulate)) at each --batch-sizes, --steps physics steps per
    call inside one jitted loop, from the reset state of seeded episodes (blocks on the floor,
    the arm's servos holding it at home), in env steps per second (batch x steps / seconds);
  * C MuJoCo: mujoco.mj_step on one thread, the same model and initial state, in steps/s;
  * pick-and-place: one env.step_batch (IK, then primitive.NUM_STEPS physics steps) of the
    scripted expert's first action in --placement-batch episodes, in seconds per call.

Rates are the median over --repeats timed calls (the best is also reported; the machine may be
shared). The first call of each jitted function (compilation, or loading it from the persistent
compilation cache, plus one run) is reported as compile_seconds. The JAX and MuJoCo versions are
printed: DESIGN.md pins jax 0.6.2 / mujoco-mjx 3.3.3 because newer releases were ~9x slower
here, and this benchmark is how to check again.

JSON (contract 2 layout): {"experiment", "episodes", "seed", "rows": [{"method", "kind", "batch",
"per_second", "best_per_second", "seconds_per_call", "compile_seconds", ...}], "device",
"jax_version", "mujoco_version"}.
"""
from __future__ import annotations

import argparse
import copy
import os
import statistics
import sys
import warnings

import numpy as np

from experiments.bench import common as bc

warnings.filterwarnings("ignore", "overflow encountered in cast")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.bench_kuka",
        description="Kuka world benchmark: MJX physics steps/s at several batch sizes beside C "
                    "MuJoCo's mj_step (one thread) on the same model, and the seconds of one "
                    "vmapped pick-and-place.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--batch-sizes", type=bc.int_list, default=[1, 16, 64],
                   help="comma-separated MJX batch sizes")
    p.add_argument("--steps", type=int, default=1000,
                   help="MJX physics steps per timed call (one jitted loop)")
    p.add_argument("--c-steps", type=int, default=20000, help="C MuJoCo steps per timed call")
    p.add_argument("--placement-batch", type=int, default=64,
                   help="episodes of the timed pick-and-place call (0: skip it)")
    p.add_argument("--repeats", type=int, default=3,
                   help="timed calls per measurement (after one warm-up call)")
    p.add_argument("--episodes", type=int, default=None,
                   help="episodes drawn for the initial states (default: the largest batch)")
    p.add_argument("--seed", type=int, default=0,
                   help="episode i is generated from fold_in(PRNGKey(seed), i)")
    bc.add_output_flags(p)
    return p


def _row(method, kind, batch, work, first, times, **extra):
    median = statistics.median(times)
    return dict(method=method, kind=kind, batch=batch, per_second=work / median,
                best_per_second=work / min(times), seconds_per_call=median,
                compile_seconds=first, **extra)


def bench_mjx(states, batch_sizes, steps: int, repeats: int):
    import jax

    from envs.kuka import physics

    rows = []
    n = states.t.shape[0]
    for batch in batch_sizes:
        idx = np.arange(batch) % n
        data = jax.tree.map(lambda x: x[idx], states.data)

        def call():
            physics.simulate_batch(data, steps).qpos.block_until_ready()

        first, times = bc.first_and_timed(call, repeats)
        rows.append(_row(f"MJX step, batch {batch}", "mjx", batch, batch * steps, first, times,
                         steps_per_call=steps))
        print(f"MJX batch {batch}: {rows[-1]['per_second']:,.0f} env steps/s", file=sys.stderr)
    return rows


def bench_c(states, steps: int, repeats: int):
    import mujoco

    from envs.kuka import scene

    model = scene.mj_model()
    data0 = mujoco.MjData(model)
    data0.qpos[:] = np.asarray(states.data.qpos[0], np.float64)
    data0.ctrl[:] = np.asarray(states.data.ctrl[0], np.float64)
    mujoco.mj_forward(model, data0)

    def call():
        data = copy.copy(data0)
        for _ in range(steps):
            mujoco.mj_step(model, data)

    first, times = bc.first_and_timed(call, repeats)
    return _row("C MuJoCo mj_step, 1 thread", "c", 1, steps, first, times, steps_per_call=steps)


def bench_placement(states, batch: int, repeats: int):
    import jax

    from envs.kuka import env, expert, primitive

    idx = np.arange(batch) % states.t.shape[0]
    states = jax.tree.map(lambda x: x[idx], states)
    actions = jax.vmap(expert.act)(states)

    def call():
        env.step_batch(states, actions).data.qpos.block_until_ready()

    first, times = bc.first_and_timed(call, repeats)
    row = _row(f"pick-and-place, batch {batch}", "pick_and_place", batch,
               batch * primitive.NUM_STEPS, first, times,
               physics_steps_per_placement=primitive.NUM_STEPS)
    row["seconds_per_placement"] = row["seconds_per_call"]
    return row


TABLE_COLUMNS = (("method", "{:<30}", "method"), ("per_second", "{:>14,.0f}", "steps/s"),
                 ("best_per_second", "{:>14,.0f}", "best steps/s"),
                 ("seconds_per_call", "{:>10.3f}", "s/call"),
                 ("compile_seconds", "{:>10.1f}", "first s"))


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    bc.check_positive(parser, args, ("steps", "c_steps", "repeats"))
    if args.placement_batch < 0:
        parser.error(f"--placement-batch must be >= 0, got {args.placement_batch}")
    if args.episodes is not None and args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    bc.start(parser, args)
    import jax
    import mujoco

    from envs.kuka import env
    from envs.kuka.config import COLUMNS
    from experiments.harness.tables import format_table
    from experiments.kuka.eval import generate_episodes

    episodes = args.episodes or max(args.batch_sizes + [args.placement_batch])
    eps = generate_episodes(COLUMNS["stacking_multi"], episodes, args.seed, episodes)
    states = env.reset_batch(eps)
    rows = bench_mjx(states, args.batch_sizes, args.steps, args.repeats)
    rows.append(bench_c(states, args.c_steps, args.repeats))
    if args.placement_batch:
        rows.append(bench_placement(states, args.placement_batch, args.repeats))
    device = jax.devices()[0]
    print(f"jax {jax.__version__}, mujoco {mujoco.__version__} on {len(jax.devices())} x "
          f"{device.platform}, {os.cpu_count()} CPU cores")
    print(format_table(rows, TABLE_COLUMNS, bc.LEGENDS["kuka"]))
    for r in rows:
        if r["kind"] == "pick_and_place":
            print(f"{r['method']}: {r['seconds_per_placement']:.2f} s per vmapped pick-and-place "
                  f"({r['physics_steps_per_placement']} physics steps each)")
    result = dict(experiment="bench_kuka", episodes=episodes, seed=args.seed, rows=rows,
                  device=f"{len(jax.devices())} x {device.platform}",
                  jax_version=jax.__version__, mujoco_version=mujoco.__version__)
    bc.finish(args, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
