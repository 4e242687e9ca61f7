"""Exports a training run as a shipped evaluation checkpoint with its NOTE.md.

`python -m experiments.ship_checkpoint --help`; see experiments/shipping/denoiser.py.
"""
from experiments.shipping.denoiser import main

if __name__ == "__main__":
    main()
