"""What the backend present does for the main jobs (``python -m experiments.bench_device``): the
grid world's on-the-fly planning, training steps of the default grid recipe, and the Kuka
rollout, with the device named. Run it on a machine with an accelerator (``pip install -e
".[cuda12]"``) and on this CPU; docs/benchmarks.md keeps what each printed.

  * on-the-fly: the main job's mode (``compile_p_mo2g --modes on_the_fly``: the shipped
    checkpoint, 10 denoising steps per plan, a plan before every move) on the CLIs' slot pool
    of B slots (``diffplan.rollouts.StreamRollout``) fed 2 x B P-MO2G validation episodes, so
    every slot is busy: the move program compiled first, ``--moves`` moves are timed. Episodes per
    second = B / (seconds per move x L), L the mean moves per episode of the same mode
    measured on ``--length-episodes`` whole episodes (that run's own episodes per second,
    end to end, is printed beside it).
  * training: steps per second of ``compile_p_mo2g --train``'s step (the default recipe and
    model, batch 64: the batch drawn, then loss, gradient, AdamW and EMA), ``--train-steps``
    steps timed after two warm-up steps.
  * Kuka: episodes per second of ``kuka_stacking``'s planner rollout (the shipped checkpoint,
    on-the-fly, MJX physics, the blocks then settled) on ``--kuka-episodes`` episodes in one
    call, timed on a second call (the first compiles).
"""
from __future__ import annotations

import argparse
import functools
import os
import statistics
import time

import numpy as np

from experiments.bench import common as bc

SEED = 1000
"""Validation episodes (never an evaluation seed)."""
PARTS = ("on_the_fly", "train", "kuka")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m experiments.bench_device",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--batch-sizes", type=bc.int_list, default=[256, 1024, 4096],
                   help="slots of the on-the-fly pool")
    p.add_argument("--moves", type=int, default=2, help="timed pool moves per batch size")
    p.add_argument("--length-episodes", type=int, default=64,
                   help="whole on-the-fly episodes run to measure the moves per episode")
    p.add_argument("--train-steps", type=int, default=5, help="timed training steps")
    p.add_argument("--kuka-episodes", type=int, default=4,
                   help="episodes of the timed Kuka call (compiling its MJX program takes "
                        "~6 GB)")
    p.add_argument("--parts", type=bc.typed_list(str), default=list(PARTS),
                   help=f"what to measure, comma-separated of {','.join(PARTS)}")
    bc.add_output_flags(p)
    return p


def device_name() -> str:
    import jax

    d = jax.devices()[0]
    return f"{jax.device_count()} x {d.device_kind} ({d.platform}), jax {jax.__version__}"


def _grid():
    from experiments.gridworld.spec import SPECS
    from experiments.harness.core import load_model

    spec = SPECS["p_mo2g"]
    denoiser, _ = load_model(spec.default_checkpoint())
    return spec, denoiser, spec.task(denoiser.num_gen_channels)


def episode_length(spec, denoiser, task, n: int) -> tuple[float, float]:
    """(mean moves per episode, episodes/s end to end) of on-the-fly on n whole episodes (the
    CLIs' evaluate_mode, batch n; a first call compiles)."""
    from experiments.gridworld import eval as ge

    episodes = ge.eval_episodes(spec.grid_config(), n, SEED)
    ge.evaluate_mode(spec, task, denoiser, episodes, SEED, "on_the_fly", n, progress=False)
    rollout, seconds = ge.evaluate_mode(spec, task, denoiser, episodes, SEED, "on_the_fly", n,
                                        progress=False)
    return float(np.mean(rollout.steps)), n / seconds


def pool_move_seconds(spec, denoiser, task, slots: int, moves: int) -> tuple[float, float]:
    """(median seconds per move of a full pool of `slots` slots, compile seconds)."""
    import jax

    from diffplan.planner import Planner
    from diffplan.rollouts import StreamRollout
    from experiments.gridworld import eval as ge
    from experiments.harness.core import planner_keys

    n = 2 * slots
    episodes = ge.eval_episodes(spec.grid_config(), n, SEED)
    keys = planner_keys(SEED, np.arange(n))
    planner = Planner(denoiser, spec.planner_config("on_the_fly"))
    stream = StreamRollout(task, planner.config, slots)
    advance = jax.jit(functools.partial(stream.advance, max_moves=1))
    # Everything committed to the device, so the pool's carry keeps one placement and the
    # advance program compiles once.
    device = jax.local_devices()[0]
    planner, keys, episodes = jax.device_put((planner, keys, episodes), device)
    carry = jax.device_put(jax.jit(stream.start)(planner, keys, episodes), device)
    begin = time.perf_counter()
    advance = advance.lower(planner, keys, episodes, carry).compile()
    compile_seconds = time.perf_counter() - begin
    times = []
    for _ in range(moves):
        begin = time.perf_counter()
        carry = jax.block_until_ready(advance(planner, keys, episodes, carry))
        times.append(time.perf_counter() - begin)
    return statistics.median(times), compile_seconds


def train_steps_per_second(steps: int) -> tuple[float, int, float]:
    """(steps/s, batch size, first-step seconds) of the default grid recipe's training step."""
    import jax

    from diffplan import sharding as shd
    from diffplan.denoiser import Denoiser
    from diffplan.losses import make_train_step
    from diffplan.train import draw_batch
    from diffplan.train_state import init_train_state, step_key
    from experiments.bench import train_worlds as bw

    model_config, config, recipe = bw.training(bw.WORLDS["gridworld"], "default", 1)
    model, mesh = Denoiser(model_config), shd.data_mesh()
    draw = functools.partial(draw_batch, batch_fn=recipe.batch_fn(),
                             batch_size=config.batch_size, mesh=mesh)
    step = make_train_step(model, config, mesh=mesh)
    state = shd.replicate(init_train_state(model, config, recipe.init_batch()), mesh)
    begin = time.perf_counter()
    state, _ = jax.block_until_ready(step.placed(state, *draw(step_key(0, 0))))
    first = time.perf_counter() - begin
    state, _ = jax.block_until_ready(step.placed(state, *draw(step_key(0, 1))))
    begin = time.perf_counter()
    for i in range(steps):
        state, metrics = step.placed(state, *draw(step_key(0, 2 + i)))
    jax.block_until_ready(metrics)
    return steps / (time.perf_counter() - begin), config.batch_size, first


def kuka_episodes_per_second(n: int) -> tuple[float, float]:
    """(episodes/s, first-call seconds) of the Kuka CLIs' planner rollout on n episodes."""
    from diffplan.planner import Planner, PlannerConfig
    from envs.kuka.config import TaskSpec
    from envs.kuka.task import KukaTask
    from experiments.kuka import eval as ke, spec as ks

    denoiser = ks.load_checked(ks.DEFAULT_CHECKPOINT, ks.NUM_STEPS, "stacking")
    planner = Planner(denoiser, PlannerConfig(mode="on_the_fly", num_steps=ks.NUM_STEPS))
    episodes = ke.generate_episodes(TaskSpec("stacking", False, "canonical"), n, SEED, n)
    task = KukaTask(follow_path=True)
    begin = time.perf_counter()
    ke.run_planner(task, planner, episodes, SEED, n)
    first = time.perf_counter() - begin
    begin = time.perf_counter()
    ke.run_planner(task, planner, episodes, SEED, n)
    return n / (time.perf_counter() - begin), first


def on_the_fly_rows(args) -> list[dict]:
    """The whole-episode run (L), then each batch size's full-pool moves; printed as they come."""
    spec, denoiser, task = _grid()
    length, whole = episode_length(spec, denoiser, task, args.length_episodes)
    print(f"on-the-fly, {args.length_episodes} whole episodes (batch {args.length_episodes}): "
          f"{length:.1f} moves per episode, {whole:.2f} episodes/s end to end", flush=True)
    rows = [dict(method="on_the_fly whole episodes", batch=args.length_episodes,
                 per_second=whole, moves_per_episode=length)]
    for slots in args.batch_sizes:
        move, compile_seconds = pool_move_seconds(spec, denoiser, task, slots, args.moves)
        rate = slots / (move * length)
        print(f"on-the-fly, batch {slots}: {rate:.2f} episodes/s ({move:.2f} s per move of "
              f"{slots} slots, median of {args.moves} moves; compiled in {compile_seconds:.1f} "
              "s)", flush=True)
        rows.append(dict(method="on_the_fly", batch=slots, per_second=rate,
                         seconds_per_move=move, compile_seconds=compile_seconds))
    return rows


def main(argv=None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    bc.check_positive(parser, args, ("moves", "length_episodes", "train_steps",
                                     "kuka_episodes"))
    if not args.parts or set(args.parts) - set(PARTS):
        parser.error(f"--parts must name some of {','.join(PARTS)}, got {args.parts}")
    bc.start(parser, args)
    device = device_name()
    print(f"device: {device}; {os.cpu_count()} CPU cores")
    rows = []
    if "on_the_fly" in args.parts:
        rows += on_the_fly_rows(args)
    if "train" in args.parts:
        rate, batch, first = train_steps_per_second(args.train_steps)
        print(f"training, default grid recipe (batch {batch}, default model): {rate:.2f} "
              f"steps/s ({args.train_steps} steps; first step {first:.1f} s)", flush=True)
        rows.append(dict(method="train", batch=batch, per_second=rate, compile_seconds=first))
    if "kuka" in args.parts:
        rate, first = kuka_episodes_per_second(args.kuka_episodes)
        print(f"kuka rollout, stacking on-the-fly ({args.kuka_episodes} episodes per call): "
              f"{rate:.3f} episodes/s (first call {first:.1f} s)", flush=True)
        rows.append(dict(method="kuka_rollout", batch=args.kuka_episodes, per_second=rate,
                         compile_seconds=first))
    result = {"experiment": "bench_device", "episodes": args.length_episodes, "seed": SEED,
              "device": device, "rows": rows}
    bc.finish(args, result)
    return result
