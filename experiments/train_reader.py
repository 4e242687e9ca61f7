"""Trains and saves the Kuka world's reader (checkpoints/kuka_reader).

`python -m experiments.train_reader --help`; see experiments/kuka/reader.py.
"""
from experiments.kuka.reader import main

if __name__ == "__main__":
    main()
