"""One episode planned for your own instruction: `python -m experiments.try_instruction "First
go to the apple, then find the pear north of it." --setting p_mo2g --seed 3 --figure out.png`
(the grid world), or `python -m experiments.try_instruction "Put the red block on the blue
block, please." --world kuka --task stacking --seed 3 --video out.gif` (the Kuka blocks).

`--world gridworld` (default): experiments/gridworld/try_instruction.py; `--world kuka`:
experiments/kuka/try_instruction.py. `python -m experiments.try_instruction --help` shows the
grid world's flags, `--world kuka --help` the Kuka world's.
"""
from __future__ import annotations

import argparse
import sys
from typing import Sequence


def world_of(argv: Sequence[str]) -> str:
    """The --world an argument list asks for ("gridworld" when it names none); a bad value
    is left to the world's parser to refuse."""
    peek = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    peek.add_argument("--world", default="gridworld")
    try:
        known, _ = peek.parse_known_args(list(argv))
    except argparse.ArgumentError:  # "--world" without a value: the grid parser says so
        return "gridworld"
    return known.world


def main(argv: Sequence[str] | None = None) -> dict:
    """Runs the try_instruction of the world argv names (default sys.argv[1:]); returns its
    outcome dict."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if world_of(argv) == "kuka":
        from experiments.kuka.try_instruction import main as run
    else:
        from experiments.gridworld.try_instruction import main as run
    return run(argv)


if __name__ == "__main__":
    main()
