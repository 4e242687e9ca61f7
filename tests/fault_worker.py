"""A training process for tests/test_faults.py (run as a script in a subprocess, so it can be
killed with SIGKILL or run under a file-size limit).

    python tests/fault_worker.py OUT_DIR STEPS [--limit-after STEP] [--dump NPZ]

trains the toy denoiser (tests/toy_denoiser.py) for STEPS steps with a checkpoint every 4
steps, resuming if OUT_DIR holds a checkpoint. --limit-after STEP: after STEP steps, every
file this process writes is limited to 3000 bytes (RLIMIT_FSIZE), as a full disk would.
--dump NPZ: write the final parameters and optimizer state to NPZ. The exit code is 0 on
success and 3 on a CheckpointWriteError or OutputWriteError (its message on stderr).
"""
import argparse
import os
import resource
import signal
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import jax  # noqa: E402
import numpy as np  # noqa: E402

from diffplan.checkpoint import CheckpointWriteError  # noqa: E402
from diffplan.train import OutputWriteError  # noqa: E402
from diffplan.jax_cache import enable_compilation_cache  # noqa: E402
from diffplan.train import TrainConfig, train  # noqa: E402
from toy_denoiser import G, TinyConfig, TinyDenoiser, toy_batch_fn  # noqa: E402

CHECKPOINT_EVERY = 4


def config(steps: int) -> TrainConfig:
    return TrainConfig(seed=5, steps=steps, batch_size=4, lr=3e-3, warmup_steps=2,
                       num_gen_channels=G, checkpoint_every=CHECKPOINT_EVERY, log_every=1)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("out_dir")
    p.add_argument("steps", type=int)
    p.add_argument("--limit-after", type=int, default=None)
    p.add_argument("--dump", default=None)
    args = p.parse_args()
    enable_compilation_cache()

    def callback(step, record):
        if args.limit_after is not None and step == args.limit_after:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a failed write, not a killed process
            resource.setrlimit(resource.RLIMIT_FSIZE, (3000, resource.RLIM_INFINITY))
        print(f"step {step}", flush=True)

    try:
        result = train(TinyDenoiser(TinyConfig()), TinyConfig(), config(args.steps),
                       toy_batch_fn, args.out_dir, progress=False, tensorboard=False,
                       callback=callback)
    except (CheckpointWriteError, OutputWriteError) as e:
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        raise SystemExit(3)
    if args.dump:
        leaves = jax.tree_util.tree_leaves((result.state.params, result.state.ema_params,
                                            result.state.opt_state))
        np.savez(args.dump, *[np.asarray(x) for x in leaves])


if __name__ == "__main__":
    main()
