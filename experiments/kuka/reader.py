"""Train the Kuka world's reader: taggers that read which block of each relation sentence is the
upper one, so that an instruction in any phrasing can be restated canonically for the planner.

Each tagger (``diffplan.reader``) is trained from its own seed on instructions in the training
phrasings only (canonical, the training paraphrases, the training-only extras); the development
phrasings are read only in the table this prints: % of 1000 instructions of the validation key
(seed 1000) restated exactly as the canonical instruction of the same relations.

    python -m experiments.train_reader --out checkpoints/kuka_reader
    python -m experiments.kuka_rearrangement --language all --reader checkpoints/kuka_reader
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Sequence

from experiments.harness import cli, core as harness, tables

READ_SENTENCES = 1000
PHRASINGS = ("canonical", "paraphrased", "development")
"""What the table reads; never the sealed held-out phrasings ("heldout"): a reader is measured on
them once, at the end, by the Kuka CLIs, and nothing is chosen on them."""


def build_parser() -> argparse.ArgumentParser:
    from envs.kuka import reader

    parser = argparse.ArgumentParser(
        prog="python -m experiments.train_reader",
        description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="where to write the reader (a new or empty directory)")
    cli.add_tagger_flags(parser, seeds=",".join(map(str, reader.SEEDS)), steps=reader.STEPS,
                         batch=reader.BATCH, unit="instructions")
    return parser


def main(argv: Sequence[str] | None = None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    seeds = list(harness.parse_seeds(parser, args))
    cli.check_at_least(parser, "--steps", args.steps, 1)
    cli.check_output_dir(parser, "--out", args.out)
    if os.path.isdir(args.out) and os.listdir(args.out):
        parser.error(f"--out {args.out!r} is not empty; give a new directory (nothing is "
                     "overwritten)")
    cli.check_output_file(parser, "--json", args.json)
    import jax
    from experiments.harness.progress import bar as progress_bar

    from diffplan.reader import save_reader, train_reader
    from envs.kuka import reader

    config = reader.reader_config()
    start = time.time()
    with progress_bar(total=len(seeds), desc="reader", unit="tagger",
                      disable=args.no_progress, file=sys.stderr, leave=False) as bar:
        params = train_reader(config, reader.role_batch, seeds, args.steps,
                              progress=lambda: bar.update(1))
    minutes = (time.time() - start) / 60
    key = jax.random.PRNGKey(harness.VALIDATION_SEED)
    rates = {p: reader.read_rate(config, params, key, READ_SENTENCES, p) for p in PHRASINGS}
    command = "python -m experiments.train_reader " + " ".join(
        sys.argv[1:] if argv is None else argv)
    save_reader(args.out, config, params, {"command": command, "seeds": seeds,
                                           "steps": args.steps, "minutes": minutes,
                                           "read_validation": rates})
    print(f"instructions restated canonically, % of {READ_SENTENCES} (validation seed "
          f"{harness.VALIDATION_SEED}); {len(seeds)} taggers x {args.steps} steps, "
          f"{minutes:.1f} min")
    print(tables.format_table([{"method": "reader", **rates}],
                              [("method", "{}", "")] + [(p, "{:11.1f}", p) for p in PHRASINGS],
                              [(" / ".join(PHRASINGS), "% of the instructions in those phrasings "
                                                       "restated exactly as the canonical one")]))
    print(f"wrote {args.out}")
    result = {"experiment": "train_reader", "out": args.out, "seeds": seeds,
              "steps": args.steps, "minutes": minutes, "read": rates,
              "machine": harness.machine()}
    if args.json:
        cli.write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
