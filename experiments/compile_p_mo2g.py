"""CompILE grid world, setting p_mo2g: `python -m experiments.compile_p_mo2g --help`."""
from experiments.gridworld.cli import main

if __name__ == "__main__":
    main("p_mo2g")
