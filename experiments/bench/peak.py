"""Timing against the matmul peak, for the UNet benchmark (experiments.bench_unet): a matmul
probe timed next to every timed call (the machine may be shared with other jobs whose load
changes by the second), jitted calls timed after their first (compiling) call, FLOPs from XLA's
cost analysis, and the result rows."""
from __future__ import annotations

import statistics
import time

import jax
import jax.numpy as jnp


def flops_of(compiled) -> float | None:
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


def compile_and_time(fn, args, repeats: int, probe: PeakProbe, donate: bool = False):
    """jit(fn) at args: (times, probe times, flops, compile_seconds); the first call (compile or
    persistent-cache load, plus one run) is not timed. ``donate``: fn is a step
    (state0, state1, *rest) -> (state0, state1, ...), timed with its state threaded through."""
    start = time.perf_counter()
    compiled = jax.jit(fn, donate_argnums=(0, 1) if donate else ()).lower(*args).compile()
    out = jax.block_until_ready(compiled(*args))
    compile_seconds = time.perf_counter() - start
    flops = flops_of(compiled)
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


def row(method, kind, model_name, n_params, batch, times, probes, flops, compile_seconds,
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
