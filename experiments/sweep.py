"""Batched evaluation sweeps over planner configurations of any registered task.

`python -m experiments.sweep --help`; see experiments/sweeping/cli.py.
"""
if __name__ == "__main__":
    from experiments.harness.processes import join_from_argv

    join_from_argv()  # first: jax.distributed before anything touches JAX
    from experiments.sweeping.cli import main

    main()
