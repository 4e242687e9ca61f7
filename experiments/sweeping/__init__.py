"""Batched evaluation sweeps: the configurations (``config``), running them with compiled
functions reused (``run``), tables, CSV and Pareto figures (``output``) and ``main`` (``cli``).
The sweep files themselves are in ``experiments/sweeps/``."""
