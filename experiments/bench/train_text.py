"""Token ids against pretrained text features, side by side (experiments.bench_train
--text-compare): the grid world's default recipe trained on the grammar's token ids and on
the frozen pretrained text encoder's features (``Recipe.text = "pretrained"``, the same model
size otherwise), each part timed alternately in one process so that the machine's load falls
on both alike; then the encoder's time per instruction.

Parts (median ms over --split-repeats rounds; in each round every variant once, after
warm-up; wall time and the process's CPU time, which other jobs on a shared machine disturb
less): the full training step as diffplan.train.train runs it (the batch drawn, with the
features assembled from the sentence table inside the jitted generation, then the step), and
one denoiser call at the evaluation batch as the planner makes it (a plan's forward, the
per-move planning cost; for the features model on the text context the planner computed once
per episode, ``LoadedDenoiser.prepare``). The encoder: a fresh encoder (nothing in memory)
encodes N new instructions (P-MO2G, training and held-out phrasings) in one batch, and one
instruction alone.
"""
from __future__ import annotations

import time

from experiments.bench import train_worlds as bw
from experiments.bench.common import LEGENDS
from experiments.harness import tables

VARIANTS = ("tokens", "pretrained")


def _variant(world, model_size: str, batch_size, settings, text: str, eval_batch: int):
    """(full step fn(key), denoiser call fn(), batch size) of one instruction input."""
    import functools

    import jax

    from diffplan import sharding as shd
    from diffplan.denoiser import Denoiser
    from diffplan.losses import make_train_step
    from diffplan.train import draw_batch, with_sentence_shapes
    from diffplan.train_state import init_train_state

    model_config, config, recipe = bw.training(world, model_size, 1,
                                               list(settings) + [f"text={text}"],
                                               batch_size=batch_size)
    model, mesh = Denoiser(model_config), shd.data_mesh()
    sentences = recipe.sentences()
    init = with_sentence_shapes(recipe.init_batch(), sentences)
    table = None if sentences is None else shd.replicate(sentences, mesh)
    draw = functools.partial(draw_batch, batch_fn=recipe.batch_fn(),
                             batch_size=config.batch_size, mesh=mesh)
    train_step = make_train_step(model, config, mesh=mesh)
    state = shd.replicate(init_train_state(model, config, init), mesh)
    batch, _ = draw(jax.random.PRNGKey(0), table)
    x = jax.numpy.tile(batch.x0[:1], (eval_batch, 1, 1, 1))
    tokens = jax.numpy.tile(batch.tokens[:1], (eval_batch,) + (1,) * (batch.tokens.ndim - 1))
    t = jax.numpy.zeros((eval_batch,), jax.numpy.int32)
    if sentences is not None:  # what the planner keeps: the text context, computed once
        tokens = model.apply({"params": state.params}, tokens, method="encode_text")
    forward = jax.jit(lambda p, x, t, tokens: model.apply({"params": p}, x, t, tokens))
    return ((lambda key: train_step.placed(state, *draw(key, table))),
            (lambda: forward(state.params, x, t, tokens)), config.batch_size)


def _encoder_times(count: int, alone: int = 5) -> dict:
    """ms (wall and CPU) per instruction of a fresh encoder on `count` new P-MO2G instructions
    in one batch, and on one instruction alone (the median of `alone` fresh encoders);
    compilation excluded: a warm-up encoder runs first."""
    import numpy as np

    from diffplan.instruction import InstructionEncoder
    from envs.gridworld import grammar
    from envs.gridworld.sentences import FEATURE_TOKENS, instruction_encoder

    rng = np.random.default_rng(0)
    texts = []
    for _ in range(count + 1):
        ref, target = rng.choice(np.arange(1, 16), 2, replace=False)
        texts.append(grammar.render("p_mo2g", int(rng.integers(12)), int(ref), int(target),
                                    int(rng.integers(8))))
    base = instruction_encoder().encoder
    InstructionEncoder(base, FEATURE_TOKENS).encode(texts)  # compile every width

    def timed(batch):
        fresh = InstructionEncoder(base, FEATURE_TOKENS)
        begin, begin_cpu = time.perf_counter(), time.process_time()
        fresh.encode(batch)
        return time.perf_counter() - begin, time.process_time() - begin_cpu

    batch = timed(texts[1:])
    one = np.median([timed(texts[0]) for _ in range(alone)], axis=0)
    return {"instructions": count, "ms_per_instruction_batch": 1000.0 * batch[0] / count,
            "cpu_ms_per_instruction_batch": 1000.0 * batch[1] / count,
            "ms_one_instruction": 1000.0 * one[0], "cpu_ms_one_instruction": 1000.0 * one[1],
            "sentences_per_instruction": float(np.mean([len(fresh.sentences_of(t))
                                                        for t in texts]))}


def compare(world, args, eval_batch: int = 64, encoder_count: int = 256) -> dict:
    """Times of both variants ({part: {variant: ms}}) and of the encoder."""
    import jax
    import numpy as np

    from diffplan.train_state import step_key

    if world.name != "gridworld":
        raise ValueError("--text-compare measures the grid world's recipe (the Kuka world's "
                         "pretrained features are not wired yet)")
    built = {v: _variant(world, args.model_size, args.batch_size, args.set, v, eval_batch)
             for v in VARIANTS}
    parts = ("full step", "denoiser call")
    wall = {part: {v: [] for v in VARIANTS} for part in parts}
    cpu = {part: {v: [] for v in VARIANTS} for part in parts}
    for v, (step, call, _) in built.items():  # compile and warm up
        for i in range(2):
            jax.block_until_ready(step(step_key(0, i)))
            jax.block_until_ready(call())
    for r in range(args.split_repeats):
        for v, (step, call, _) in built.items():
            for part, fn in zip(parts, (lambda: step(step_key(0, 2 + r)), call)):
                begin, begin_cpu = time.perf_counter(), time.process_time()
                jax.block_until_ready(fn())
                wall[part][v].append(time.perf_counter() - begin)
                cpu[part][v].append(time.process_time() - begin_cpu)

    def medians(times):
        return {part: {v: 1000.0 * float(np.median(x)) for v, x in by.items()}
                for part, by in times.items()}

    return {"world": world.name, "model_size": args.model_size,
            "batch_size": built["tokens"][2], "eval_batch": eval_batch,
            "rounds": args.split_repeats, "ms": medians(wall), "cpu_ms": medians(cpu),
            "encoder": _encoder_times(encoder_count)}


def format_compare(result: dict) -> str:
    cpu = result["cpu_ms"]
    rows = [{"part": f"{part} ({v})", "ms": ms, "ratio": ms / by["tokens"],
             "cpu": cpu[part][v], "cpu_ratio": cpu[part][v] / cpu[part]["tokens"]}
            for part, by in result["ms"].items() for v, ms in by.items()]
    columns = (("part", "{:<28}", "part"), ("ms", "{:>9.2f}", "ms"),
               ("ratio", "{:>10.3f}", "vs tokens"), ("cpu", "{:>9.2f}", "cpu ms"),
               ("cpu_ratio", "{:>10.3f}", "cpu vs"))
    enc = result["encoder"]
    return "\n".join([
        f"token ids vs pretrained features ({result['world']}, {result['model_size']} model, "
        f"training batch {result['batch_size']}, denoiser call at batch {result['eval_batch']}; "
        f"{result['rounds']} alternating rounds):",
        tables.format_table(rows, columns, LEGENDS["train_text"]),
        f"text encoder: {enc['ms_per_instruction_batch']:.1f} ms (CPU "
        f"{enc['cpu_ms_per_instruction_batch']:.1f}) per instruction in a batch of "
        f"{enc['instructions']} new P-MO2G instructions ({enc['sentences_per_instruction']:.2f} "
        f"sentences each), {enc['ms_one_instruction']:.1f} ms (CPU "
        f"{enc['cpu_ms_one_instruction']:.1f}) for one alone"])
