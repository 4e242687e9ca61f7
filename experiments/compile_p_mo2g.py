"""CompILE grid world, setting p_mo2g: `python -m experiments.compile_p_mo2g --help`."""
if __name__ == "__main__":
    from experiments.harness.processes import join_from_argv

    join_from_argv()  # first: jax.distributed before anything touches JAX
    from experiments.gridworld.cli import main

    main("p_mo2g")
