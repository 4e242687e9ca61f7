"""Shared machinery of the CompILE grid-world experiments (Tables 1, 4 and 6 of the paper).

``experiments.compile_1o1g``, ``compile_mo1g`` and ``compile_p_mo2g`` are thin wrappers around
:func:`main`: load (or train) the setting's denoiser, evaluate it on fresh seeded episodes in
every planning mode, print a table, write JSON (contract 2 of DESIGN.md), and optionally the
executed trajectories and figures.

Seeds: evaluation episode i of ``--seed S`` is ``episode.generate(fold_in(PRNGKey(S), i))``, the
convention of ``envs.gridworld.export`` (so ``export --seed S`` writes the same episodes).
Training draws its examples from ``fold_in(step_key, TRAIN_STREAM)`` keys of its own seed (see
``envs.gridworld.training``): a different key stream, so training never sees the evaluation episodes
(tests/test_compile_experiments.py checks a sample for overlap).
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import sys
import time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from diffplan.jax_cache import enable_compilation_cache

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CHECKPOINT_ROOT = os.path.join(REPO_ROOT, "checkpoints")
VALIDATION_SEED = 1000
"""The episodes every choice (psi, step counts, warm-start schedule, checkpoint) was made on."""
EVALUATION_SEEDS = (2001, 2002, 2003)
"""The seeds the README reports on (3 x 1000 episodes); never used to choose anything."""
DEFAULT_EVAL_SEED = EVALUATION_SEEDS[0]
ROLLOUT_STREAM = 0x9A11


MODEL_SIZES = {
    # For tests and smoke runs: compiles and trains in seconds, learns little.
    "tiny": dict(embed_dim=8, widths=(8, 16), num_res_blocks=1, attn_levels=(), cross_attn_levels=(1,),
                 text_dim=16, text_layers=1, text_heads=2, groups=4, head_dim=8),
    # The shipped grid-world denoiser, sized for a 2-core CPU.
    # Widths (16, 32, 64): ~50 MFLOP per sample. experiments/bench_unet.py measured a
    # 2.8M-parameter (32, 64, 128) UNet at ~1.6x the forward time and ~1.8x the train-step time
    # of this size on this CPU; on-the-fly evaluation is dominated by denoiser calls.
    "default": dict(embed_dim=32, widths=(16, 32, 64), num_res_blocks=1, attn_levels=(2,),
                    cross_attn_levels=(0, 1, 2), text_dim=64, text_layers=2, text_heads=4,
                    groups=8, head_dim=16),
}


MODE_REPLAN = {"on_the_fly": "always", "warm_start": "on_change"}
TRIGGER_WORDS = {"always": "before every move",
                 "on_change": "when new cells were seen or the sub-goal was reached"}
"""Each re-planning mode's default trigger: the paper-style on-the-fly row runs a full denoising
before every move (the paper's Algorithm 1); the warm-start row, the cheap default, re-plans
when the observation changed or the plan's sub-goal was reached."""


@dataclasses.dataclass(frozen=True)
class ExperimentSpec:
    """Everything a setting's experiment fixes: world, model, training and planning defaults."""

    setting: str
    grid_repr: str = "embed"
    goal_channel: bool = True
    prediction: str = "x0"
    detour_prob: float = 0.5
    goal_loss_weight: float = 3.0
    train_steps: int = 8000
    batch_size: int = 64
    lr: float = 1e-3
    warmup_steps: int = 200
    num_steps: int = 10
    # Warm re-plans (the default of the warm-start row, chosen on validation seed 1000 x 1000
    # P-MO2G episodes against paper-style on-the-fly, SR 100.0 at 152.2 calls/episode): the
    # previous plan re-noised to step 1 of a 2-step schedule and denoised in one call, and only
    # when new cells were seen or the sub-goal was reached (replan "on_change"): SR 100.0 at
    # 11.5 calls/episode (3-step schedule: 100.0 at 22.0; re-planning before every move, 3/1:
    # 100.0 at 31.4). Evaluation seeds 2001-2003: README, "Cheaper re-planning".
    warm_start_step: int = 1
    warm_num_steps: int | None = 2
    eval_batch: int = 250
    fresh_noise: bool = True
    eta: float = 0.0
    # Re-planning trigger of every re-planning row; None: each mode's own (MODE_REPLAN).
    replan: str | None = None
    modes: tuple[str, ...] = ("one_shot", "k_shot", "on_the_fly", "warm_start")
    main_mode: str = "on_the_fly"

    @property
    def name(self) -> str:
        return f"compile_{self.setting}"

    def grid_config(self):
        from envs.gridworld.config import make_config
        return make_config(self.setting)

    def task(self, num_gen_channels: int | None = None):
        """The setting's GridTask for a denoiser with num_gen_channels generated channels
        (default: the current recipe's)."""
        from envs.gridworld.task import NUM_GEN_CHANNELS, GridTask
        return GridTask(self.grid_config(), use_goal_channel=self.goal_channel,
                        num_gen_channels=num_gen_channels or NUM_GEN_CHANNELS)

    def model_config(self, size: str = "default"):
        from diffplan.denoiser import DenoiserConfig
        from envs.gridworld import grammar
        from envs.gridworld.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS
        if size not in MODEL_SIZES:
            raise ValueError(f"unknown model size {size!r}; expected one of {sorted(MODEL_SIZES)}")
        return DenoiserConfig(
            vocab_size=len(grammar.VOCAB), max_tokens=grammar.MAX_TOKENS,
            num_cond_channels=NUM_COND_CHANNELS, num_gen_channels=NUM_GEN_CHANNELS,
            grid_repr=self.grid_repr, **MODEL_SIZES[size])

    def recipe(self):
        from envs.gridworld.training import Recipe
        return Recipe(detour_prob=self.detour_prob, goal_loss_weight=self.goal_loss_weight,
                      goal_channel=self.goal_channel)

    def train_config(self, seed: int = 0, steps: int | None = None,
                     checkpoint_every: int = 500):
        from diffplan.train import TrainConfig
        steps = self.train_steps if steps is None else steps
        from envs.gridworld.task import NUM_GEN_CHANNELS
        return TrainConfig(seed=seed, steps=steps, batch_size=self.batch_size, lr=self.lr,
                           num_gen_channels=NUM_GEN_CHANNELS,
                           prediction=self.prediction,
                           warmup_steps=min(self.warmup_steps, max(steps // 10, 0)),
                           num_train_timesteps=100, checkpoint_every=checkpoint_every,
                           log_every=max(1, min(100, steps // 10)))

    def replan_of(self, mode: str) -> str:
        """The re-planning trigger of a mode's row: self.replan if set, else the mode's own
        (paper-style on-the-fly re-plans before every move; warm start on change)."""
        return self.replan or MODE_REPLAN.get(mode, "always")

    def planner_config(self, mode: str, **overrides):
        from diffplan.planner import PlannerConfig
        return PlannerConfig(mode=mode, num_steps=self.num_steps,
                             warm_start_step=self.warm_start_step,
                             warm_num_steps=self.warm_num_steps,
                             fresh_noise=self.fresh_noise, eta=self.eta,
                             replan=self.replan_of(mode), **overrides)

    @property
    def training_name(self) -> str:
        """The denoiser's name: the main one, or an ablation's (other grid repr / no g)."""
        suffix = ("" if self.grid_repr == "embed" else f"_{self.grid_repr}") + \
            ("" if self.goal_channel else "_no_goal")
        return TRAINING_NAME + suffix

    def default_checkpoint(self) -> str:
        return os.path.join(CHECKPOINT_ROOT, self.training_name)

    def default_train_dir(self) -> str:
        return os.path.join(REPO_ROOT, "runs", self.training_name)


TRAINING_NAME = "compile_gridworld"
"""One denoiser serves the three settings: it is trained on a fixed mixture of them
(envs.gridworld.training.TRAINING_MIXTURE), which costs one training instead of three; the
shipped checkpoint is checkpoints/compile_gridworld and `--train` of any setting trains it."""

SPECS = {
    "1o1g": ExperimentSpec("1o1g", modes=("one_shot", "on_the_fly", "warm_start")),
    "mo1g": ExperimentSpec("mo1g", modes=("one_shot", "on_the_fly", "warm_start")),
    "p_mo2g": ExperimentSpec("p_mo2g"),
}


# ----------------------------------------------------------------------------------- data

def eval_episodes(grid_config, n: int, seed: int, chunk: int = 1024):
    """Evaluation episodes: episode i = generate(fold_in(PRNGKey(seed), i)). (Episode, n)."""
    from envs.gridworld.episode import generate
    gen = jax.jit(jax.vmap(generate, in_axes=(0, None)), static_argnums=1)
    root = jax.random.PRNGKey(seed)
    parts = []
    for start in range(0, n, chunk):
        idx = jnp.arange(start, min(n, start + chunk))
        keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(idx)
        parts.append(jax.device_get(gen(keys, grid_config)))
    return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)


# ------------------------------------------------------------------------------ training

def train_setting(spec: ExperimentSpec, out_dir: str, *, seed: int = 0, steps: int | None = None,
                  progress: bool = True, model_size: str = "default",
                  checkpoint_every: int = 500, callback=None):
    """Trains the setting's denoiser into out_dir with the grid world's training recipe
    (envs.gridworld.training.Recipe), resuming if out_dir holds a checkpoint.
    Returns (ema params, model config, seconds)."""
    from diffplan.denoiser import Denoiser
    from diffplan.train import train

    model_config = spec.model_config(model_size)
    recipe = spec.recipe()
    start = time.time()
    result = train(Denoiser(model_config), model_config,
                   spec.train_config(seed, steps, checkpoint_every),
                   recipe.batch_fn(), out_dir, init_batch=recipe.init_batch(),
                   progress=progress, callback=callback,
                   extra_metadata={**recipe.metadata(), "model_size": model_size})
    return result.ema_params, model_config, time.time() - start


def load_model(checkpoint_dir: str):
    """The LoadedDenoiser of a checkpoint (diffplan.load_denoiser) and its metadata; raises
    FileNotFoundError when there is none."""
    from diffplan.checkpoint import read_metadata
    from diffplan.denoiser import load_denoiser

    denoiser = load_denoiser(checkpoint_dir)
    return denoiser, read_metadata(checkpoint_dir)


# ---------------------------------------------------------------------------- evaluation

STREAM_MODES = ("on_the_fly", "warm_start")


@functools.lru_cache(maxsize=None)
def rollout_fn(task, num_slots: int | None = None):
    """jitted (planner, keys (N,), episodes, token) -> Rollout: diffplan.rollout, or with
    num_slots the slot pool (diffplan.rollout_stream, re-planning modes), which reports its
    progress after every move to experiments.progress.RELAY under ``token`` (int32 ()). The
    planner is an argument, so one compilation serves every checkpoint of the same
    architecture and every seed."""
    from diffplan.rollouts import rollout, rollout_stream
    from experiments.progress import RELAY

    if num_slots is None:
        return jax.jit(lambda planner, keys, episodes, token: rollout(task, planner, keys,
                                                                      episodes))
    return jax.jit(lambda planner, keys, episodes, token: rollout_stream(
        task, planner, keys, episodes, num_slots, on_move=RELAY, token=token))


def evaluate_mode(spec, task, denoiser, episodes, seed, mode, batch_size, progress=True,
                  record_plans=False):
    """Runs one planning mode on the episodes (N of them); returns (Rollout as numpy, seconds).

    Re-planning modes run the slot pool (diffplan.rollout_stream) with batch_size slots over
    calls of up to 4 x batch_size episodes (a slot starts the next episode as soon as its
    episode ends; the progress bar moves as episodes end); the other modes run batches of
    batch_size episodes, processed in order of expert length (a batch's loop runs until its
    slowest episode ends). Episode i always uses the key fold_in(fold_in(PRNGKey(seed),
    ROLLOUT_STREAM), i), so nothing depends on the batching.
    """
    from tqdm import tqdm

    from diffplan.planner import Planner
    from experiments.progress import PARTS, RELAY

    n = int(np.shape(episodes.tokens)[0])
    planner = Planner(denoiser, spec.planner_config(mode, record_plans=record_plans))
    stream = mode in STREAM_MODES and not record_plans
    root = jax.random.fold_in(jax.random.PRNGKey(seed), ROLLOUT_STREAM)
    start = time.time()
    bar = tqdm(total=n, desc=f"{spec.setting} {METHOD_NAMES[mode]} (seed {seed})", unit="ep",
               disable=not progress, file=sys.stderr, leave=True, dynamic_ncols=True)
    per_call = min(n, 4 * batch_size) if stream else batch_size
    if stream:
        run = rollout_fn(task, min(batch_size, per_call))
        order = np.arange(n)
    else:
        run = rollout_fn(task)
        order = np.argsort(np.asarray(episodes.expert_length), kind="stable")
    outs = []
    try:
        for lo in range(0, n, per_call):
            idx = order[lo:lo + per_call]
            chunk = jax.tree.map(lambda x: x[idx], episodes)
            keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.asarray(idx))
            if len(idx) < per_call and lo > 0:
                # Pad the last call to the compiled size (padding results are dropped).
                pad = per_call - len(idx)
                chunk = jax.tree.map(lambda x: np.concatenate([x, x[:pad]]), chunk)
                keys = jnp.concatenate([keys, keys[:pad]])
            token = RELAY.attach(bar, offset=lo)
            try:
                out = jax.device_get(run(planner, keys, chunk, jnp.int32(token * PARTS)))
            finally:
                RELAY.detach(token)
            outs.append(jax.tree.map(lambda x: x[:len(idx)], out))
            bar.update(min(lo + len(idx), n) - bar.n)
    finally:
        bar.close()
    seconds = time.time() - start
    merged = jax.tree.map(lambda *xs: np.concatenate(xs), *outs)
    inverse = np.argsort(order)
    return jax.tree.map(lambda x: x[inverse], merged), seconds


def concat_trees(trees):
    """Concatenates pytrees of numpy arrays along their leading axis."""
    return jax.tree.map(lambda *xs: np.concatenate(xs), *trees)


PER_SEED_FIELDS = ("SR", "SR_ordered", "GD", "path_f1", "denoiser_calls_per_episode", "seconds")


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> list[float]:
    """95% Wilson score interval of a rate, in percent."""
    if n == 0:
        return [0.0, 100.0]
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [100.0 * max(0.0, centre - half), 100.0 * min(1.0, centre + half)]


def add_intervals(row, rollout, episodes, has_reference):
    """Adds SR_ci95 (and SR_ordered_ci95) over the pooled episodes to a metrics row."""
    n = len(rollout.steps)
    row["SR_ci95"] = wilson_interval(int(round(row["SR"] * n / 100)), n)
    if has_reference:
        row["SR_ordered_ci95"] = wilson_interval(int(round(row["SR_ordered"] * n / 100)), n)


def format_intervals(rows, seeds) -> str:
    """Per-seed SR and the pooled 95% intervals, one line per row."""
    lines = [f"SR per seed ({', '.join(map(str, seeds))}) and 95% interval of the pooled SR:"]
    for row in rows:
        per = " / ".join(f"{row['per_seed'][str(s)]['SR']:.1f}" for s in seeds)
        lo, hi = row["SR_ci95"]
        extra = ""
        if "SR_ordered_ci95" in row:
            olo, ohi = row["SR_ordered_ci95"]
            per_o = " / ".join(f"{row['per_seed'][str(s)]['SR_ordered']:.1f}" for s in seeds)
            extra = f"; SR_ordered {per_o} [{olo:.2f}, {ohi:.2f}]"
        lines.append(f"  {row['method']:<22} {per} [{lo:.2f}, {hi:.2f}]{extra}")
    return "\n".join(lines)


def metrics_row(method, rollout, episodes, seconds, has_reference):
    from envs.gridworld.metrics import plan_metrics, trajectory_metrics

    row = {"method": method}
    row.update(trajectory_metrics(rollout.positions, rollout.steps, episodes.target,
                                  episodes.expert_path,
                                  episodes.reference if has_reference else None))
    row.update(plan_metrics(rollout.first_plan[..., 0], episodes.expert_path))
    row["collisions_per_episode"] = float(np.mean(rollout.final_state.collisions))
    row["denoiser_calls_per_episode"] = float(np.mean(rollout.denoiser_calls))
    row["plans_per_episode"] = float(np.mean(rollout.num_plans))
    row["seconds"] = float(seconds)
    return row


METHOD_NAMES = {"one_shot": "one-shot", "k_shot": "two-shot", "on_the_fly": "on-the-fly",
                "warm_start": "warm-start on-the-fly"}

TABLE_COLUMNS = (("method", "{:<22}"), ("SR", "{:>7.2f}"), ("SR_ordered", "{:>7.2f}"),
                 ("GD", "{:>6.3f}"), ("path_precision", "{:>7.2f}"), ("path_recall", "{:>7.2f}"),
                 ("path_f1", "{:>7.2f}"), ("plan_f1", "{:>7.2f}"),
                 ("denoiser_calls_per_episode", "{:>8.1f}"), ("seconds", "{:>8.1f}"))
HEADERS = {"method": "method", "SR": "SR", "SR_ordered": "SR_ord", "GD": "GD",
           "path_precision": "Prec", "path_recall": "Rec", "path_f1": "F1",
           "plan_f1": "planF1", "denoiser_calls_per_episode": "calls", "seconds": "sec"}


def format_table(rows) -> str:
    """A plain-text table of result rows (missing values shown as '-')."""
    widths = {k: len(fmt.format(0 if k != "method" else "")) for k, fmt in TABLE_COLUMNS}
    head = " ".join(HEADERS[k].rjust(widths[k]) if k != "method" else HEADERS[k].ljust(widths[k])
                    for k, _ in TABLE_COLUMNS)
    lines = [head, "-" * len(head)]
    for row in rows:
        cells = []
        for k, fmt in TABLE_COLUMNS:
            cells.append(fmt.format(row[k]) if k in row else "-".rjust(widths[k]))
        lines.append(" ".join(cells))
    return "\n".join(lines)


def contract_arrays(episodes, grid_config) -> dict:
    """The episodes in the export format of contract 1 (numpy)."""
    from envs.gridworld import env, grammar

    reset = jax.jit(jax.vmap(lambda e: env.reset(e, grid_config)))
    seen0 = np.asarray(reset(episodes).seen)
    return {
        "grid": np.asarray(episodes.grid, np.int8),
        "agent": np.asarray(episodes.agent, np.int32),
        "target": np.asarray(episodes.target, np.int32),
        "reference": np.asarray(episodes.reference, np.int32),
        "expert_path": np.asarray(episodes.expert_path, bool),
        "expert_length": np.asarray(episodes.expert_length, np.int32),
        "visible0": seen0.astype(bool),
        "instruction": np.array([grammar.decode(t) for t in np.asarray(episodes.tokens)]),
        "object_names": np.array(grammar.OBJECT_NAMES),
    }


def write_trajectories(path, rollout, episodes, grid_config):
    arrays = contract_arrays(episodes, grid_config)
    final = rollout.positions[np.arange(len(rollout.steps)), rollout.steps]
    arrays.update(positions=np.asarray(rollout.positions, np.int32),
                  steps=np.asarray(rollout.steps, np.int32),
                  success=np.all(final == np.asarray(episodes.target), axis=-1))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(path, **arrays)


# ------------------------------------------------------------------------------------ CLI

def build_parser(spec: ExperimentSpec) -> argparse.ArgumentParser:
    from experiments import cli

    p = argparse.ArgumentParser(
        prog=f"python -m experiments.{spec.name}",
        description=(f"CompILE grid world, setting {spec.setting}: evaluate the diffusion planner "
                     "on fresh seeded episodes in each planning mode, measured on what the agent "
                     "executed (with collisions), and print/write the results table."))
    p.add_argument("--episodes", type=int, default=1000,
                   help="number of evaluation episodes (default 1000)")
    p.add_argument("--seed", type=int, default=DEFAULT_EVAL_SEED,
                   help="evaluation seed: episode i is generated from fold_in(PRNGKey(seed), i) "
                        f"(default {DEFAULT_EVAL_SEED}, an evaluation seed; training uses a "
                        "disjoint key stream)")
    p.add_argument("--seeds", metavar="S1,S2,...", default=None,
                   help="evaluate on several seeds (--episodes each) and report pooled metrics "
                        "with 95%% intervals and per-seed values; the README's tables use "
                        f"{','.join(map(str, EVALUATION_SEEDS))} (evaluation seeds); "
                        f"{VALIDATION_SEED} is the validation seed every choice was made on")
    p.add_argument("--json", metavar="PATH", help="write the results (contract 2) as JSON")
    p.add_argument("--trajectories", metavar="PATH.npz",
                   help="write the executed trajectories of the main row and the episodes "
                        "(of every seed, in order)")
    cli.add_training_flags(p, training_name=TRAINING_NAME, served="all three settings",
                           train_steps=spec.train_steps, checkpoint_every=500,
                           model_sizes=MODEL_SIZES)
    p.add_argument("--prediction", choices=("eps", "x0"), default=None,
                   help="network target of --train: the noise (the paper) or the clean plan "
                        f"(default {spec.prediction}; evaluation follows the checkpoint)")
    p.add_argument("--modes", default=",".join(spec.modes),
                   help=f"comma-separated planning modes to evaluate (default "
                        f"{','.join(spec.modes)})")
    p.add_argument("--num-steps", type=int, default=spec.num_steps,
                   help=f"denoising steps per full plan (default {spec.num_steps})")
    p.add_argument("--warm-start-step", type=int, default=spec.warm_start_step,
                   help="steps of the warm-start schedule skipped by its re-plans: each costs "
                        "--warm-num-steps minus this denoiser calls "
                        f"(default {spec.warm_start_step})")
    p.add_argument("--warm-num-steps", type=int, default=spec.warm_num_steps,
                   help="steps of the warm-start row's schedule (default "
                        f"{spec.warm_num_steps or 'the --num-steps'}): its first plan runs all "
                        "of them from noise, each re-plan resumes at --warm-start-step")
    p.add_argument("--noise", choices=("fresh", "episode"),
                   default="fresh" if spec.fresh_noise else "episode",
                   help="initial noise of re-plans: 'fresh' draws new noise at every move, "
                        "'episode' reuses the episode's noise so plans change only where the "
                        "observation did (default %(default)s)")
    p.add_argument("--eta", type=float, default=spec.eta,
                   help="sampler stochasticity: 0 = DDIM (default), 1 = DDPM-like")
    p.add_argument("--replan", choices=("always", "on_change"), default=spec.replan,
                   help="re-planning trigger of every re-planning row: before every move "
                        "('always', the paper) or only when new cells were seen or the plan's "
                        "sub-goal was reached ('on_change'); default: each row's own, "
                        + ", ".join(f"{m} {r}" for m, r in MODE_REPLAN.items()))
    p.add_argument("--batch-size", type=int, default=spec.eval_batch,
                   help=f"episodes per jitted evaluation call (default {spec.eval_batch})")
    p.add_argument("--figures", metavar="DIR",
                   help="write PNGs of a few episodes: map, executed path, and the predicted "
                        "paths and goal estimates at several re-plans")
    p.add_argument("--num-figures", type=int, default=None,
                   help="episodes drawn with --figures (default 4)")
    p.add_argument("--profile", metavar="DIR",
                   help="write a JAX profiler trace (TensorBoard / Perfetto) of one batch of "
                        "the main planning mode to DIR, after the evaluation")
    p.add_argument("--baselines", nargs="?", const="bc,cql,dd", default=None,
                   metavar="NAMES",
                   help="add rows of the shipped baselines (checkpoints/baselines; "
                        "comma-separated of bc,cql,dd; the flag alone: all three), measured on "
                        "the same episodes and seeds as the planner's rows")
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    return p


def write_profile(out_dir: str, spec, task, denoiser, episodes, seed: int, mode: str,
                  batch_size: int) -> None:
    """A profiler trace of one (already compiled) batch of ``mode``."""
    n = min(batch_size, int(np.shape(episodes.tokens)[0]))
    batch = jax.tree.map(lambda x: x[:n], episodes)
    evaluate_mode(spec, task, denoiser, batch, seed, mode, n, progress=False)  # compile
    with jax.profiler.trace(out_dir):
        evaluate_mode(spec, task, denoiser, batch, seed, mode, n, progress=False)


def parse_seeds(parser, args):
    """The evaluation seeds: --seeds (comma-separated) or --seed."""
    if args.seeds is None:
        return (args.seed,)
    try:
        seeds = tuple(int(x) for x in args.seeds.split(",") if x.strip())
    except ValueError:
        parser.error(f"--seeds must be comma-separated integers, got {args.seeds!r}")
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        parser.error(f"--seeds must be distinct non-negative integers, got {args.seeds!r}")
    return seeds


TRAIN_FLAGS = {"train_dir": "--train-dir", "train_steps": "--train-steps",
               "train_seed": "--train-seed", "checkpoint_every": "--checkpoint-every",
               "prediction": "--prediction", "model_size": "--model-size"}


def check_args(parser, args, spec):
    """Validates the arguments (one-line errors before any work) and fills the defaults of
    the flags that only make sense together with another one. Returns the modes."""
    from diffplan.planner import MODES
    from experiments import cli

    cli.only_with(parser, args, "train", TRAIN_FLAGS)
    cli.only_with(parser, args, "figures", {"num_figures": "--num-figures"})
    if args.train and args.checkpoint is not None:
        parser.error("--checkpoint and --train exclude each other: --train evaluates what it "
                     "trains (its output directory is --train-dir)")
    cli.check_at_least(parser, "--train-steps", args.train_steps, 2)
    cli.check_at_least(parser, "--checkpoint-every", args.checkpoint_every, 1)
    cli.check_at_least(parser, "--num-figures", args.num_figures, 1)
    cli.check_output_file(parser, "--json", args.json)
    cli.check_output_file(parser, "--trajectories", args.trajectories, suffix=".npz")
    cli.check_output_dir(parser, "--figures", args.figures)
    cli.check_output_dir(parser, "--train-dir", args.train_dir)
    cli.check_output_dir(parser, "--profile", args.profile)
    args.train_steps = spec.train_steps if args.train_steps is None else args.train_steps
    args.train_seed = 0 if args.train_seed is None else args.train_seed
    args.checkpoint_every = 500 if args.checkpoint_every is None else args.checkpoint_every
    args.prediction = spec.prediction if args.prediction is None else args.prediction
    args.model_size = "default" if args.model_size is None else args.model_size
    args.num_figures = 4 if args.num_figures is None else args.num_figures
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if not 0 <= args.eta <= 10 or args.eta != args.eta:
        parser.error(f"--eta must be in [0, 10], got {args.eta}")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.batch_size < 1:
        parser.error(f"--batch-size must be >= 1, got {args.batch_size}")
    if args.num_steps < 1:
        parser.error(f"--num-steps must be >= 1, got {args.num_steps}")
    warm_steps = args.num_steps if args.warm_num_steps is None else args.warm_num_steps
    if warm_steps < 1:
        parser.error(f"--warm-num-steps must be >= 1, got {warm_steps}")
    if not 0 <= args.warm_start_step < warm_steps:
        parser.error(f"--warm-start-step must be in 0..{warm_steps - 1}")
    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        parser.error(f"unknown --modes {bad}; choose from {MODES}")
    args.baselines = check_baselines(parser, args.baselines)
    return modes


def check_baselines(parser, names: str | None) -> tuple[str, ...]:
    """The --baselines names (distinct, known, with a shipped checkpoint); () without it."""
    if names is None:
        return ()
    from diffplan.baselines.policies import BASELINES

    chosen = tuple(n.strip() for n in names.split(",") if n.strip())
    bad = [n for n in chosen if n not in BASELINES]
    if bad or not chosen or len(set(chosen)) != len(chosen):
        parser.error(f"--baselines must be distinct names of {','.join(BASELINES)}, got "
                     f"{names!r}")
    root = os.path.join(CHECKPOINT_ROOT, "baselines")
    missing = [n for n in chosen if not os.path.isdir(os.path.join(root, n))]
    if missing:
        parser.error(f"no shipped baseline checkpoint for {','.join(missing)} under {root}: "
                     "make them with `python -m experiments.train_baselines --ship`")
    return chosen


def fail(message: str, code: int = 2):
    """Ends the program with one line on stderr (a user error, not a bug)."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(code)


def load_checked(checkpoint: str, spec: ExperimentSpec, modes, parser,
                 train_command: str | None = None):
    """The checkpoint's LoadedDenoiser, checked against the grid world and the requested step
    counts; one-line errors for a missing, unreadable or mismatched checkpoint (naming
    train_command, default the setting's `--train`, as the way to get one)."""
    from envs.gridworld.task import NUM_COND_CHANNELS

    try:
        denoiser, _ = load_model(checkpoint)
    except FileNotFoundError:
        command = train_command or f"python -m experiments.{spec.name} --train"
        fail(f"no checkpoint in {checkpoint}: train one with `{command}` (or pass another "
             "checkpoint directory)")
    except ValueError as e:
        fail(f"cannot read the checkpoint {checkpoint}: {e}")
    size = spec.grid_config().size
    h, w, g = denoiser.plan_shape
    if (denoiser.num_cond_channels, h, w) != (NUM_COND_CHANNELS, size, size) or g not in (2, 3):
        fail(f"the checkpoint {checkpoint} plans {h}x{w} maps with {denoiser.num_cond_channels} "
             f"condition and {g} generated channels; the grid world needs {size}x{size} with "
             f"{NUM_COND_CHANNELS} and 2 or 3")
    for mode in modes:
        try:
            spec.planner_config(mode).check_schedule(denoiser.schedule.num_train_steps)
        except ValueError as e:
            parser.error(str(e))
    return denoiser


def main(setting: str, argv: Sequence[str] | None = None) -> dict:
    spec = SPECS[setting]
    parser = build_parser(spec)
    args = parser.parse_args(argv)
    modes = check_args(parser, args, spec)
    seeds = parse_seeds(parser, args)
    spec = dataclasses.replace(spec, num_steps=args.num_steps,
                               warm_start_step=args.warm_start_step,
                               warm_num_steps=args.warm_num_steps,
                               fresh_noise=args.noise == "fresh", eta=args.eta,
                               replan=args.replan)
    enable_compilation_cache()
    progress = not args.no_progress

    train_seconds = None
    if args.train:
        spec = dataclasses.replace(spec, prediction=args.prediction)
        checkpoint = args.train_dir or spec.default_train_dir()
        from diffplan.train import ConfigMismatchError
        try:
            _, _, train_seconds = train_setting(
                spec, checkpoint, seed=args.train_seed, steps=args.train_steps,
                progress=progress, model_size=args.model_size,
                checkpoint_every=args.checkpoint_every)
        except ConfigMismatchError as e:
            fail(str(e))
    else:
        checkpoint = args.checkpoint or spec.default_checkpoint()
    denoiser = load_checked(checkpoint, spec, modes, parser)

    grid_config = spec.grid_config()
    task = spec.task(denoiser.num_gen_channels)
    per_seed = {seed: eval_episodes(grid_config, args.episodes, seed) for seed in seeds}
    episodes = concat_trees(list(per_seed.values()))
    rows, rollouts = [], {}
    for mode in modes:
        outs = [evaluate_mode(spec, task, denoiser, eps, seed, mode, args.batch_size, progress)
                for seed, eps in per_seed.items()]
        rollout_np = concat_trees([r for r, _ in outs])
        row = metrics_row(METHOD_NAMES[mode], rollout_np, episodes, sum(t for _, t in outs),
                          grid_config.has_reference)
        if len(seeds) > 1:
            add_intervals(row, rollout_np, episodes, grid_config.has_reference)
            row["per_seed"] = {
                str(seed): {k: v for k, v in metrics_row(
                    METHOD_NAMES[mode], r, eps, t, grid_config.has_reference).items()
                    if k in PER_SEED_FIELDS}
                for (seed, eps), (r, t) in zip(per_seed.items(), outs)}
        rows.append(row)
        rollouts[mode] = rollout_np
    if args.baselines:
        from experiments.baselines_eval import baseline_rows

        try:
            rows += baseline_rows(setting, seeds, args.episodes, args.batch_size, progress,
                                  methods=args.baselines, episodes_by_seed=per_seed)
        except (FileNotFoundError, ValueError) as e:
            fail(f"cannot evaluate the baselines: {e}")

    main_mode = spec.main_mode if spec.main_mode in modes else modes[0]
    result = {
        "experiment": spec.name,
        "episodes": args.episodes,
        "seed": seeds[0],
        "seeds": list(seeds),
        "validation": bool(VALIDATION_SEED in seeds),
        "setting": setting,
        "checkpoint": os.path.relpath(checkpoint, REPO_ROOT) if checkpoint else None,
        "num_steps": spec.num_steps,
        "warm_start_step": spec.warm_start_step,
        "warm_num_steps": spec.warm_num_steps or spec.num_steps,
        "noise": "fresh" if spec.fresh_noise else "episode",
        "eta": spec.eta,
        "replan": {mode: spec.replan_of(mode) for mode in modes if mode in MODE_REPLAN},
        "trajectories_method": METHOD_NAMES[main_mode],
        "train_seconds": train_seconds,
        "machine": f"{os.cpu_count()} CPU cores, jax {jax.__version__} on "
                   f"{jax.devices()[0].platform}",
        "rows": rows,
    }
    triggers = "; ".join(f"{METHOD_NAMES[m]} re-plans {TRIGGER_WORDS[r]}"
                         for m, r in result["replan"].items())
    print(f"\n{spec.name}: {args.episodes} episodes per seed, seed(s) "
          f"{','.join(map(str, seeds))}, {spec.num_steps} denoising steps per plan (warm start: "
          f"{result['warm_num_steps']}-step schedule from step {spec.warm_start_step}), "
          f"checkpoint {result['checkpoint']}" + (f"\n{triggers}" if triggers else ""))
    print(format_table(rows))
    if len(seeds) > 1:
        print(format_intervals(rows, seeds))
    if args.json:
        from experiments import cli

        cli.write_json(args.json, result)
    if args.trajectories:
        write_trajectories(args.trajectories, rollouts[main_mode], episodes, grid_config)
        print(f"wrote {args.trajectories} ({METHOD_NAMES[main_mode]} trajectories)")
    if args.profile:
        write_profile(args.profile, spec, task, denoiser, per_seed[seeds[0]], seeds[0],
                      main_mode, args.batch_size)
        print(f"wrote a profiler trace of one {METHOD_NAMES[main_mode]} batch to {args.profile}")
    if args.figures:
        from experiments.compile_figures import write_figures
        paths = write_figures(args.figures, spec, task, denoiser, per_seed[seeds[0]], seeds[0],
                              min(args.num_figures, args.episodes))
        print(f"wrote {len(paths)} figures to {args.figures}")
    return result
