"""The paper's ablation (Table 4) on MO1G and P-MO2G, each row a model we train.

`python -m experiments.ablation_compile --help`; see experiments/gridworld/ablation.py.
"""
from experiments.gridworld.ablation import main

if __name__ == "__main__":
    main()
