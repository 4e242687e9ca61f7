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
import json
import pathlib
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import optax

from diffplan.jax_cache import enable_compilation_cache
from diffplan.denoiser import Denoiser, DenoiserConfig, count_params, init_params, make_denoise_fn

TARGET_PERCENT_OF_PEAK = 40.0

# The model sizes we use (grid world: vocab of ~64 tokens, L <= 32, C = 5 condition channels).
CONFIGS = {
    "small": DenoiserConfig(widths=(16, 32, 64), head_dim=16, embed_dim=32, text_dim=64,
                            text_layers=2, groups=8),
    "default": DenoiserConfig(),
    "large": DenoiserConfig(widths=(32, 64, 128), num_res_blocks=2, embed_dim=64,
                            mid_block=True),
}


def _flops(compiled) -> float | None:
    try:
        ca = compiled.cost_analysis()
    except Exception:  # noqa: BLE001 - not every backend implements it
        return None
    if isinstance(ca, (list, tuple)):
        ca = ca[0] if ca else None
    if not ca or "flops" not in ca:
        return None
    return float(ca["flops"])


class PeakProbe:
    """The matmul peak, measured next to every timed call.

    The machine may be shared with other jobs whose load changes from second to second, so
    each timed call of a benchmarked function is paired with a matmul call just before it and
    its percent of peak is the median over pairs of (its GFLOP/s) / (that matmul's GFLOP/s).
    """

    def __init__(self, n: int):
        a = jax.random.normal(jax.random.PRNGKey(0), (n, n), jnp.float32)
        b = jax.random.normal(jax.random.PRNGKey(1), (n, n), jnp.float32)
        self.n, self.args = n, (a, b)
        self.flops = 2.0 * n ** 3
        start = time.perf_counter()
        self.fn = jax.jit(jnp.matmul).lower(a, b).compile()
        jax.block_until_ready(self.fn(a, b))
        self.compile_seconds = time.perf_counter() - start
        self.samples: list[float] = []  # seconds of every probe call

    def __call__(self) -> float:
        start = time.perf_counter()
        jax.block_until_ready(self.fn(*self.args))
        seconds = time.perf_counter() - start
        self.samples.append(seconds)
        return seconds


def _compile_and_time(fn, args, repeats: int, probe: PeakProbe, donate: bool = False):
    """jit(fn) at args: (times, probe times, flops, compile_seconds); the first call (compile or
    persistent-cache load, plus one run) is not timed. ``donate``: fn is a step
    (state0, state1, *rest) -> (state0, state1, ...), timed with its state threaded through."""
    start = time.perf_counter()
    compiled = jax.jit(fn, donate_argnums=(0, 1) if donate else ()).lower(*args).compile()
    out = jax.block_until_ready(compiled(*args))
    compile_seconds = time.perf_counter() - start
    flops = _flops(compiled)
    times, probes = [], []
    state = out[:2] if donate else None
    for _ in range(repeats):
        probes.append(probe())
        t0 = time.perf_counter()
        if donate:
            state = jax.block_until_ready(compiled(*state, *args[2:]))[:2]
        else:
            jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return times, probes, flops, compile_seconds


def bench_matmul(probe: PeakProbe, repeats: int) -> dict:
    times = [probe() for _ in range(repeats)]
    med = statistics.median(times)
    return dict(method=f"matmul_{probe.n}", kind="matmul", model=None, params=None, batch=None,
                ms=med * 1e3, best_ms=min(times) * 1e3, gflop=probe.flops / 1e9,
                gflops=probe.flops / med / 1e9, best_gflops=probe.flops / min(times) / 1e9,
                percent_of_peak=None, compile_seconds=probe.compile_seconds)


def make_inputs(cfg: DenoiserConfig, batch: int, size: int, num_tokens: int, seed: int):
    """A realistic planning batch: (x (B,H,W,C+G), t (B,), tokens (B,L))."""
    k = jax.random.split(jax.random.PRNGKey(seed), 5)
    ids = jax.random.randint(k[0], (batch, size, size, 1), 0, cfg.vocab_size).astype(jnp.float32)
    feats = jax.random.bernoulli(k[1], 0.3, (batch, size, size, cfg.num_cond_channels - 1))
    gen = jnp.where(jax.random.bernoulli(k[2], 0.1, (batch, size, size, cfg.num_gen_channels)),
                    1.0, -1.0)
    x = jnp.concatenate([ids, feats.astype(jnp.float32), gen], axis=-1)
    t = jax.random.randint(k[3], (batch,), 0, 100)
    lengths = jax.random.randint(k[4], (batch, 1), 3, num_tokens + 1)
    tokens = jnp.where(jnp.arange(num_tokens)[None] < lengths,
                       4 + jnp.arange(num_tokens)[None] % (cfg.vocab_size - 4), 0)
    return x, t, tokens.astype(jnp.int32)


def make_train_step(model: Denoiser, optimizer, num_train_steps: int = 100):
    """(params, opt_state, x0, tokens, key) -> (params, opt_state, loss): one Adam step on the
    DDPM eps-MSE of the generated channels (condition channels held clean)."""
    c = model.config.num_cond_channels
    ab = jnp.linspace(0.999, 0.01, num_train_steps)  # alphas_cumprod stand-in: cost only

    def loss_fn(params, x0, tokens, key):
        kt, ke = jax.random.split(key)
        t = jax.random.randint(kt, (x0.shape[0],), 0, num_train_steps)
        eps = jax.random.normal(ke, x0.shape[:-1] + (x0.shape[-1] - c,))
        a = ab[t][:, None, None, None]
        x_t = jnp.concatenate([x0[..., :c], jnp.sqrt(a) * x0[..., c:] + jnp.sqrt(1 - a) * eps],
                              axis=-1)
        pred = model.apply({"params": params}, x_t, t, tokens)
        return jnp.mean(jnp.square(pred - eps))

    def step(params, opt_state, x0, tokens, key):
        loss, grads = jax.value_and_grad(loss_fn)(params, x0, tokens, key)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


def _row(method, kind, model_name, n_params, batch, times, probes, flops, compile_seconds,
         probe: PeakProbe):
    """A result row; percent_of_peak is the median over (call, adjacent matmul) pairs."""
    med = statistics.median(times)
    gflops = flops / med / 1e9 if flops else None
    pct = (statistics.median(100.0 * (flops / t) / (probe.flops / p) for t, p in zip(times, probes))
           if flops else None)
    return dict(method=method, kind=kind, model=model_name, params=n_params, batch=batch,
                ms=med * 1e3, best_ms=min(times) * 1e3,
                gflop=flops / 1e9 if flops else None, gflops=gflops,
                best_gflops=flops / min(times) / 1e9 if flops else None,
                percent_of_peak=pct,
                adjacent_matmul_gflops=probe.flops / statistics.median(probes) / 1e9,
                compile_seconds=compile_seconds)


def bench_model(name: str, cfg: DenoiserConfig, args, probe: PeakProbe, log) -> tuple[list, dict]:
    model = Denoiser(cfg)
    variables = init_params(model, jax.random.PRNGKey(args.seed), args.size, args.size)
    params = variables["params"]
    n_params = count_params(params)
    x, t, tokens = make_inputs(cfg, args.batch, args.size, args.tokens, args.seed)
    rows = []
    times, probes, flops, cs = _compile_and_time(model.apply, (variables, x, t, tokens),
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
        times, probes, flops, cs = _compile_and_time(
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
        times, probes, _, cs = _compile_and_time(plan, sargs, args.sampler_repeats, probe)
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
    return "\n".join(lines)


def _list(type_):
    def parse(text):
        try:
            return [type_(v) for v in text.split(",") if v]
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from e
    return parse


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.bench_unet",
        description="Benchmark the denoiser UNet on this machine: matmul peak, forward and train "
                    "step GFLOP/s (XLA cost analysis) as percent of the peak, and the sampler's "
                    "cost per plan. Prints a table; --json writes the rows.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--configs", type=_list(str), default=list(CONFIGS),
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
    parser.add_argument("--sampler-steps", type=_list(int), default=[10, 20, 50],
                        help="comma-separated DDIM step counts")
    parser.add_argument("--sampler-repeats", type=int, default=2, help="timed sampler calls")
    parser.add_argument("--train-timesteps", type=int, default=100,
                        help="diffusion training timesteps of the schedule (the paper: 100)")
    parser.add_argument("--no-train", action="store_true", help="skip the train step")
    parser.add_argument("--no-sampler", action="store_true", help="skip the sampler")
    parser.add_argument("--seed", type=int, default=0, help="random seed of inputs and params")
    parser.add_argument("--json", metavar="PATH", default=None, help="write the results here")
    parser.add_argument("--no-cache", action="store_true",
                        help="do not use JAX's persistent compilation cache (compile_seconds "
                             "then measures real compilation)")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("batch", "size", "tokens", "repeats", "matmul_n", "sampler_repeats",
                 "train_timesteps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")
    unknown = [c for c in args.configs + [args.sampler_config] if c not in CONFIGS]
    if unknown:
        parser.error(f"unknown configs {unknown}; choose from {list(CONFIGS)}")
    bad_steps = [k for k in args.sampler_steps if not 1 <= k <= args.train_timesteps]
    if bad_steps:
        parser.error(f"--sampler-steps {bad_steps} must be in [1, {args.train_timesteps}]")
    if args.json is not None and not pathlib.Path(args.json).resolve().parent.is_dir():
        parser.error(f"--json {args.json}: directory does not exist")
    for c in set(args.configs + [args.sampler_config]):
        m = CONFIGS[c].min_size_multiple
        if args.size % m:
            parser.error(f"--size {args.size} must be divisible by {m} for config {c}")
        if args.tokens > CONFIGS[c].max_tokens:
            parser.error(f"--tokens {args.tokens} exceeds max_tokens={CONFIGS[c].max_tokens}")
    if not args.no_cache:
        enable_compilation_cache()

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
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
