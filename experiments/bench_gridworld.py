"""Grid-world throughput: episode generation and environment stepping.

`python -m experiments.bench_gridworld --help`; see experiments/bench/gridworld.py.
"""
from experiments.bench.gridworld import main

if __name__ == "__main__":
    raise SystemExit(main())
