"""Planner throughput: the jitted, vmapped rollout against the same model driven eagerly.

`python -m experiments.bench_planner --help`; see experiments/bench/planner.py.
"""
from experiments.bench.planner import main

if __name__ == "__main__":
    raise SystemExit(main())
