"""A text-only probe: do the Kuka relation phrasings teach a tagger to read development ones.

`python -m experiments.kuka_role_probe --help`; see experiments/kuka/role_probe.py.
"""
if __name__ == "__main__":
    from experiments.harness.processes import join_from_argv

    join_from_argv()  # first: jax.distributed before anything touches JAX
    from experiments.kuka.role_probe import main

    main()
