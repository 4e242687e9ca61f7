"""CompILE grid world, setting 1o1g: `python -m experiments.compile_1o1g --help`."""
from experiments.gridworld.cli import main

if __name__ == "__main__":
    main("1o1g")
