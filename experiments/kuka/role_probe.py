"""Can the Kuka relation phrasings teach a reader to generalise? A text-only probe, in minutes.

A small tagger (diffplan's TextEncoder, a linear head) is trained, from scratch for each seed, on
single relation sentences in the training phrasings (``envs.kuka.grammar``, templates 0-7, plus
any ``--extra`` phrasing) to say of every block word whether it names the upper or the lower
block. It is then read on the development phrasings (8-11), which training never shows (the
sealed held-out phrasings are never read here: nothing is chosen on them). A
sentence counts as read when both of its block words get their role. This is the part of
language that a planner must get from the words alone; the probe asks whether a set of training
phrasings allows it at all, before an hour of denoiser training is spent on it. It is not the
planner: the denoiser learns its reading from the diffusion loss, not from these labels.

    python -m experiments.kuka_role_probe --seeds 0,1,2
    python -m experiments.kuka_role_probe --extra "Set the {bottom} block below the {top} block."
"""
from __future__ import annotations

import argparse
import sys
from typing import Sequence

from experiments.harness import cli, core as harness, processes, tables

STEPS = 2000
BATCH = 128
EVAL_SENTENCES = 500


def check_extra(templates: Sequence[str]) -> list[str]:
    """The --extra phrasings, or ValueError naming what is wrong with one: each has the slots
    {top} and {bottom} once and only words of the training phrasings (so the development
    phrasings stay made of known words and the vocabulary does not change), and none is a
    development or sealed held-out phrasing."""
    from diffplan import language
    from envs.kuka import grammar

    split = grammar.RELATION_SPLIT
    known = split.training_words()
    never = {**{split.templates[k]: "a development" for k in split.unseen},
             **{split.templates[k]: "a sealed held-out" for k in split.sealed}}
    for template in templates:
        if template in never:
            raise ValueError(f"{template!r} is {never[template]} phrasing; it cannot be "
                             "trained on")
        for slot in grammar.SLOTS:
            if template.count(slot) != 1:
                raise ValueError(f"{template!r} must hold {slot} exactly once")
        unknown = sorted(language.template_words([template], grammar.SLOTS) - known)
        if unknown:
            raise ValueError(f"{template!r}: {unknown[0]!r} is not a word of the training "
                             "phrasings")
    return list(templates)


def compiled(templates):
    """int32 (T, SENTENCE_TOKENS) the templates' token ids, slots as placeholders."""
    import numpy as np
    from envs.kuka import grammar

    return np.stack([grammar.VOCABULARY.compile(t, grammar.SLOTS, grammar.SENTENCE_TOKENS)
                     for t in templates])


def role_batch(key, templates, n: int):
    """n sentences drawn from templates int32 (T, S) with two distinct random blocks:
    (tokens int32 (n, S), roles int32 (n, S) 1 where the token names the lower block,
    named bool (n, S) the block words); jit-able."""
    import jax
    import jax.numpy as jnp
    from diffplan import language
    from envs.kuka import grammar, scene

    k_which, k_blocks = jax.random.split(key)
    which = jax.random.randint(k_which, (n,), 0, templates.shape[0])
    blocks = jax.vmap(lambda k: jax.random.permutation(k, scene.NUM_BLOCKS)[:2])(
        jax.random.split(k_blocks, n))
    slots = grammar.block_token(blocks)
    tokens = jax.vmap(language.fill_slots)(jnp.asarray(templates)[which], slots)
    bottom = tokens == slots[:, 1:2]
    return tokens, bottom.astype(jnp.int32), bottom | (tokens == slots[:, 0:1])


def train_and_read(seed: int, train, held_out, steps: int, word_dropout: float):
    """(training-phrasing rate, [rate of each development template]) in percent of sentences
    read right, for a tagger (``diffplan.reader.Tagger`` over one sentence) trained ``steps``
    steps of BATCH sentences from seed."""
    import jax
    import jax.numpy as jnp
    from diffplan import language
    from diffplan.reader import ReaderConfig, Tagger, train_tagger
    from envs.kuka import grammar, scene

    language.check_dropout_rate(word_dropout)
    block_words = grammar.block_token(jnp.arange(scene.NUM_BLOCKS))
    config = ReaderConfig(len(grammar.VOCAB), grammar.SENTENCE_TOKENS, len(grammar.ROLES))

    def batch(key):
        tokens, roles, named = role_batch(key, train, BATCH)
        if word_dropout:
            tokens = language.drop_words(jax.random.fold_in(key, 1), tokens, word_dropout,
                                         block_words)
        return tokens, roles, named

    params = train_tagger(config, batch, seed, steps)

    def rate(templates):
        tokens, roles, named = role_batch(jax.random.PRNGKey(10_000 + seed), templates,
                                          EVAL_SENTENCES)
        read = Tagger(config).apply(params, tokens).argmax(-1)
        right = jnp.where(named, read == roles, True)
        return 100.0 * float(jnp.all(right, -1).mean())

    return rate(train), [rate(held_out[j:j + 1]) for j in range(held_out.shape[0])]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.kuka_role_probe",
        description=__doc__.split("\n\n")[0] + " Trains a text-only tagger on the Kuka "
        "relation phrasings of training (and --extra ones) and reports how often it reads "
        "the roles of the development phrasings right.")
    parser.add_argument("--extra", action="append", default=[], metavar="TEMPLATE",
                        help="an added training phrasing with the slots {top} and {bottom}, "
                             "made of the training phrasings' words; repeatable")
    parser.add_argument("--broad", action="store_true",
                        help="also train on the grammar's training-only extra phrasings "
                             "(envs.kuka.grammar.EXTRA, what the 'broad' training language "
                             "draws)")
    parser.add_argument("--word-dropout", type=float, default=0.0,
                        help="probability that a non-block word of a training sentence is "
                             "dropped (default 0)")
    cli.add_tagger_flags(parser, seeds="0,1,2", steps=STEPS, batch=BATCH, unit="sentences")
    processes.add_process_flags(parser)  # every process trains the taggers; process 0 writes
    return parser


def main(argv: Sequence[str] | None = None) -> dict:
    from diffplan import language

    parser = build_parser()
    args = parser.parse_args(argv)
    processes.start(parser, args)
    from envs.kuka import grammar

    seeds = list(harness.parse_seeds(parser, args))
    try:
        broad = ([grammar.RELATION_TEMPLATES[k] for k in grammar.EXTRA] if args.broad
                 else [])
        extra = check_extra(broad + [t for t in args.extra if t not in broad])
        language.check_dropout_rate(args.word_dropout, "--word-dropout")
    except ValueError as e:
        parser.error(str(e))
    cli.check_at_least(parser, "--steps", args.steps, 1)
    cli.check_output_file(parser, "--json", args.json)
    from experiments.harness.progress import bar

    split = grammar.RELATION_SPLIT
    train = compiled([grammar.RELATION_TEMPLATES[k] for k in split.training] + extra)
    held = [grammar.RELATION_TEMPLATES[k] for k in split.unseen]
    rows = []
    with bar(total=len(seeds), desc="role probe", unit="tagger", disable=args.no_progress,
             file=sys.stderr, leave=False) as taggers:
        for seed in seeds:
            trained, read = train_and_read(seed, train, compiled(held), args.steps,
                                           args.word_dropout)
            rows.append({"method": f"seed {seed}", "training": trained,
                         **{f"#{k}": r for k, r in zip(split.unseen, read)},
                         "all_development": min(read) == 100.0})
            taggers.update(1)
    columns = [("method", "{}", "tagger", "the tagger's training seed"),
               ("training", "{:9.1f}", "training", "% of training-phrasing sentences read")] + [
        (f"#{k}", "{:7.1f}", f"#{k}") for k in split.unseen]
    print(f"sentences whose block words get their roles, % of {EVAL_SENTENCES} per phrasing "
          f"({args.steps} steps; development: " + "; ".join(
              f"#{k} {t!r}" for k, t in zip(split.unseen, held)) + ")")
    print(tables.format_table(rows, columns, [("#k", "% of development phrasing k's sentences "
                                                        "read (both block words' roles right)")]))
    print(f"taggers that read every development phrasing: "
          f"{sum(r['all_development'] for r in rows)} of {len(rows)}")
    result = {"experiment": "kuka_role_probe", "extra": extra, "steps": args.steps,
              "word_dropout": args.word_dropout, "seeds": seeds,
              "development": dict(zip(map(str, split.unseen), held)), "rows": rows,
              "machine": harness.machine()}
    if args.json:
        cli.write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
