"""Kuka block world, rearrangement (the paper's Table 2).

`python -m experiments.kuka_rearrangement --help` lists the flags; see experiments/kuka_cli.py.
"""
from experiments.kuka_cli import main

if __name__ == "__main__":
    main("rearrangement")
