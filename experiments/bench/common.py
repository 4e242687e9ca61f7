"""What the throughput benchmarks (bench_gridworld, bench_kuka, bench_unet) share: list-valued
flags, the --json / --no-cache flags and their checks, timing loops, the result file, and the
legends printed under every benchmark's table (LEGENDS)."""
from __future__ import annotations

import argparse
import os
import time

from experiments.harness.tables import legend

FIRST_CALL = ("the first call's seconds: compilation (or its load from the compilation cache) and "
              "one run")
TIMED = "median over the timed calls, compilation excluded"
LEGENDS = {
    "gridworld": (("kind", "what is timed"), ("batch", "episodes per call"),
                  ("steps/call", "env steps per episode per call"),
                  ("per second", f"units (unit column) per second, {TIMED}"),
                  ("best", "the fastest call's rate"), ("target", "the rate to meet"),
                  ("ratio", "per second / target"), ("compile s", FIRST_CALL)),
    "unet": (("params", "parameters, millions"), ("ms", f"milliseconds per call, {TIMED}"),
             ("best ms", "the fastest call"), ("GFLOP", "per call, from XLA's cost analysis"),
             ("GFLOP/s", "GFLOP / ms"), ("% peak", "of the matmul just before each call"),
             ("ms/plan", "sampler call ms / batch"), ("compile s", FIRST_CALL)),
    "kuka": (("steps/s", f"env steps per second (batch x steps per call / seconds), {TIMED}"),
             ("best steps/s", "the fastest call's"), ("s/call", f"seconds per call, {TIMED}"),
             ("first s", FIRST_CALL)),
    "planner": (("batch", "episodes per call"),
                ("episodes/s", "episodes per second, compilation excluded"),
                ("calls/s", "denoiser calls per second"),
                ("compile s", "lowering + XLA compilation, the persistent cache off"),
                ("peak GB", "the process's peak resident memory up to this row"),
                ("jitted/this", "the jitted row's episodes/s over this row's (bound: this row's "
                                "share of the ceiling)")),
    "train": (("step", "training step of the evaluation"),
              ("train min", "training wall minutes so far, compilation included, evaluations "
                            "excluded"),
              ("SR, SR_ord, F1 / column SRs", "on the validation episodes (seed 1000), %")),
    "train_split": (("ms", f"milliseconds per call, {TIMED}"), ("% step", "of the full step"),
                    ("compile s", FIRST_CALL)),
    "train_text": (("ms", "milliseconds per call, median over the alternating rounds, "
                          "compilation excluded"),
                   ("vs tokens", "ratio to the token-id model's median in the same rounds"),
                   ("cpu ms", "the process's CPU milliseconds per call (all threads), median"),
                   ("cpu vs", "its ratio to the token-id model's")),
}
"""What each benchmark table's columns mean (experiments.harness.tables.legend)."""


def typed_list(type_):
    """An argparse type: comma-separated values of type_."""
    def parse(text):
        try:
            return [type_(v) for v in text.split(",") if v]
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from e
    return parse


def int_list(text: str) -> list[int]:
    """An argparse type: comma-separated positive integers."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}")
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def add_output_flags(parser: argparse.ArgumentParser) -> None:
    """--json PATH and --no-cache."""
    parser.add_argument("--json", metavar="PATH", default=None, help="write the results here")
    parser.add_argument("--no-cache", action="store_true",
                        help="do not use the persistent compilation cache (compile_seconds then "
                             "measures real compilation)")


def check_positive(parser, args, names) -> None:
    """Each of args.<name> (names with underscores) is >= 1."""
    for name in names:
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")


def start(parser, args) -> None:
    """Checks --json's directory, then turns the compilation cache on unless --no-cache."""
    if args.json and not os.path.isdir(os.path.dirname(os.path.abspath(args.json))):
        parser.error(f"--json {args.json}: directory does not exist")
    if not args.no_cache:
        from diffplan.jax_cache import enable_compilation_cache

        enable_compilation_cache()


def timed(fn, args_list) -> list[float]:
    """Seconds of each call fn(*args) (blocking on the result)."""
    import jax

    times = []
    for args in args_list:
        begin = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - begin)
    return times


def first_and_timed(fn, repeats: int):
    """(first call seconds, [seconds of `repeats` more calls]); fn blocks until it is done."""
    begin = time.perf_counter()
    fn()
    first = time.perf_counter() - begin
    return first, timed(fn, [()] * repeats)


def finish(args, result: dict) -> None:
    """Writes the result to --json (atomically), if given."""
    if args.json:
        from experiments.harness import cli

        cli.write_json(args.json, result)
