"""Kuka block world, stacking (the paper's Table 2).

`python -m experiments.kuka_stacking --help` lists the flags; see experiments/kuka/cli.py.
"""
if __name__ == "__main__":
    from experiments.harness.processes import join_from_argv

    join_from_argv()  # first: jax.distributed before anything touches JAX
    from experiments.kuka.cli import main

    main("stacking")
