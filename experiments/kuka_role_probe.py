"""A text-only probe: do the Kuka relation phrasings teach a tagger to read development ones.

`python -m experiments.kuka_role_probe --help`; see experiments/kuka/role_probe.py.
"""
from experiments.kuka.role_probe import main

if __name__ == "__main__":
    main()
