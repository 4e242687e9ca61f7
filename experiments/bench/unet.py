"""Denoiser (UNet) throughput benchmark on whatever JAX device is present.

    python -m experiments.bench_unet [--json bench_unet.json] [--configs small,default,large]

Measures in one run:
  * the practical matmul peak: jit(a @ b) of dense float32 (N x N) matrices (--matmul-n),
    in GFLOP/s;
  * for each model config (small / default / large, batch --batch, --size x --size maps):
    the jitted forward pass, and the jitted train step (forward + backward + Adam update via
    optax, the DDPM eps-MSE loss on the generated channels); FLOPs per call from XLA's cost
    analysis (``jax.jit(f).lower(...).compile().cost_analysis()``), achieved GFLOP/s and the
    percent of the matmul peak;
  * the sampler (``diffplan.sample``, DDIM, condition channels held fixed) with the
    --sampler-config model: the time of one call that plans --batch episodes at each of
    --sampler-steps, and the cost per plan (call time / batch).

Times are medians over --repeats timed calls (the best is reported too). The machine may be
shared with other jobs whose load changes by the second, so every timed call is paired with a
matmul call just before it: percent_of_peak is the median over calls of the call's GFLOP/s
over its adjacent matmul's GFLOP/s ("matmul_peak_gflops" in the JSON is the best matmul rate
seen in the run). The first call of each jitted function (compilation or a load from JAX's persistent
compilation cache, plus one run) is reported as compile_seconds. The target: the UNet forward
at >= 40% of the matmul peak.

JSON (contract 2 layout): {"experiment": "bench_unet", "episodes": batch, "seed", "rows":
[{"method", "kind" ("matmul" | "forward" | "train_step" | "sampler"), "model", "params",
"batch", "ms", "best_ms", "gflop", "gflops", "percent_of_peak", "adjacent_matmul_gflops",
"compile_seconds", ...};
sampler rows add "num_steps", "denoiser_calls", "ms_per_plan", "ms_per_call" and
"time_over_forwards" (call time / (denoiser calls x forward time))],
"matmul_peak_gflops", "target_percent_of_peak", "configs", "device", "jax_version"}.
"""
from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import optax

from diffplan.denoiser import Denoiser, DenoiserConfig, count_params, init_params, make_denoise_fn
from experiments.bench import common as bc
from experiments.bench.peak import PeakProbe, bench_matmul, compile_and_time, row as _row
from experiments.bench.workload import make_inputs, make_train_step

TARGET_PERCENT_OF_PEAK = 40.0

# The model sizes we use (grid world: vocab of ~64 tokens, L <= 32, C = 5 condition channels).
CONFIGS = {
    "small": DenoiserConfig(widths=(16, 32, 64), head_dim=16, embed_dim=32, text_dim=64,
                            text_layers=2, groups=8),
    "default": DenoiserConfig(),
    "large": DenoiserConfig(widths=(32, 64, 128), num_res_blocks=2, embed_dim=64,
                            mid_block=True),
}


def bench_model(name: str, cfg: DenoiserConfig, args, probe: PeakProbe, log) -> tuple[list, dict]:
    model = Denoiser(cfg)
    variables = init_params(model, jax.random.PRNGKey(args.seed), args.size, args.size)
    params = variables["params"]
    n_params = count_params(params)
    x, t, tokens = make_inputs(cfg, args.batch, args.size, args.tokens, args.seed)
    rows = []
    times, probes, flops, cs = compile_and_time(model.apply, (variables, x, t, tokens),
                                                 args.repeats, probe)
    fwd = _row(f"{name}_forward", "forward", name, n_params, args.batch, times, probes, flops,
               cs, probe)
    fwd["ms_per_sample"] = fwd["ms"] / args.batch
    rows.append(fwd)
    log(f"{name}: {n_params / 1e6:.2f}M params, forward {fwd['ms']:.1f} ms")
    if not args.no_train:
        optimizer = optax.adam(1e-4)
        opt_state = optimizer.init(params)
        step = make_train_step(model, optimizer)
        targs = (jax.tree_util.tree_map(jnp.copy, params), opt_state, x, tokens,
                 jax.random.PRNGKey(args.seed))
        times, probes, flops, cs = compile_and_time(
            step, targs, max(2, args.repeats // 2 + 1), probe, donate=True)
        tr = _row(f"{name}_train_step", "train_step", name, n_params, args.batch, times, probes,
                  flops, cs, probe)
        tr["train_over_forward"] = tr["ms"] / fwd["ms"]
        rows.append(tr)
        log(f"{name}: train step {tr['ms']:.1f} ms")
    return rows, dict(model=model, variables=variables, x=x, tokens=tokens,
                      forward_ms=fwd["ms"], forward_gflop=fwd["gflop"], params=n_params)


def bench_sampler(name: str, ctx: dict, steps_list, args, probe: PeakProbe, log) -> list:
    """One jitted ``sample`` call per step count. Its FLOPs are the denoiser's (calls x forward
    FLOPs): XLA's cost analysis counts a loop body once."""
    from diffplan.sampler import denoiser_calls, sample
    from diffplan.schedule import cosine_schedule

    model, variables, x, tokens = ctx["model"], ctx["variables"], ctx["x"], ctx["tokens"]
    cfg = model.config
    schedule = cosine_schedule(args.train_timesteps)
    known_mask = (jnp.arange(cfg.num_channels) < cfg.num_cond_channels)[None, None, None, :]
    rows = []
    for k in steps_list:
        def plan(variables, key, x_known, tokens, k=k):
            fn = make_denoise_fn(model, variables, tokens)
            return sample(fn, schedule, key, x_known, known_mask, num_steps=k)

        sargs = (variables, jax.random.PRNGKey(args.seed), x, tokens)
        times, probes, _, cs = compile_and_time(plan, sargs, args.sampler_repeats, probe)
        calls = denoiser_calls(k)
        flops = calls * ctx["forward_gflop"] * 1e9 if ctx["forward_gflop"] else None
        row = _row(f"{name}_sample_{k}", "sampler", name, ctx["params"], args.batch, times,
                   probes, flops, cs, probe)
        row.update(num_steps=k, denoiser_calls=calls, ms_per_plan=row["ms"] / args.batch,
                   ms_per_call=row["ms"] / calls,
                   time_over_forwards=row["ms"] / (calls * ctx["forward_ms"]))
        rows.append(row)
        log(f"{name}: sampler {k} steps {row['ms']:.0f} ms per batch "
            f"({row['ms_per_plan']:.2f} ms per plan)")
    return rows


def format_table(rows) -> str:
    head = (f"{'method':<24}{'params':>8}{'ms':>10}{'best ms':>10}{'GFLOP':>9}{'GFLOP/s':>9}"
            f"{'% peak':>8}{'ms/plan':>9}{'compile s':>10}")
    lines = [head, "-" * len(head)]

    def f(v, fmt):
        width = int(fmt.split(".")[0])
        return format(v, fmt) if v is not None else "-".rjust(width)

    for r in rows:
        params = f"{r['params'] / 1e6:.2f}M" if r.get("params") else "-"
        lines.append(f"{r['method']:<24}{params:>8}{f(r['ms'], '10.1f')}{f(r['best_ms'], '10.1f')}"
                     f"{f(r['gflop'], '9.2f')}{f(r['gflops'], '9.1f')}"
                     f"{f(r['percent_of_peak'], '8.1f')}{f(r.get('ms_per_plan'), '9.2f')}"
                     f"{f(r['compile_seconds'], '10.1f')}")
    return "\n".join(lines + [bc.legend(bc.LEGENDS["unet"])])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.bench_unet",
        description="Benchmark the denoiser UNet on this machine: matmul peak, forward and train "
                    "step GFLOP/s (XLA cost analysis) as percent of the peak, and the sampler's "
                    "cost per plan. Prints a table; --json writes the rows.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--configs", type=bc.typed_list(str), default=list(CONFIGS),
                        help=f"comma-separated model configs from {list(CONFIGS)}")
    parser.add_argument("--batch", "--episodes", dest="batch", type=int, default=64,
                        help="batch size (plans / episodes per call)")
    parser.add_argument("--size", type=int, default=16, help="map height = width")
    parser.add_argument("--tokens", type=int, default=16, help="instruction length L")
    parser.add_argument("--repeats", type=int, default=5,
                        help="timed calls per forward measurement (train: about half)")
    parser.add_argument("--matmul-n", type=int, default=2048, help="matmul size N (N x N @ N x N)")
    parser.add_argument("--sampler-config", default="default",
                        help="model config used for the sampler measurement")
    parser.add_argument("--sampler-steps", type=bc.typed_list(int), default=[10, 20, 50],
                        help="comma-separated DDIM step counts")
    parser.add_argument("--sampler-repeats", type=int, default=2, help="timed sampler calls")
    parser.add_argument("--train-timesteps", type=int, default=100,
                        help="diffusion training timesteps of the schedule (the paper: 100)")
    parser.add_argument("--no-train", action="store_true", help="skip the train step")
    parser.add_argument("--no-sampler", action="store_true", help="skip the sampler")
    parser.add_argument("--seed", type=int, default=0, help="random seed of inputs and params")
    bc.add_output_flags(parser)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    bc.check_positive(parser, args, ("batch", "size", "tokens", "repeats", "matmul_n",
                                     "sampler_repeats", "train_timesteps"))
    unknown = [c for c in args.configs + [args.sampler_config] if c not in CONFIGS]
    if unknown:
        parser.error(f"unknown configs {unknown}; choose from {list(CONFIGS)}")
    bad_steps = [k for k in args.sampler_steps if not 1 <= k <= args.train_timesteps]
    if bad_steps:
        parser.error(f"--sampler-steps {bad_steps} must be in [1, {args.train_timesteps}]")
    for c in set(args.configs + [args.sampler_config]):
        m = CONFIGS[c].min_size_multiple
        if args.size % m:
            parser.error(f"--size {args.size} must be divisible by {m} for config {c}")
        if args.tokens > CONFIGS[c].max_tokens:
            parser.error(f"--tokens {args.tokens} exceeds max_tokens={CONFIGS[c].max_tokens}")
    bc.start(parser, args)

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    probe = PeakProbe(args.matmul_n)
    mm = bench_matmul(probe, args.repeats)
    log(f"matmul {args.matmul_n}: {mm['gflops']:.1f} GFLOP/s")
    rows = [mm]
    ctxs = {}
    names = list(args.configs)
    if not args.no_sampler and args.sampler_config not in names:
        names.append(args.sampler_config)
    for name in names:
        model_rows, ctx = bench_model(name, CONFIGS[name], args, probe, log)
        if name in args.configs:
            rows += model_rows
        ctxs[name] = ctx
    if not args.no_sampler:
        rows += bench_sampler(args.sampler_config, ctxs[args.sampler_config],
                              args.sampler_steps, args, probe, log)
    # The best matmul rate seen in the whole run (every probe call counts).
    peak = probe.flops / min(probe.samples) / 1e9
    mm["best_gflops"] = peak

    device = jax.devices()[0]
    print(f"jax {jax.__version__} on {len(jax.devices())} x {device.platform} "
          f"({getattr(device, 'device_kind', '')}); batch {args.batch}, "
          f"{args.size}x{args.size} maps, L={args.tokens}; matmul {args.matmul_n}: median "
          f"{mm['gflops']:.1f}, best {peak:.1f} GFLOP/s. % peak: vs the matmul run just before "
          f"each call (median over calls).")
    print(format_table(rows))
    for r in rows:
        if r["kind"] == "forward" and r["percent_of_peak"] is not None:
            verdict = "meets" if r["percent_of_peak"] >= TARGET_PERCENT_OF_PEAK else "misses"
            print(f"{r['method']}: {r['percent_of_peak']:.1f}% of the matmul peak ({verdict} the "
                  f"{TARGET_PERCENT_OF_PEAK:.0f}% target; {r['gflops']:.1f} GFLOP/s, "
                  f"{100 * r['gflops'] / peak:.1f}% of the run's best matmul)")
    result = dict(
        experiment="bench_unet", episodes=args.batch, seed=args.seed, rows=rows,
        matmul_peak_gflops=peak, target_percent_of_peak=TARGET_PERCENT_OF_PEAK,
        configs={n: CONFIGS[n].to_dict() for n in names}, size=args.size, tokens=args.tokens,
        device=f"{len(jax.devices())} x {device.platform}", jax_version=jax.__version__)
    bc.finish(args, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
