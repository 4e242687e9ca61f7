"""The benchmarks (``python -m experiments.bench_*``): ratios measured side by side in one run.
``common``, ``peak``, ``workload`` and ``eager`` are shared; ``train`` runs over
``train_worlds`` and ``train_split``."""
