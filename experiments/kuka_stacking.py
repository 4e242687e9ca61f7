"""Kuka block world, stacking (the paper's Table 2): `python -m experiments.kuka_stacking --help`."""
from experiments.kuka_common import main

if __name__ == "__main__":
    main("stacking")
