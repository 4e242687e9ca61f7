"""Does a grid-world denoiser read which object its instruction names (a diagnostic on its own
training batches): `python -m experiments.goal_probe --checkpoint DIR`; see
experiments/gridworld/goal_probe.py and `--help`."""
from experiments.gridworld.goal_probe import main

if __name__ == "__main__":
    main()
