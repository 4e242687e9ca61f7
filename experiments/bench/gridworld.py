"""Grid-world throughput benchmark: episode generation and environment stepping.

    python -m experiments.bench_gridworld [--json bench_gridworld.json]

Measures, on whatever JAX devices are present (the default backend):
  * episode generation: jit(episode.generate_batch) of --episodes episodes per call, for each
    setting (layout, objects, instruction tokens and the expert path by BFS, with re-drawn
    layouts when unsolvable), in episodes per second;
  * environment steps: jit(vmap(step + observe)) at each --batch-sizes, with random actions
    (pre-drawn, so no RNG in the timed loop), many steps inside one jitted lax.scan so that the
    Python dispatch does not dominate; the observation (env.Observation: cell tokens as seen,
    visited cells, the agent's cell) is consumed (see below) so XLA cannot drop it. Episodes that end (on the target or after
    max_steps) stay frozen; the step is branch-free, so a frozen step costs the same as a move.
    Each step's observation is XOR-folded into an accumulator of its shape (every value read
    once, as a consumer would), summed once at the end.
  * two diagnostic rows at the largest batch: env.step alone, and step + observe + the
    observation expanded into its binary feature channels (Observation.features: obstacle seen,
    agent, visited, visible), the layout the planner's condition is built from.

Rates are the median over --repeats timed calls (the best is also reported; the machine may be
shared). The first call of each jitted function (compilation, or loading it from the persistent
compilation cache, plus one run) is reported as compile_seconds. The targets are 2,000,000 env
steps/s at batch 4096 and 20,000 generated P-MO2G episodes/s; ratios >= 1 meet them.

JSON (contract 2 layout): {"experiment", "episodes", "seed", "rows": [{"method", "kind",
"setting", "batch", "per_second", "best_per_second", "seconds_per_call", "compile_seconds",
"target", "ratio", ...}], "targets", "device", "jax_version"}.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from envs.gridworld import env, episode
from envs.gridworld.config import SETTINGS, make_config
from experiments.bench import common as bc

TARGET_ENV_STEPS_PER_S = 2_000_000
TARGET_ENV_BATCH = 4096
TARGET_EPISODES_PER_S = 20_000
TARGET_EPISODE_SETTING = "p_mo2g"


def bench_generation(setting: str, num_episodes: int, repeats: int, seed: int):
    """Returns (row dict, the episodes of the first call)."""
    config = make_config(setting)
    fn = jax.jit(lambda key: episode.generate_batch(key, config, num_episodes))
    start = time.perf_counter()
    first = jax.block_until_ready(fn(jax.random.PRNGKey(seed)))
    compile_seconds = time.perf_counter() - start
    times = bc.timed(fn, [(jax.random.PRNGKey(seed + 1 + r),) for r in range(repeats)])
    median = statistics.median(times)
    target = TARGET_EPISODES_PER_S if setting == TARGET_EPISODE_SETTING else None
    row = dict(
        method=f"generate_{setting}", kind="generation", setting=setting, batch=num_episodes,
        per_second=num_episodes / median, best_per_second=num_episodes / min(times),
        seconds_per_call=median, compile_seconds=compile_seconds, target=target,
        ratio=(num_episodes / median / target) if target else None,
        mean_expert_length=float(np.mean(np.asarray(first.expert_length))),
    )
    return row, first


ENV_MEASURES = {"observe": "env", "step": "env (step only)", "features": "env (+features)"}


def _env_runner(config, measure: str = "observe"):
    """jitted (state, actions (T, B)) -> (state, checksum); measure: "observe" (step + observe),
    "step" (step alone) or "features" (step + observe + Observation.features)."""
    v_step = jax.vmap(lambda s, a: env.step(s, a, config))
    observe = measure != "step"

    def expanded(o):
        return (o.cells, o.features) if measure == "features" else o

    v_observe = jax.vmap(lambda s: expanded(env.observe(s, config)))

    @jax.jit
    def run(state, actions):
        """actions int32 (T, B): T steps of step (+ observe) inside one scan."""

        def body(carry, action):
            s, acc = carry
            s = v_step(s, action)
            if observe:
                # Every observation is read once (XOR-folded into an accumulator of its own
                # shape and dtype) so XLA must compute it; a per-step sum would time a
                # reduction instead.
                obs = v_observe(s)
                acc = jax.tree.map(jnp.bitwise_xor, acc, obs)
            else:
                acc = acc + s.agent.sum()
            return (s, acc), None

        init = (jax.tree.map(jnp.zeros_like, v_observe(state)) if observe else jnp.int32(0))
        (state, acc), _ = jax.lax.scan(body, (state, init), actions)
        checksum = sum(jnp.sum(x.astype(jnp.int32)) for x in jax.tree.leaves(acc))
        return state, checksum

    return run


def bench_env(setting: str, episodes, batch_sizes, work: int, repeats: int, seed: int,
              measure: str = "observe"):
    """Rows of env steps per second at each batch size; episodes: a generated batch (tiled
    when a batch size exceeds it). measure: see _env_runner ("step" and "features" are
    diagnostic rows, without a target)."""
    config = make_config(setting)
    run = _env_runner(config, measure)
    reset = jax.jit(jax.vmap(lambda e: env.reset(e, config)))
    available = episodes.agent.shape[0]
    rng = np.random.default_rng(seed)
    rows = []
    for batch in batch_sizes:
        idx = np.arange(batch) % available
        state = reset(jax.tree.map(lambda a: a[idx], episodes))
        num_steps = int(min(20_000, max(100, work // batch)))
        actions = [jnp.asarray(rng.integers(0, 4, (num_steps, batch)), jnp.int32)
                   for _ in range(repeats + 1)]
        start = time.perf_counter()
        jax.block_until_ready(run(state, actions[0]))
        compile_seconds = time.perf_counter() - start
        times = bc.timed(run, [(state, a) for a in actions[1:]])
        median = statistics.median(times)
        steps = batch * num_steps
        target = (TARGET_ENV_STEPS_PER_S if batch == TARGET_ENV_BATCH and measure == "observe"
                  else None)
        suffix = {"observe": "_observe", "step": "_only", "features": "_observe_features"}
        rows.append(dict(
            method=f"env_step{suffix[measure]}_{setting}_b{batch}",
            kind=ENV_MEASURES[measure], setting=setting,
            batch=batch, steps_per_call=num_steps, per_second=steps / median,
            best_per_second=steps / min(times), seconds_per_call=median,
            compile_seconds=compile_seconds, target=target,
            ratio=(steps / median / target) if target else None))
    return rows


def format_table(rows) -> str:
    header = (f"{'kind':<17}{'setting':<8}{'batch':>6}{'steps/call':>11}{'per second':>13}"
              f"{'best':>13}  {'unit':<9}{'target':>11}{'ratio':>7}{'compile s':>11}")
    lines = [header, "-" * len(header)]
    for r in rows:
        unit = "episodes" if r["kind"] == "generation" else "steps"
        target = format(r["target"], ",") if r["target"] else "-"
        ratio = format(r["ratio"], ".2f") if r["ratio"] is not None else "-"
        lines.append(
            f"{r['kind']:<17}{r['setting']:<8}{r['batch']:>6}{r.get('steps_per_call', '-'):>11}"
            f"{r['per_second']:>13,.0f}{r['best_per_second']:>13,.0f}  {unit:<9}{target:>11}"
            f"{ratio:>7}{r['compile_seconds']:>11.1f}")
    return "\n".join(lines + [bc.legend(bc.LEGENDS["gridworld"])])


def _settings_list(text: str) -> list[str]:
    values = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in values if v not in SETTINGS]
    if not values or bad:
        raise argparse.ArgumentTypeError(f"unknown settings {bad}; choose from {SETTINGS}")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.bench_gridworld",
        description="Grid-world throughput: episodes generated per second (each setting, with "
                    "expert paths) and env steps per second under jit(vmap(step + observe)) at "
                    "several batch sizes, compared with the targets (2,000,000 env steps/s at "
                    "batch 4096; 20,000 P-MO2G episodes/s).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--settings", type=_settings_list, default=list(SETTINGS),
                        help="comma-separated settings whose episode generation is timed")
    parser.add_argument("--episodes", type=int, default=4096,
                        help="episodes generated per timed call (one jitted generate_batch)")
    parser.add_argument("--env-setting", choices=SETTINGS, default="p_mo2g",
                        help="setting whose env stepping is timed (its episodes are generated "
                             "once and tiled to each batch size)")
    parser.add_argument("--batch-sizes", type=bc.int_list, default=[1, 64, 1024, 4096],
                        help="comma-separated env batch sizes")
    parser.add_argument("--work", type=int, default=1_000_000,
                        help="env steps per timed call: each call scans work // batch steps "
                             "(clipped to 100..20000)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="timed calls per measurement (after one warm-up call)")
    parser.add_argument("--no-diagnostics", action="store_true",
                        help="skip the diagnostic rows (at the largest batch size): env.step "
                             "without observe, and step + observe + the observation's feature "
                             "channels")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    bc.add_output_flags(parser)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    bc.check_positive(parser, args, ("episodes", "work", "repeats"))
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    bc.start(parser, args)

    rows = []
    env_episodes = None
    settings = list(args.settings)
    if args.env_setting not in settings:
        settings.append(args.env_setting)  # its episodes are needed for the env benchmark
    for setting in settings:
        row, episodes = bench_generation(setting, args.episodes, args.repeats, args.seed)
        if setting in args.settings:
            rows.append(row)
        if setting == args.env_setting:
            env_episodes = episodes
        print(f"generation {setting}: {row['per_second']:,.0f} episodes/s", file=sys.stderr)
    env_rows = bench_env(args.env_setting, env_episodes, args.batch_sizes, args.work,
                         args.repeats, args.seed)
    rows += env_rows
    if not args.no_diagnostics:
        for measure in ("step", "features"):
            rows += bench_env(args.env_setting, env_episodes, [max(args.batch_sizes)],
                              args.work, args.repeats, args.seed, measure=measure)

    device = jax.devices()[0]
    print(f"jax {jax.__version__} on {len(jax.devices())} x {device.platform} "
          f"({getattr(device, 'device_kind', '')})")
    print(format_table(rows))
    for r in rows:
        if r["ratio"] is not None:
            what = "episodes/s" if r["kind"] == "generation" else "env steps/s"
            verdict = "meets" if r["ratio"] >= 1 else "misses"
            print(f"{r['method']}: {r['per_second']:,.0f} {what} = {r['ratio']:.2f} x the target "
                  f"{r['target']:,} ({verdict} it)")
    result = dict(
        experiment="bench_gridworld", episodes=args.episodes, seed=args.seed, rows=rows,
        targets=dict(env_steps_per_second=TARGET_ENV_STEPS_PER_S, env_batch=TARGET_ENV_BATCH,
                     episodes_per_second=TARGET_EPISODES_PER_S,
                     episodes_setting=TARGET_EPISODE_SETTING),
        device=f"{len(jax.devices())} x {device.platform}", jax_version=jax.__version__)
    bc.finish(args, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
