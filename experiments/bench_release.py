"""The paper release's P-MO2G denoiser timed beside ours, in the same run.

`python -m experiments.bench_release --help`; see experiments/bench/release.py.
"""
from experiments.bench.release import main

if __name__ == "__main__":
    raise SystemExit(main())
