"""Several XLA programs compiled at once: lowered one after another in Python, then compiled in
threads, so that a multi-core CPU compiles them side by side (the Kuka CLIs' planning modes)."""
from __future__ import annotations

import os

import jax
import numpy as np


def available_memory_gb() -> float:
    """GiB of memory available now (/proc/meminfo's MemAvailable, else the free pages)."""
    try:
        with open("/proc/meminfo") as f:
            kib = next(int(line.split()[1]) for line in f if line.startswith("MemAvailable:"))
        return kib / 2 ** 20
    except (OSError, StopIteration, ValueError):
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2 ** 30


THREADS_VARIABLE = "DIFFPLAN_COMPILE_THREADS"
"""An environment variable: at most this many programs compiled at once (default: the CPU's
cores). The test suite sets 1: its two workers already keep both cores busy, and two MJX
programs compiled at once by one worker took that worker to 13 GB."""


def compile_threads() -> int:
    """Programs compile_together may compile at once: $DIFFPLAN_COMPILE_THREADS, else the
    cores; a value that is not a positive integer is refused in one line."""
    value = os.environ.get(THREADS_VARIABLE)
    if value is None:
        return os.cpu_count() or 1
    if not value.strip().isdigit() or int(value) < 1:
        raise ValueError(f"${THREADS_VARIABLE} must be a positive integer, got {value!r}")
    return int(value)


def compile_together(fn, arg_sets, min_memory_gb: float = 16.0):
    """[fn's compiled program for each args of arg_sets]: traced and lowered one after another
    (Python holds the lock), then compiled by XLA in threads, so on a multi-core CPU the
    programs compile at once (the Kuka CLI's two planning modes on 2 cores: 117 s one after
    another, 75 s at once; its default command 7:32 -> 6:30 from an empty cache, peak memory
    5.9 -> 11.8 GB). One at a time on a single core, with less than min_memory_gb of memory
    available, or as $DIFFPLAN_COMPILE_THREADS says (compile_threads). Each result is called
    like fn with arguments of the same shapes."""
    from concurrent.futures import ThreadPoolExecutor

    lowered = [fn.lower(*args) for args in arg_sets]
    enough = available_memory_gb() >= min_memory_gb
    workers = min(len(lowered), compile_threads()) if enough else 1
    if workers < 2:
        return [low.compile() for low in lowered]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(lambda low: low.compile(), lowered))


def compiled_planners(task, denoiser, configs: dict, episodes, batch: int, bar=None) -> dict:
    """{name: (Planner, its compiled rollout)} for each PlannerConfig of configs: the
    rollout_fn(task) programs for batches of ``batch`` episodes per device shaped like
    ``episodes`` (a leading axis; with several devices the episodes split over them,
    rollout_fn(task, mesh=...)), compiled at once (compile_together); each is called as
    rollout_fn's.
    bar: a progress bar (experiments.harness.progress.bar) that says "compiling" meanwhile (a
    minute or more for MJX programs) and until its next update."""
    from diffplan.planner import Planner
    from diffplan.sharding import data_mesh
    from experiments.harness.core import planner_keys, rollout_fn

    mesh = data_mesh()
    batch *= mesh.size
    planners = {name: Planner(denoiser, config) for name, config in configs.items()}
    idx = np.minimum(np.arange(batch), jax.tree.leaves(episodes)[0].shape[0] - 1)
    chunk = jax.tree.map(lambda x: x[idx], episodes)
    keys = planner_keys(0, np.arange(batch))
    args = [(p, keys, chunk, 0) for p in planners.values()]
    if bar is not None:
        bar.compiling(f"compiling {len(args)} planning program(s)")
    runs = compile_together(rollout_fn(task, mesh=mesh), args)
    return {name: (p, r) for (name, p), r in zip(planners.items(), runs)}
