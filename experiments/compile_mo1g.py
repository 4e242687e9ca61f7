"""CompILE grid world, setting mo1g: `python -m experiments.compile_mo1g --help`."""
if __name__ == "__main__":
    from experiments.harness.processes import join_from_argv

    join_from_argv()  # first: jax.distributed before anything touches JAX
    from experiments.gridworld.cli import main

    main("mo1g")
