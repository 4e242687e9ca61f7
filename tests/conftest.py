"""Shared test setup: the repo on sys.path, JAX's persistent compilation cache, and session-scoped
fixtures that compile each jitted grid-world function once for the whole test session.

The compilation cache lives in $DIFFPLAN_JAX_CACHE or ~/.cache/diffplan-jax: compiled programs
are reused across test runs (and by the CLIs, which use the same directory).
"""
from __future__ import annotations

import functools
import os
import pathlib
import sys

import jax
import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from diffplan.jax_cache import enable_compilation_cache  # noqa: E402

enable_compilation_cache()
# One program compiled at a time per test process (experiments.harness.compiling): the two
# workers keep both cores busy already, and a worker compiling two MJX programs at once
# took that worker to 13 GB.
os.environ.setdefault("DIFFPLAN_COMPILE_THREADS", "1")

from xdist_scheduling import crash_diagnosis, make_scheduler  # noqa: E402


def pytest_xdist_make_scheduler(config, log):
    """Tests by module on the workers (a module's fixtures are built once), except that every
    test that compiles MJX programs runs on one worker, one after the other: an MJX program
    takes ~1 min and ~5 GB to compile, the Kuka tests share many of them (in-process and
    through the persistent compilation cache), and two workers compiling the same ones at
    once doubled the suite's MJX time. The MJX group is the largest unit, so it starts first;
    the other worker runs the grid-world modules meanwhile. A worker that dies is reported and
    the run goes on to its summary (tests/xdist_scheduling.py)."""
    return make_scheduler(config, log)


def pytest_handlecrashitem(crashitem, report, sched):
    """xdist's report of a test whose worker died says how it died (signal, likely cause) and
    how much memory was left."""
    report.longrepr = f"{report.longrepr}: {crash_diagnosis(report)}"


def _peak_rss_gb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20  # KB on Linux


_WORKER_PEAKS: dict[str, float] = {}


def pytest_sessionfinish(session):
    """A worker sends its peak resident memory to the controller (xdist's workeroutput)."""
    output = getattr(session.config, "workeroutput", None)
    if output is not None:
        output["peak_rss_gb"] = _peak_rss_gb()


def pytest_testnodedown(node, error):
    peak = getattr(node, "workeroutput", {}).get("peak_rss_gb")
    if peak is not None:
        _WORKER_PEAKS[node.gateway.id] = peak


def pytest_terminal_summary(terminalreporter):
    """One line before the summary: each test process's peak resident memory (the suite's
    budget is their sum; docs/benchmarks.md, "Test suite")."""
    if hasattr(terminalreporter.config, "workeroutput"):
        return
    main = "controller" if _WORKER_PEAKS else "pytest"
    peaks = {**dict(sorted(_WORKER_PEAKS.items())), main: _peak_rss_gb()}
    if _TIMELINE:
        _write_timeline()
    terminalreporter.write_line(
        "peak resident memory: " + ", ".join(f"{k} {v:.1f} GB" for k, v in peaks.items())
        + f" (sum {sum(peaks.values()):.1f} GB; at one moment at most "
        + (f"{_TREE[0].stop():.1f} GB)" if _TREE else "unknown)"))


def pytest_addoption(parser):
    parser.addoption(
        "--timeline", metavar="PATH", default=None,
        help="write one JSON line per test phase to PATH: the worker that ran it, its start and "
             "end in seconds from the session's start, the phase and the test id (where the "
             "suite's wall time goes: which worker ran what, and when it went idle)")


_TIMELINE: dict = {}


def _tree_rss_gb(pid: int) -> float:
    """Resident memory of a process and its descendants, in GB (0 where /proc is not there)."""
    total, stack = 0.0, [pid]
    while stack:
        pid = stack.pop()
        try:
            with open(f"/proc/{pid}/status") as f:
                total += next((int(ln.split()[1]) for ln in f if ln.startswith("VmRSS:")), 0)
            for task in os.listdir(f"/proc/{pid}/task"):
                with open(f"/proc/{pid}/task/{task}/children") as f:
                    stack += [int(c) for c in f.read().split()]
        except (OSError, ValueError):
            continue
    return total / 2 ** 20


class _TreeMemory:
    """The largest sum of the test processes' resident memory at one moment (sampled every
    half second by a thread of the controller): what the machine must have free for the suite."""

    def __init__(self):
        import threading

        self.peak, self._stop = 0.0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.wait(0.5):
            self.peak = max(self.peak, _tree_rss_gb(os.getpid()))

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return max(self.peak, _tree_rss_gb(os.getpid()))


_TREE: list = []


_COMPILES = {"programs": 0, "seconds": 0.0, "cache_hits": 0}
"""With --timeline: this process's XLA compilations (count, seconds; persistent-cache loads
included, and counted apart) since its last test ended."""


def _count_compiles():
    from jax import monitoring

    def duration(event, seconds, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            _COMPILES["programs"] += 1
            _COMPILES["seconds"] += seconds

    def event(name, **_):
        if name == "/jax/compilation_cache/cache_hits":
            _COMPILES["cache_hits"] += 1

    monitoring.register_event_duration_secs_listener(duration)
    monitoring.register_event_listener(event)


def pytest_sessionstart(session):
    if session.config.getoption("--timeline", None):
        _count_compiles()
    if hasattr(session.config, "workeroutput"):
        return
    _TREE.append(_TreeMemory())
    path = session.config.getoption("--timeline", None)
    if path:
        import time

        _TIMELINE.update(path=path, t0=time.time(), lines=[])


def pytest_runtest_logreport(report):
    """On the controller (or a run without workers): the phase's worker, start, end and id."""
    if not _TIMELINE or not hasattr(report, "start"):
        return
    worker = getattr(getattr(report, "node", None), "gateway", None)
    _TIMELINE["lines"].append({
        "worker": worker.id if worker is not None else "main",
        "start": round(report.start - _TIMELINE["t0"], 3),
        "end": round(report.stop - _TIMELINE["t0"], 3),
        "phase": report.when, "test": report.nodeid, "outcome": report.outcome,
        **dict(report.user_properties).get("compiles", {})})


def _write_timeline():
    import json

    with open(_TIMELINE["path"], "w") as f:
        for line in _TIMELINE["lines"]:
            f.write(json.dumps(line) + "\n")


def _malloc_trim():
    """Returns the C heap's free pages to the kernel (glibc's malloc_trim; nothing elsewhere)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem):
    """After every test, the memory freed by XLA's compiler goes back to the kernel. glibc keeps
    freed heap pages: compiling one MJX rollout left the process at 4.1 GB resident, 0.7 GB
    after malloc_trim, and a test worker that never trimmed grew to 13 GB while it held ~2 GB
    of live data. (A compile's own peak is unchanged; what goes is the high-water mark each
    process kept for the rest of the run, which the two workers' budget adds up.) With
    --timeline, the test's compilations go into its teardown report."""
    _malloc_trim()
    if item.config.getoption("--timeline", None):
        item.user_properties.append(("compiles", dict(_COMPILES, seconds=round(
            _COMPILES["seconds"], 2))))
        _COMPILES.update(programs=0, seconds=0.0, cache_hits=0)


MAX_MAPPINGS = 32768
"""Memory mappings of a test process above which its compiled programs are dropped (half the
kernel's default vm.max_map_count, 65530)."""


def memory_mappings() -> int:
    """The memory mappings of this process (0 where /proc is not there)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


@pytest.fixture(scope="module", autouse=True)
def release_compiled_programs():
    """Drops JAX's in-memory compiled programs after a test module once the process holds more
    than MAX_MAPPINGS memory mappings. Every loaded XLA CPU executable holds ~10 mappings (more
    for large ones) until its cache entry goes: a worker that ran all the grid-world modules
    reached ~63000 of the kernel's default limit of 65530 (vm.max_map_count), and past it LLVM
    segfaulted while compiling the next program. A later module that needs a dropped program
    reads it back from the persistent cache. (Dropping after every module kept the peak at
    20000 but made the suite 32% slower: the MJX programs were re-read module after module.)"""
    yield
    if memory_mappings() > MAX_MAPPINGS:
        jax.clear_caches()


GRID_BATCH = 64
"""Episodes per generated test batch (one compilation per setting serves every seed)."""


@pytest.fixture(scope="session")
def grid_configs():
    """setting -> the paper's GridConfig of that setting."""
    from envs.gridworld.config import SETTINGS, make_config

    return {s: make_config(s) for s in SETTINGS}


@pytest.fixture(scope="session")
def gen_batch(grid_configs):
    """(setting, seed) -> (Episode of numpy arrays with a leading (GRID_BATCH,) axis, visible0 bool
    (GRID_BATCH, H, W)): episodes 0..GRID_BATCH-1 of seed, i.e. ``episode.generate_batch(
    PRNGKey(seed), config, GRID_BATCH)`` (test_generate_batch_prefix_stable checks it), with
    visible0 from env.reset. Uses export.generate_chunk, so one compilation per setting serves
    every seed and the export tests; results memoised per (setting, seed)."""
    from envs.gridworld import export

    @functools.lru_cache(maxsize=64)
    def gen(setting, seed):
        eps, visible0 = export.generate_chunk(jax.random.PRNGKey(seed), np.int32(0),
                                              grid_configs[setting], GRID_BATCH)
        return jax.tree.map(np.asarray, eps), np.asarray(visible0)

    return gen


ROLL_STEPS = 110
"""Steps of a test rollout: longer than max_steps = 100, so every episode ends inside it."""


def mixed_actions(episodes, seed: int, num_steps: int = ROLL_STEPS) -> np.ndarray:
    """int32 (B, num_steps) actions: even episodes follow their expert path (then act randomly),
    odd episodes act uniformly at random (many collisions at the border and obstacles)."""
    rng = np.random.default_rng(seed)
    b = episodes.agent.shape[0]
    actions = rng.integers(0, 4, size=(b, num_steps)).astype(np.int32)
    deltas = np.diff(episodes.expert_positions, axis=1)  # (B, max_steps, 2)
    moves = np.array([[-1, 0], [0, 1], [1, 0], [0, -1]])
    for i in range(0, b, 2):
        n = int(episodes.expert_length[i])
        for t in range(n):
            actions[i, t] = int(np.flatnonzero((moves == deltas[i, t]).all(-1))[0])
    return actions


@pytest.fixture(scope="session")
def rollout(grid_configs, gen_batch):
    """(setting, seed) -> dict of numpy arrays of a jitted reset + ROLL_STEPS x (step + observe)
    rollout (under vmap) of the episodes gen_batch(setting, seed) with mixed_actions(seed):
      "episodes", "visible0", "actions" int32 (B, T),
      "states0": State at t=0 (leading B), "obs0": its Observation,
      "states": State after each step (leading B, T), "obs": Observation after each step.
    Compiled once per setting; memoised for a few seeds."""
    from envs.gridworld import env

    jitted = {}

    def compiled(setting):
        if setting not in jitted:
            config = grid_configs[setting]
            v_reset = jax.vmap(lambda e: env.reset(e, config))
            v_step = jax.vmap(lambda s, a: env.step(s, a, config))
            v_observe = jax.vmap(lambda s: env.observe(s, config))

            @jax.jit
            def run(episodes, actions):
                s0 = v_reset(episodes)

                def body(state, action):
                    nxt = v_step(state, action)
                    return nxt, (nxt, v_observe(nxt))

                _, (states, obs) = jax.lax.scan(body, s0, actions.T)
                # scan stacks time first: move it after the batch axis.
                swap = functools.partial(jax.numpy.swapaxes, axis1=0, axis2=1)
                return s0, v_observe(s0), jax.tree.map(swap, states), jax.tree.map(swap, obs)

            jitted[setting] = run
        return jitted[setting]

    @functools.lru_cache(maxsize=4)
    def run(setting, seed):
        episodes, visible0 = gen_batch(setting, seed)
        actions = mixed_actions(episodes, seed)
        s0, o0, states, obs = compiled(setting)(episodes, actions)
        out = dict(states0=s0, obs0=o0, states=states, obs=obs)
        out = jax.tree.map(np.asarray, out)
        out.update(episodes=episodes, visible0=visible0, actions=actions)
        return out

    return run


@pytest.fixture(scope="session")
def observe_fn(grid_configs):
    """setting -> jitted vmapped env.observe (State with leading batch axis -> Observation)."""
    from envs.gridworld import env

    cache = {}

    def get(setting):
        if setting not in cache:
            config = grid_configs[setting]
            cache[setting] = jax.jit(jax.vmap(lambda s: env.observe(s, config)))
        return cache[setting]

    return get
