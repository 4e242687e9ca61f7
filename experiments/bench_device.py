"""What the backend present (CPU, GPU, TPU) does for the main jobs: on-the-fly episodes per second
at batch 256 / 1024 / 4096, training steps per second, the Kuka rollout's episodes per second.

`python -m experiments.bench_device --help`; see experiments/bench/device.py.
"""
from experiments.bench.device import main

if __name__ == "__main__":
    main()
