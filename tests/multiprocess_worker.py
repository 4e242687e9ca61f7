"""One process of a multi-process training run for tests/test_multiprocess.py: the toy denoiser
(tests/toy_denoiser.py) trained through ``diffplan.train.train``, joined with the CLIs' flags
(``experiments.harness.processes``), so the test drives the real ``jax.distributed`` path.

    python tests/multiprocess_worker.py OUT_DIR --coordinator 127.0.0.1:PORT \\
        --num-processes 2 --process-id I

Prints the step it resumes from (``resume: N``, 0 for a fresh run) before training.
"""
import argparse
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.dirname(HERE), HERE]

TRAIN = dict(seed=1, steps=200, batch_size=16, lr=1e-2, warmup_steps=10,
             checkpoint_every=50, log_every=1)
"""The run: the same global batch with one process or several."""


def run(out_dir: str, progress: bool = False):
    """Trains the toy denoiser into out_dir (resuming); returns diffplan.train's result."""
    from diffplan.train import TrainConfig, train
    from toy_denoiser import G, TinyConfig, TinyDenoiser, toy_batch_fn

    config = TrainConfig(num_gen_channels=G, **TRAIN)
    return train(TinyDenoiser(TinyConfig()), TinyConfig(), config, toy_batch_fn, out_dir,
                 progress=progress, tensorboard=False)


def main():
    from experiments.harness import processes

    parser = argparse.ArgumentParser()
    parser.add_argument("out_dir")
    processes.add_process_flags(parser)
    args = parser.parse_args()
    processes.start(parser, args)
    from diffplan import checkpoint as ckpt
    from diffplan.jax_cache import enable_compilation_cache

    enable_compilation_cache()
    print(f"resume: {ckpt.latest_step(args.out_dir) or 0}", flush=True)
    run(args.out_dir)
    print("done", flush=True)


if __name__ == "__main__":
    main()
