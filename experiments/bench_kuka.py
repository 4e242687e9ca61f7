"""Kuka world throughput: MJX physics steps beside C MuJoCo, seconds per pick-and-place.

`python -m experiments.bench_kuka --help`; see experiments/bench/kuka.py.
"""
from experiments.bench.kuka import main

if __name__ == "__main__":
    raise SystemExit(main())
