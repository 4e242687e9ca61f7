"""CompILE grid world, setting mo1g: `python -m experiments.compile_mo1g --help`."""
from experiments.gridworld.cli import main

if __name__ == "__main__":
    main("mo1g")
