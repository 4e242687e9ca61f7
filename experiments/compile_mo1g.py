"""CompILE grid world, setting mo1g: `python -m experiments.compile_mo1g --help`."""
from experiments.compile_common import main

if __name__ == "__main__":
    main("mo1g")
