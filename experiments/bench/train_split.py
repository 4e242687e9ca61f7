"""The time split of one training step of a world's default recipe (experiments.bench_train
--split / --split-only).

Parts, each a separately jitted function on the shapes of the real step, timed after warm-up
(median of --split-repeats calls, each waited for): generation (the recipe's batch_fn, drawn as
diffplan.train.train draws it), the denoiser forward alone, forward+backward
(jax.value_and_grad of diffplan.losses.diffusion_loss), and the full step exactly as
diffplan.train.train runs it (generation, then the jitted step of
diffplan.losses.make_train_step: loss, gradient, clipped AdamW, EMA). Shares are of the full
step. Then the real training loop (diffplan.train.fit through experiments.harness.recipes, as
--train runs it, in a temporary directory) for --split-seconds after its compilation, with
steps/s in windows of --split-window seconds, so that a slowdown after the first minutes shows.
"""
from __future__ import annotations

import sys
import time

from experiments.bench import train_worlds as bw
from experiments.bench.common import LEGENDS
from experiments.harness import core as harness, tables

SYNC_EVERY = 4
"""The sustained run logs (and so waits for its steps) every this many steps: its time marks."""


def add_flags(parser) -> None:
    parser.add_argument("--split", action="store_true",
                        help="also measure the time split of a training step (before the "
                             "training-to-target run)")
    parser.add_argument("--split-only", action="store_true",
                        help="measure the time split of a training step and exit (no training "
                             "to target; nothing is written to --train-dir)")
    parser.add_argument("--split-seconds", type=float, default=60.0,
                        help="seconds of the sustained run of the real training loop, after its "
                             "compilation (default 60)")
    parser.add_argument("--split-window", type=float, default=10.0,
                        help="steps/s is reported per window of this many seconds of the "
                             "sustained run (default 10)")
    parser.add_argument("--split-repeats", type=int, default=10,
                        help="timed calls of each part after warm-up; the median is reported "
                             "(default 10)")


def check_flags(parser, args) -> None:
    if args.split_seconds <= 0 or args.split_window <= 0:
        parser.error("--split-seconds and --split-window must be > 0, got "
                     f"{args.split_seconds} and {args.split_window}")
    if args.split_window > args.split_seconds:
        parser.error(f"--split-window ({args.split_window}) must be <= --split-seconds "
                     f"({args.split_seconds})")
    if args.split_repeats < 1:
        parser.error(f"--split-repeats must be >= 1, got {args.split_repeats}")


def _parts(world, model_size: str, batch_size, repeats: int, bar, settings=()
           ) -> tuple[dict, dict, int]:
    """({part: median ms}, {part: first-call seconds}, batch size) of the four parts."""
    import functools

    import jax
    import numpy as np

    from diffplan import sharding as shd
    from diffplan.denoiser import Denoiser
    from diffplan.losses import diffusion_loss, make_train_step
    from diffplan.schedule import cosine_schedule
    # The generation call of diffplan.train.train's step (split key, batch_fn, placement).
    from diffplan.train import draw_batch
    from diffplan.train_state import init_train_state, step_key

    bar.set_postfix_str("initial state")
    model_config, config, recipe = bw.training(world, model_size, 1, settings,
                                               batch_size=batch_size)
    model, mesh = Denoiser(model_config), shd.data_mesh()
    draw = functools.partial(draw_batch, batch_fn=recipe.batch_fn(),
                             batch_size=config.batch_size, mesh=mesh)
    train_step = make_train_step(model, config, mesh=mesh)
    state = shd.replicate(init_train_state(model, config, recipe.init_batch()), mesh)
    ab = cosine_schedule(config.num_train_timesteps).alphas_cumprod
    G, prediction = config.num_gen_channels, config.prediction
    forward = jax.jit(lambda p, x, t, tokens: model.apply({"params": p}, x, t, tokens))
    loss_grad = jax.jit(jax.value_and_grad(
        lambda p, batch, key: diffusion_loss(p, model.apply, batch, key, ab, G, prediction,
                                             config.timestep_power)[0]))
    begin = time.perf_counter()
    batch, _ = jax.block_until_ready(draw(step_key(0, 0)))
    compile_s = {"generation": time.perf_counter() - begin}  # its first call: compilation
    t = jax.random.randint(jax.random.PRNGKey(1), batch.x0.shape[:1], 0, ab.shape[0])
    calls = {
        "generation": lambda key: draw(key),
        "forward": lambda key: forward(state.params, batch.x0, t, batch.tokens),
        "forward+backward": lambda key: loss_grad(state.params, batch, key),
        "full step": lambda key: train_step.placed(state, *draw(key)),
    }
    ms = {}
    for name, fn in calls.items():
        bar.set_postfix_str(name)
        begin = time.perf_counter()
        jax.block_until_ready(fn(step_key(0, 0)))
        compile_s.setdefault(name, time.perf_counter() - begin)
        jax.block_until_ready(fn(step_key(0, 1)))  # warm-up
        times = []
        for i in range(repeats):
            begin = time.perf_counter()
            jax.block_until_ready(fn(step_key(0, 2 + i)))
            times.append(time.perf_counter() - begin)
        ms[name] = 1000.0 * float(np.median(times))
        bar.update(1)
    return ms, compile_s, config.batch_size


class _Stop(Exception):
    pass


def _sustained(world, model_size: str, batch_size, seconds: float, window: float,
               progress: bool, settings=()) -> dict:
    """Steps/s of the real training loop over `seconds` after its first time mark, in windows."""
    import tempfile

    from experiments.harness.progress import bar as progress_bar

    marks = []
    bar = progress_bar(total=round(seconds), desc=f"{world.name} sustained training",
                       unit="s", disable=not progress, file=sys.stderr, leave=False,
                       dynamic_ncols=True)

    def callback(step, record):
        marks.append((step, time.perf_counter()))
        elapsed = marks[-1][1] - marks[0][1]
        bar.update(min(round(seconds), int(elapsed)) - bar.n)
        if elapsed >= seconds:
            raise _Stop()

    with bar, tempfile.TemporaryDirectory(prefix="bench_train_split-") as out_dir:
        try:
            bw.run_training(world, out_dir, model_size=model_size,
                            checkpoint_every=world.train_steps, progress=False,
                            callback=callback, settings=settings, batch_size=batch_size,
                            log_every=SYNC_EVERY)
        except _Stop:
            pass
    if len(marks) < 2:
        harness.fail(f"the training loop stopped before it was timed ({len(marks)} marks)")
    (s0, t0), (s1, t1) = marks[0], marks[-1]
    windows, (ws, wt) = [], marks[0]
    for i, (s, t) in enumerate(marks[1:]):
        if t - wt >= window or i == len(marks) - 2:
            windows.append({"start": wt - t0, "seconds": t - wt, "steps": s - ws,
                            "steps_per_second": (s - ws) / max(t - wt, 1e-9)})
            ws, wt = s, t
    return {"seconds": t1 - t0, "steps": s1 - s0,
            "steps_per_second": (s1 - s0) / max(t1 - t0, 1e-9), "windows": windows,
            "window": window, "sync_every": SYNC_EVERY}


def measure(world, args) -> dict:
    """The split of world's step (args: --model-size, --batch-size, --split-*, --no-progress)."""
    from experiments.harness.progress import bar as progress_bar

    progress = not args.no_progress
    with progress_bar(total=4, desc=f"{world.name} step parts (compile, time)", unit="part",
                      disable=not progress, file=sys.stderr, leave=False,
                      dynamic_ncols=True) as bar:
        ms, compile_s, batch = _parts(world, args.model_size, args.batch_size,
                                      args.split_repeats, bar, args.set)
    full = ms["full step"]
    sustained = _sustained(world, args.model_size, batch, args.split_seconds, args.split_window,
                           progress, args.set)
    sustained["examples_per_second"] = sustained["steps_per_second"] * batch
    return {"world": world.name, "model_size": args.model_size, "batch_size": batch,
            "repeats": args.split_repeats, "machine": harness.machine(),
            "parts": [{"part": name, "ms": v, "share": 100.0 * v / full,
                       "compile_seconds": compile_s[name]} for name, v in ms.items()],
            "steps_per_second": 1000.0 / full, "examples_per_second": 1000.0 * batch / full,
            "sustained": sustained}


def format_split(split: dict) -> str:
    """The split as a table and a few lines of text."""
    columns = (("part", "{:<18}", "part"), ("ms", "{:>9.2f}", "ms"),
               ("share", "{:>7.1f}", "% step"), ("compile_seconds", "{:>10.1f}", "compile s"))
    sus = split["sustained"]
    windows = " ".join(f"{w['steps_per_second']:.2f}" for w in sus["windows"])
    return "\n".join([
        f"time split of a training step ({split['world']}, {split['model_size']} model, batch "
        f"{split['batch_size']}; median of {split['repeats']} calls after warm-up; "
        f"{split['machine']}):",
        tables.format_table(split["parts"], columns, LEGENDS["train_split"]),
        f"full step: {split['steps_per_second']:.2f} steps/s, "
        f"{split['examples_per_second']:.1f} examples/s",
        f"training loop over {sus['seconds']:.1f} s: {sus['steps']} steps, "
        f"{sus['steps_per_second']:.2f} steps/s, {sus['examples_per_second']:.1f} examples/s",
        f"steps/s per {sus['window']:g} s window: {windows}"])
