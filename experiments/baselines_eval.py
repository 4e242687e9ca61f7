"""The grid-world baselines' rows (BC, CQL, DD-style; the paper's Table 1), reference agents' too.

`python -m experiments.baselines_eval --help`; see experiments/gridworld/baselines.py.
"""
from experiments.gridworld.baselines import main

if __name__ == "__main__":
    main()
