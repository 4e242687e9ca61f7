"""Trains the baselines (BC, CQL, DD-style) of either world and ships them.

`python -m experiments.train_baselines --help`; see experiments/shipping/train_baselines.py.
"""
from experiments.shipping.train_baselines import main

if __name__ == "__main__":
    main()
