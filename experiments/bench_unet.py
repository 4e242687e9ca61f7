"""Denoiser (UNet) throughput on whatever JAX device is present.

`python -m experiments.bench_unet --help`; see experiments/bench/unet.py.
"""
from experiments.bench.unet import main

if __name__ == "__main__":
    raise SystemExit(main())
