"""Training cost of either world: the training time to reach a success rate.

`python -m experiments.bench_train --help`; see experiments/bench/train.py.
"""
from experiments.bench.train import main

if __name__ == "__main__":
    main()
