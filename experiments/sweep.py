"""Batched evaluation sweeps over planner configurations of any registered task.

`python -m experiments.sweep --help`; see experiments/sweeping/cli.py.
"""
from experiments.sweeping.cli import main

if __name__ == "__main__":
    main()
