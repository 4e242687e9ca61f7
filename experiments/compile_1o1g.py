"""CompILE grid world, setting 1o1g: `python -m experiments.compile_1o1g --help`."""
if __name__ == "__main__":
    from experiments.harness.processes import join_from_argv

    join_from_argv()  # first: jax.distributed before anything touches JAX
    from experiments.gridworld.cli import main

    main("1o1g")
