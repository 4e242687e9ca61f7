"""Kuka block world, rearrangement (the paper's Table 2).

`python -m experiments.kuka_rearrangement --help` lists the flags; see experiments/kuka/cli.py.
"""
from experiments.kuka.cli import main

if __name__ == "__main__":
    main("rearrangement")
