"""Shared machinery of the Kuka block experiments (the paper's Tables 2 and 5).

``experiments.kuka_stacking`` and ``experiments.kuka_rearrangement`` are thin wrappers around
:func:`main`: load (or ``--train``) the Kuka denoiser, run the diffusion planner
(``diffplan.Planner`` through ``diffplan.rollout`` on ``envs.kuka.task.KukaTask``;
``--policy expert``: the scripted expert) on fresh seeded episodes
of the kind's single- and multi-constraint tasks under MJX physics, measure success on the final
physical block poses, print a table and write JSON (contract 2 of DESIGN.md), the final states
(contract 4), figures and videos.

Seeds: episode i of ``--seed S`` is ``generate(fold_in(PRNGKey(S), i), spec)`` in every
column (so the columns share their initial layouts); the planner's key of episode i is
``fold_in(fold_in(PRNGKey(S), ROLLOUT_STREAM), i)``, so nothing depends on the batching.
Every choice (model, training, psi, step counts) was made on the validation seed 1000; the
README reports the evaluation seeds 2001-2003. Training draws its examples from another key
stream (envs.kuka.training.TRAIN_STREAM).
"""
from __future__ import annotations

import argparse
import functools
import os
import sys
import time
import warnings
from typing import Sequence

import numpy as np

DEFAULT_EPISODES = 200
VALIDATION_SEED = 1000
"""The episodes every choice was made on."""
EVALUATION_SEEDS = (2001, 2002, 2003)
"""The seeds the README reports on; never used to choose anything."""
DEFAULT_SEED = EVALUATION_SEEDS[0]
DEFAULT_BATCH = 64
POLICIES = ("planner", "expert")
MODES = ("on_the_fly", "one_shot")
"""Planning modes of the Kuka experiments: a plan before every placement (the paper's
on-the-fly planning, the main rows), or one plan at t = 0 followed to the end."""
MAIN_MODE = "on_the_fly"
METHOD_NAMES = {"on_the_fly": "on-the-fly", "one_shot": "one-shot"}
LANGUAGES = ("canonical", "paraphrased")
NUM_STEPS = 10
"""Denoising steps per plan."""
PAPER = {
    # (single, multi) for each kind: Table 2 of the paper (Diffuser has no multi-constraint
    # number) and Table 5's "Complex LI" row (paraphrased instructions).
    "stacking": {"ours (paper)": (99.50, 98.38), "DD (paper)": (58.00, 60.30),
                 "Diffuser (paper)": (45.60, None), "ours, paraphrased (paper)": (98.70, 97.33)},
    "rearrangement": {"ours (paper)": (99.80, 98.85), "DD (paper)": (62.70, 67.20),
                      "Diffuser (paper)": (58.90, None),
                      "ours, paraphrased (paper)": (97.80, 78.55)},
}

# MJX casts some of MuJoCo's float64 "infinite" defaults to float32 when it builds the model.
warnings.filterwarnings("ignore", "overflow encountered in cast")

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TRAINING_NAME = "kuka"
"""One denoiser serves both experiments, all four Table 2 columns and both phrasings: the
shipped one is checkpoints/kuka, and `--train` of either experiment trains it (into
runs/kuka by default)."""
DEFAULT_CHECKPOINT = os.path.join(REPO_ROOT, "checkpoints", TRAINING_NAME)
DEFAULT_TRAIN_DIR = os.path.join(REPO_ROOT, "runs", TRAINING_NAME)
TRAIN_STEPS = 12000
TRAIN_BATCH = 32
TRAIN_LR = 1e-3
WARMUP_STEPS = 200
CHECKPOINT_EVERY = 250
PREDICTION = "x0"


# ---------------------------------------------------------------------------- training

def model_config(size: str = "default"):
    """The Kuka denoiser's DenoiserConfig: the grid world's model sizes (compile_common's
    MODEL_SIZES) on the Kuka planning tensor (24 x 24, 2 condition and 3 generated channels,
    the Kuka vocabulary, cells embedded with the instruction words' table)."""
    from diffplan.denoiser import DenoiserConfig
    from envs.kuka import grammar
    from envs.kuka.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS
    from experiments.compile_common import MODEL_SIZES

    return DenoiserConfig(vocab_size=len(grammar.VOCAB), max_tokens=grammar.MAX_TOKENS,
                          num_cond_channels=NUM_COND_CHANNELS,
                          num_gen_channels=NUM_GEN_CHANNELS, grid_repr="embed",
                          **MODEL_SIZES[size])


def train_config(seed: int = 0, steps: int = TRAIN_STEPS,
                 checkpoint_every: int = CHECKPOINT_EVERY, prediction: str = PREDICTION):
    from diffplan.train import TrainConfig
    from envs.kuka.task import NUM_GEN_CHANNELS

    return TrainConfig(seed=seed, steps=steps, batch_size=TRAIN_BATCH, lr=TRAIN_LR,
                       warmup_steps=min(WARMUP_STEPS, max(steps // 10, 0)),
                       num_gen_channels=NUM_GEN_CHANNELS, prediction=prediction,
                       num_train_timesteps=100, checkpoint_every=checkpoint_every,
                       log_every=max(1, min(50, steps // 10)))


def train_denoiser(out_dir: str, *, seed: int = 0, steps: int = TRAIN_STEPS,
                   model_size: str = "default", checkpoint_every: int = CHECKPOINT_EVERY,
                   prediction: str = PREDICTION, progress: bool = True) -> float:
    """Trains the Kuka denoiser into out_dir with envs.kuka.training.Recipe (resuming if
    out_dir holds a checkpoint of the same settings). Returns the wall seconds of this call."""
    from diffplan.denoiser import Denoiser
    from diffplan.train import train
    from envs.kuka.training import Recipe

    config, recipe = model_config(model_size), Recipe()
    start = time.time()
    train(Denoiser(config), config, train_config(seed, steps, checkpoint_every, prediction),
          recipe.batch_fn(), out_dir, init_batch=recipe.init_batch(), progress=progress,
          extra_metadata={**recipe.metadata(), "model_size": model_size})
    return time.time() - start


# --------------------------------------------------------------------------------- CLI

def build_parser(kind: str) -> argparse.ArgumentParser:
    from experiments.compile_common import MODEL_SIZES

    p = argparse.ArgumentParser(
        prog=f"python -m experiments.kuka_{kind}",
        description=(f"Kuka block world, {kind}: run the diffusion planner (or the scripted "
                     f"expert) on fresh seeded episodes of the single- and multi-constraint "
                     f"{kind} tasks (the paper's Table 2 columns; Table 5 with paraphrased "
                     "instructions) in MuJoCo MJX physics, measure success on the final "
                     "physical block poses (strict, contract 4, and Diffuser's looser check), "
                     "and print/write the results table."))
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES,
                   help=f"evaluation episodes per column and seed (default {DEFAULT_EPISODES})")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED,
                   help="evaluation seed: episode i is generated from fold_in(PRNGKey(seed), i) "
                        f"in each column (default {DEFAULT_SEED}, an evaluation seed)")
    p.add_argument("--seeds", metavar="S1,S2,...", default=None,
                   help="evaluate on several seeds (--episodes each) and report pooled rates "
                        "with 95%% intervals and per-seed values; the README uses "
                        f"{','.join(map(str, EVALUATION_SEEDS))}; {VALIDATION_SEED} is the "
                        "validation seed every choice was made on")
    p.add_argument("--policy", choices=POLICIES, default="planner",
                   help="who acts: 'planner' (the diffusion planner, default) or 'expert' (the "
                        "scripted expert through the same primitive and physics)")
    p.add_argument("--language", choices=LANGUAGES + ("both",), default="canonical",
                   help="instruction phrasing: 'canonical' (Table 2, default), 'paraphrased' "
                        "with inverted prepositions (Table 5), or 'both' (every row for each)")
    p.add_argument("--modes", default=",".join(MODES),
                   help=f"comma-separated planning modes (default {','.join(MODES)}); the "
                        "first of them gives the main row")
    from experiments import cli

    cli.add_training_flags(p, training_name=TRAINING_NAME, served="both Kuka experiments",
                           train_steps=TRAIN_STEPS, checkpoint_every=CHECKPOINT_EVERY,
                           model_sizes=MODEL_SIZES)
    p.add_argument("--num-steps", type=int, default=NUM_STEPS,
                   help=f"denoising steps per plan (default {NUM_STEPS})")
    p.add_argument("--carry", choices=("path", "arc"), default="path",
                   help="carry blocks along the in-painted path ('path', default) or the "
                        "expert's arc around the base ('arc')")
    p.add_argument("--json", metavar="PATH", help="write the results (contract 2) as JSON")
    p.add_argument("--states", metavar="PATH.npz",
                   help="write the final physics state of every episode of the main row "
                        "(contract 4): single-constraint episodes first, then multi-constraint "
                        "(each over the seeds in order)")
    p.add_argument("--batch-size", type=int, default=DEFAULT_BATCH,
                   help=f"episodes per jitted, vmapped call (default {DEFAULT_BATCH})")
    p.add_argument("--figures", metavar="DIR",
                   help="write PNGs of a few episodes: the top-down view before every "
                        "placement with the in-painted path, pick and goal estimate, and the "
                        "view at the end (expert: its first path)")
    p.add_argument("--num-figures", type=int, default=3,
                   help="episodes per column drawn with --figures (default 3)")
    p.add_argument("--video", metavar="DIR",
                   help="render a few episodes offscreen to animated GIFs (needs an EGL or "
                        "OSMesa GL backend; without one a line says so and the run goes on)")
    p.add_argument("--num-videos", type=int, default=2,
                   help="episodes per column rendered with --video (default 2)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return p


TRAIN_FLAGS = {"train_dir": "--train-dir", "train_steps": "--train-steps",
               "train_seed": "--train-seed", "checkpoint_every": "--checkpoint-every",
               "model_size": "--model-size"}


def check_args(parser, args) -> tuple[str, ...]:
    """Validates the arguments (one-line errors before any work); returns the modes."""
    from experiments import cli

    cli.only_with(parser, args, "train", TRAIN_FLAGS)
    if args.policy == "expert" and (args.train or args.checkpoint):
        parser.error("--train and --checkpoint only make sense with --policy planner")
    if args.train and args.checkpoint is not None:
        parser.error("--checkpoint and --train exclude each other: --train evaluates what it "
                     "trains (its output directory is --train-dir)")
    cli.check_at_least(parser, "--train-steps", args.train_steps, 2)
    cli.check_at_least(parser, "--checkpoint-every", args.checkpoint_every, 1)
    for flag, value, minimum in (("--episodes", args.episodes, 1), ("--seed", args.seed, 0),
                                 ("--batch-size", args.batch_size, 1),
                                 ("--num-steps", args.num_steps, 1),
                                 ("--num-figures", args.num_figures, 0),
                                 ("--num-videos", args.num_videos, 0)):
        cli.check_at_least(parser, flag, value, minimum)
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_file(parser, "--states", args.states, suffix=".npz")
    for flag in ("figures", "video", "train_dir"):
        cli.check_output_dir(parser, f"--{flag.replace('_', '-')}", getattr(args, flag))
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    bad = [m for m in modes if m not in MODES]
    if bad or not modes or len(set(modes)) != len(modes):
        parser.error(f"--modes must be distinct modes of {MODES}, got {args.modes!r}")
    return modes


def fail(message: str, code: int = 2):
    """Ends the program with one line on stderr (a user error, not a bug)."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(code)


def load_checked(checkpoint: str, num_steps: int, kind: str):
    """The checkpoint's LoadedDenoiser, checked against the Kuka planning tensor and the
    step count; one-line errors for a missing, unreadable or mismatched checkpoint."""
    from diffplan.denoiser import load_denoiser
    from envs.kuka import grid
    from envs.kuka.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS

    try:
        denoiser = load_denoiser(checkpoint)
    except FileNotFoundError:
        fail(f"no checkpoint in {checkpoint}: train one with `python -m experiments.kuka_{kind} "
             "--train` (or pass another --checkpoint directory)")
    except ValueError as e:
        fail(f"cannot read the checkpoint {checkpoint}: {e}")
    want = (grid.GRID_SIZE, grid.GRID_SIZE, NUM_GEN_CHANNELS)
    if tuple(denoiser.plan_shape) != want or denoiser.num_cond_channels != NUM_COND_CHANNELS:
        fail(f"the checkpoint {checkpoint} plans {tuple(denoiser.plan_shape)} with "
             f"{denoiser.num_cond_channels} condition channels; the Kuka world needs {want} "
             f"with {NUM_COND_CHANNELS}")
    if num_steps > denoiser.schedule.num_train_steps:
        fail(f"--num-steps {num_steps} exceeds the checkpoint's schedule of "
             f"{denoiser.schedule.num_train_steps} training timesteps")
    return denoiser


# ----------------------------------------------------------------------------- running

@functools.lru_cache(maxsize=None)
def _generate_fn():
    """jitted (keys, spec) -> Episode batch, built once (a new jax.jit per call re-traced it
    for every column and seed)."""
    import jax

    from envs.kuka.config import TaskSpec
    from envs.kuka.episode import episode_keys, generate

    return jax.jit(jax.vmap(generate, in_axes=(0, None)), static_argnums=1)


def generate_episodes(spec, n: int, seed: int, batch: int):
    """Episodes 0..n-1 of a seed (numpy Episode with a leading (n,) axis)."""
    import jax

    from envs.kuka.config import TaskSpec
    from envs.kuka.episode import episode_keys, generate

    gen = _generate_fn()
    parts = [jax.device_get(gen(episode_keys(seed, min(batch, n - lo), lo), spec))
             for lo in range(0, n, batch)]
    return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)


def _physical(states) -> dict:
    """The final physical state of a batch of env.States as numpy arrays."""
    import jax

    from envs.kuka import physics

    return {"block_pos": jax.vmap(physics.block_pos)(states.data),
            "block_quat": jax.vmap(physics.block_quat)(states.data),
            "held": jax.vmap(physics.held)(states.data),
            "placements": states.t, "done": states.done}


def _padded(episodes, idx, size: int):
    """Episodes idx, padded to size rows with copies of the last (dropped afterwards)."""
    import jax

    idx = np.concatenate([idx, np.full(size - len(idx), idx[-1])])
    return idx, jax.tree.map(lambda x: x[idx], episodes)


def run_expert(episodes, batch: int, bar=None):
    """The scripted expert on every episode, in calls of `batch` (the last padded).

    Returns dict of numpy arrays: block_pos (n, 4, 3), block_quat (n, 4, 4), held (n, 4),
    placements (n,), done (n,), frames (n, MAX_STEPS, F, nq)."""
    from envs.kuka import env, expert

    n = episodes.block_xy.shape[0]
    outs = []
    for lo in range(0, n, batch):
        _, chunk = _padded(episodes, np.arange(lo, min(n, lo + batch)), batch)
        states, frames = expert.run_expert(env.reset_batch(chunk))
        keep = min(batch, n - lo)
        out = dict(_physical(states), frames=frames)
        outs.append({k: np.asarray(v)[:keep] for k, v in out.items()})
        if bar is not None:
            bar.update(keep)
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


def planner_keys(seed: int, idx):
    """The planner's PRNG keys of episodes idx of a seed."""
    import jax
    import jax.numpy as jnp

    from experiments.compile_common import ROLLOUT_STREAM

    root = jax.random.fold_in(jax.random.PRNGKey(seed), ROLLOUT_STREAM)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.asarray(idx))


def run_planner(task, planner, episodes, seed: int, batch: int, bar=None):
    """The planner on every episode with diffplan.rollout, in calls of `batch` episodes (the
    last padded to the compiled size). Returns the final physical states (as
    :func:`run_expert`, without frames) plus denoiser_calls and num_plans (n,).

    Not the slot pool (diffplan.rollout_stream): its jitted program, with a physics reset and
    a pick-and-place in one loop body, needed more than 7 GB of memory to compile here (the
    batched rollout ~4.8 GB); a batch ends with its slowest episode, at most 6 placements."""
    import jax

    from experiments.compile_common import rollout_fn

    n = episodes.block_xy.shape[0]
    run = rollout_fn(task)
    outs = []
    for lo in range(0, n, batch):
        idx, chunk = _padded(episodes, np.arange(lo, min(n, lo + batch)), batch)
        out = run(planner, planner_keys(seed, idx), chunk, 0)
        out = jax.device_get(dict(_physical(out.final_state), denoiser_calls=out.denoiser_calls,
                                  num_plans=out.num_plans))
        keep = min(batch, n - lo)
        outs.append({k: np.asarray(v)[:keep] for k, v in out.items()})
        if bar is not None:
            bar.update(keep)
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


# ----------------------------------------------------------------------------- metrics

def constraint_success(episodes, final):
    """(strict, diffuser) bool (n, 3): each instructed constraint holds at the end (padding
    rows False), by contract 4's check and by Diffuser's."""
    import jax

    from envs.kuka import metrics

    pos, held = final["block_pos"], final["held"]
    constraints = np.asarray(episodes.constraints)
    out = []
    for check in (metrics.on_matrix, metrics.diffuser_on_matrix):
        out.append(np.asarray(jax.vmap(lambda p, h, c: metrics.satisfied(check(p, h), c))(
            pos, held, constraints)))
    return out[0], out[1]


def column_metrics(method: str, column: str, episodes, final, seconds: float) -> dict:
    """A results row from the final physical states (numpy)."""
    import jax

    from envs.kuka import metrics

    strict, loose = constraint_success(episodes, final)
    valid = np.asarray(episodes.constraints)[..., 0] >= 0
    tower = np.asarray(jax.vmap(metrics.single_tower)(final["block_pos"], final["held"]))
    is_stacking = bool(np.asarray(episodes.tower).all())
    row = {
        "method": method, "column": column, "episodes": int(len(valid)),
        "constraints": int(valid.sum()),
        "SR": 100.0 * strict.sum() / valid.sum(),
        "SR_diffuser": 100.0 * loose.sum() / valid.sum(),
        "all_constraints": 100.0 * np.mean((strict | ~valid).all(-1)),
        "tower": 100.0 * tower.mean() if is_stacking else None,
        "placements_per_episode": float(np.mean(final["placements"])),
        "seconds": float(seconds),
    }
    if "denoiser_calls" in final:
        row["denoiser_calls_per_episode"] = float(np.mean(final["denoiser_calls"]))
        row["plans_per_episode"] = float(np.mean(final["num_plans"]))
    return row


def add_intervals(row: dict, per_seed: dict) -> None:
    """Adds SR_ci95 (95% Wilson interval of the pooled constraint success rate; constraints
    of one episode are counted as independent trials) and per-seed SR to a row."""
    from experiments.compile_common import wilson_interval

    n = row["constraints"]
    row["SR_ci95"] = wilson_interval(int(round(row["SR"] * n / 100)), n)
    row["per_seed"] = {str(s): {k: r[k] for k in ("SR", "SR_diffuser", "seconds")}
                       for s, r in per_seed.items()}


TABLE_COLUMNS = (("method", "{:<46}", "method"), ("episodes", "{:>6d}", "eps"),
                 ("SR", "{:>7.2f}", "SR"), ("SR_diffuser", "{:>8.2f}", "SR_Diff"),
                 ("all_constraints", "{:>7.2f}", "all"), ("tower", "{:>7.2f}", "tower"),
                 ("placements_per_episode", "{:>6.2f}", "moves"),
                 ("denoiser_calls_per_episode", "{:>6.1f}", "calls"),
                 ("seconds", "{:>7.1f}", "sec"))


def format_table(rows) -> str:
    """A plain-text table of result rows (missing values shown as '-')."""
    widths = [len(fmt.format(0 if key != "method" else "")) for key, fmt, _ in TABLE_COLUMNS]
    head = " ".join(h.ljust(w) if k == "method" else h.rjust(w)
                    for (k, _, h), w in zip(TABLE_COLUMNS, widths))
    lines = [head, "-" * len(head)]
    for row in rows:
        cells = [fmt.format(row[k]) if row.get(k) is not None else "-".rjust(w)
                 for (k, fmt, _), w in zip(TABLE_COLUMNS, widths)]
        lines.append(" ".join(cells))
    return "\n".join(lines)


def pooled_row(method: str, rows, seconds: float) -> dict:
    """The main row: every column's constraints pooled (the contract-4 SR of the states file)."""
    total = sum(r["constraints"] for r in rows)
    episodes = sum(r["episodes"] for r in rows)

    def mean(key, weight):
        values = [(r[key], r[weight]) for r in rows if r.get(key) is not None]
        if not values:
            return None
        return sum(v * w for v, w in values) / sum(w for _, w in values)

    row = {"method": method, "column": "all", "episodes": episodes, "constraints": total,
           "SR": mean("SR", "constraints"), "SR_diffuser": mean("SR_diffuser", "constraints"),
           "all_constraints": mean("all_constraints", "episodes"),
           "tower": mean("tower", "episodes"),
           "placements_per_episode": mean("placements_per_episode", "episodes"),
           "seconds": float(seconds)}
    if any("denoiser_calls_per_episode" in r for r in rows):
        row["denoiser_calls_per_episode"] = mean("denoiser_calls_per_episode", "episodes")
    return row


def write_json(path: str, result: dict) -> None:
    from experiments import cli

    cli.write_json(path, result)


def write_states(path: str, parts) -> None:
    """Contract 4: the final physics state of every episode (parts: (episodes, final) pairs)."""
    from envs.kuka import grammar, scene

    arrays = {
        "block_pos": np.concatenate([f["block_pos"] for _, f in parts]).astype(np.float32),
        "block_quat": np.concatenate([f["block_quat"] for _, f in parts]).astype(np.float32),
        "held": np.concatenate([f["held"] for _, f in parts]).astype(bool),
        "block_half_size": np.asarray(scene.BLOCK_HALF_SIZE, np.float32),
        "constraints": np.concatenate([np.asarray(e.constraints) for e, _ in parts]).astype(
            np.int32),
        "instruction": np.array([grammar.decode(t) for e, _ in parts
                                 for t in np.asarray(e.tokens)]),
    }
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(path, **arrays)


def write_videos(out_dir: str, videos: dict) -> list[str]:
    from envs.kuka import render

    if not videos:
        return []
    result = render.write_videos(out_dir, videos)
    if result is None:
        print(f"--video: no GL backend for offscreen rendering ({'/'.join(render.GL_BACKENDS)} "
              "failed); no videos written")
        return []
    print(f"wrote {len(result[0])} videos to {out_dir} (MUJOCO_GL={result[1]})")
    return result[0]


def _concat(dicts):
    return {k: np.concatenate([d[k] for d in dicts]) for k in dicts[0]}


def _label(mode: str | None, multi: bool, language: str, policy: str) -> str:
    who = "expert" if policy == "expert" else f"planner {METHOD_NAMES[mode]}"
    what = "multi-constraint" if multi else "single constraint"
    return f"{who}, {what}" + (", paraphrased" if language == "paraphrased" else "")


# --------------------------------------------------------------------------------- main

def main(kind: str, argv: Sequence[str] | None = None) -> dict:
    parser = build_parser(kind)
    args = parser.parse_args(argv)
    modes = check_args(parser, args)
    from experiments.compile_common import parse_seeds

    seeds = parse_seeds(parser, args)

    from diffplan.jax_cache import enable_compilation_cache

    enable_compilation_cache()
    import jax
    from tqdm import tqdm

    from envs.kuka.config import TaskSpec
    from envs.kuka.episode import episode_keys, generate

    progress = not args.no_progress
    planner_policy = args.policy == "planner"
    train_seconds, checkpoint, task, denoiser = None, None, None, None
    if planner_policy:
        from diffplan.train import ConfigMismatchError
        from envs.kuka.task import KukaTask

        if args.train:
            checkpoint = args.train_dir or DEFAULT_TRAIN_DIR
            try:
                train_seconds = train_denoiser(
                    checkpoint, seed=args.train_seed or 0,
                    steps=args.train_steps or TRAIN_STEPS,
                    model_size=args.model_size or "default",
                    checkpoint_every=args.checkpoint_every or CHECKPOINT_EVERY,
                    progress=progress)
            except ConfigMismatchError as e:
                fail(str(e))
        else:
            checkpoint = args.checkpoint or DEFAULT_CHECKPOINT
        denoiser = load_checked(checkpoint, args.num_steps, kind)
        task = KukaTask(follow_path=args.carry == "path")
    else:
        modes = (None,)

    languages = LANGUAGES if args.language == "both" else (args.language,)
    specs = [TaskSpec(kind, multi, language) for language in languages
             for multi in (False, True)]
    episodes = {(spec, seed): generate_episodes(spec, args.episodes, seed, args.batch_size)
                for spec in specs for seed in seeds}
    bar = tqdm(total=args.episodes * len(seeds) * len(specs) * len(modes),
               desc=f"kuka {kind} ({args.policy})", unit="ep", disable=not progress,
               file=sys.stderr, leave=False, dynamic_ncols=True)
    rows, finals = {}, {}
    start = time.time()
    for mode in modes:
        planner = None
        if planner_policy:
            from diffplan.planner import Planner, PlannerConfig
            planner = Planner(denoiser, PlannerConfig(mode=mode, num_steps=args.num_steps))
        for spec in specs:
            per_seed, parts = {}, []
            for seed in seeds:
                t0 = time.time()
                eps = episodes[spec, seed]
                final = (run_planner(task, planner, eps, seed, args.batch_size, bar)
                         if planner_policy else run_expert(eps, args.batch_size, bar))
                per_seed[seed] = column_metrics("", "", eps, final, time.time() - t0)
                parts.append(final)
            final = _concat(parts)
            eps = jax.tree.map(lambda *xs: np.concatenate(xs),
                               *[episodes[spec, s] for s in seeds])
            row = column_metrics(_label(mode, spec.multi, spec.language, args.policy),
                                 "multi" if spec.multi else "single", eps, final,
                                 sum(r["seconds"] for r in per_seed.values()))
            row.update(mode=mode, language=spec.language)
            if len(seeds) > 1:
                add_intervals(row, per_seed)
            rows[mode, spec], finals[mode, spec] = row, (eps, final)
    bar.close()
    main_mode, main_language = modes[0], languages[0]
    main_specs = [s for s in specs if s.language == main_language]
    main_name = args.policy if not planner_policy else f"planner {METHOD_NAMES[main_mode]}"
    main_row = pooled_row(main_name + (", paraphrased" if main_language == "paraphrased" else ""),
                          [rows[main_mode, s] for s in main_specs],
                          sum(rows[main_mode, s]["seconds"] for s in main_specs))
    if len(seeds) > 1:
        main_row["SR_ci95"] = _pooled_interval(main_row)
    all_rows = [main_row] + [rows[m, s] for m in modes for s in specs]
    result = {
        "experiment": f"kuka_{kind}",
        "episodes": args.episodes,
        "seed": seeds[0],
        "seeds": list(seeds),
        "validation": VALIDATION_SEED in seeds,
        "policy": args.policy,
        "language": args.language,
        "modes": [m for m in modes if m is not None],
        "checkpoint": os.path.relpath(checkpoint, REPO_ROOT) if checkpoint else None,
        "num_steps": args.num_steps if planner_policy else None,
        "carry": args.carry if planner_policy else None,
        "train_seconds": train_seconds,
        "states_method": main_row["method"],
        "paper": {name: dict(zip(("single", "multi"), values))
                  for name, values in PAPER[kind].items()},
        "machine": f"{os.cpu_count()} CPU cores, jax {jax.__version__} on "
                   f"{jax.devices()[0].platform}",
        "seconds": time.time() - start,
        "rows": all_rows,
    }
    print(f"\nkuka_{kind}: {args.episodes} episodes per column and seed, seed(s) "
          f"{','.join(map(str, seeds))}, policy {args.policy}"
          + (f" ({os.path.relpath(checkpoint, REPO_ROOT)}, {args.num_steps} denoising steps "
             f"per plan)" if planner_policy else "")
          + "; success on final physical poses (SR strict, contract 4; SR_Diff Diffuser's "
            "check)")
    print(format_table(all_rows))
    if len(seeds) > 1:
        print(f"SR per seed ({', '.join(map(str, seeds))}) and 95% interval of the pooled SR:")
        for row in all_rows[1:]:
            per = " / ".join(f"{row['per_seed'][str(s)]['SR']:.1f}" for s in seeds)
            lo, hi = row["SR_ci95"]
            print(f"  {row['method']:<46} {per} [{lo:.2f}, {hi:.2f}]")
    print("paper (single / multi): " + "; ".join(
        f"{name} {s:.2f} / " + (f"{m:.2f}" if m is not None else "-")
        for name, (s, m) in PAPER[kind].items()))
    if args.json:
        write_json(args.json, result)
    if args.states:
        parts = [finals[main_mode, s] for s in main_specs]
        write_states(args.states, parts)
        print(f"wrote {args.states} ({sum(len(f['placements']) for _, f in parts)} final states "
              f"of the '{main_row['method']}' row)")
    count = max(args.num_figures if args.figures else 0, args.num_videos if args.video else 0)
    if count:
        from experiments import kuka_figures

        traces = {}
        if planner_policy:
            main_planner = Planner(denoiser, PlannerConfig(mode=main_mode,
                                                           num_steps=args.num_steps))
        for spec in specs:
            eps = jax.tree.map(lambda x: x[:count], episodes[spec, seeds[0]])
            if planner_policy:
                traces[spec] = kuka_figures.trace(task, main_planner, eps,
                                                  planner_keys(seeds[0], np.arange(count)))
            else:
                traces[spec] = kuka_figures.expert_trace(eps, finals[None, spec][1])
        if args.figures and args.num_figures:
            written = [p for spec in specs for p in kuka_figures.write_figures(
                args.figures, spec, traces[spec], args.num_figures)]
            print(f"wrote {len(written)} figures to {args.figures}")
        if args.video and args.num_videos:
            videos = {}
            for spec in specs:
                videos.update(kuka_figures.video_frames(spec, traces[spec], args.num_videos))
            write_videos(args.video, videos)
    return result


def _pooled_interval(row: dict) -> list[float]:
    from experiments.compile_common import wilson_interval

    n = row["constraints"]
    return wilson_interval(int(round(row["SR"] * n / 100)), n)
