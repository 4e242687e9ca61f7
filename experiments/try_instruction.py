"""One episode planned for your own instruction: `python -m experiments.try_instruction "First
go to the apple, then find the pear north of it." --setting p_mo2g --seed 3 --figure out.png`.

`--world gridworld` (default; experiments/gridworld/try_instruction.py); `--world kuka`: not
yet. `python -m experiments.try_instruction --help`.
"""
from experiments.gridworld.try_instruction import main

if __name__ == "__main__":
    main()
