"""The evaluation harness every experiment shares, whatever the world: seeds and the keys they
give, seeded episodes, the jitted rollout, pooled rates with intervals, one-line errors
and checkpoint checks (text tables: ``tables``). World-specific evaluation lives in
``experiments.gridworld`` / ``experiments.kuka``.

Seeds: evaluation episode i of seed S is ``generate(fold_in(PRNGKey(S), i), spec)`` (the
convention of ``envs.gridworld.export`` and ``envs.kuka.episode.episode_keys``); the planner's
key of episode i is ``fold_in(fold_in(PRNGKey(S), ROLLOUT_STREAM), i)``, so no result depends
on the batching. Every choice (psi, step counts, schedules, checkpoints) was made on
VALIDATION_SEED; tables report EVALUATION_SEEDS. Training draws from other key streams
(``envs.<world>.training.TRAIN_STREAM``).
"""
from __future__ import annotations

import functools
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from diffplan.language import LANGUAGES

LANGUAGE_CHOICES = {**{language: (language,) for language in LANGUAGES}, "all": LANGUAGES}
"""--language of the grid-world CLIs: one phrasing (diffplan.language.LANGUAGES; "unseen" the
held-out phrasings training never saw) or a row for each ("all"). The Kuka CLIs' are
experiments.kuka.spec.LANGUAGE_CHOICES."""

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CHECKPOINT_ROOT = os.path.join(REPO_ROOT, "checkpoints")
VALIDATION_SEED = 1000
"""The episodes every choice (psi, step counts, warm-start schedule, checkpoint) was made on."""
EVALUATION_SEEDS = (2001, 2002, 2003)
"""The seeds the README reports on; never used to choose anything."""
DEFAULT_EVAL_SEED = EVALUATION_SEEDS[0]
ROLLOUT_STREAM = 0x9A11
"""Folded into an evaluation seed's key to give the planner's keys (a stream of its own)."""


# ------------------------------------------------------------------------ seeds and keys

def episode_keys(seed: int, start: int, stop: int) -> jax.Array:
    """Keys (stop - start,) of evaluation episodes start..stop-1 of a seed."""
    root = jax.random.PRNGKey(seed)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(start, stop))


def planner_keys(seed: int, idx) -> jax.Array:
    """The planner's keys (len(idx),) of episodes idx of a seed."""
    root = jax.random.fold_in(jax.random.PRNGKey(seed), ROLLOUT_STREAM)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.asarray(idx))


@functools.lru_cache(maxsize=None)
def _batched(generate):
    """jit(vmap(generate)) over keys, the spec static: built once per world."""
    return jax.jit(jax.vmap(generate, in_axes=(0, None)), static_argnums=1)


def seeded_episodes(generate, spec, n: int, seed: int, chunk: int):
    """Episodes 0..n-1 of a seed, ``generate(key, spec)`` (spec hashable), in jitted calls of up
    to ``chunk``: an Episode of numpy arrays with a leading (n,) axis."""
    gen = _batched(generate)
    parts = [jax.device_get(gen(episode_keys(seed, lo, min(n, lo + chunk)), spec))
             for lo in range(0, n, chunk)]
    return concat_trees(parts)


def concat_trees(trees):
    """Concatenates pytrees of numpy arrays along their leading axis."""
    return jax.tree.map(lambda *xs: np.concatenate(xs), *trees)


def parse_seeds(parser, args) -> tuple[int, ...]:
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


def add_seed_flags(parser, *, episodes: int, episodes_help: str, where: str = "",
                   episode_of: str = "generated from fold_in(PRNGKey(seed), i)") -> None:
    """--episodes, --seed and --seeds (where: what episode i is drawn for, e.g. ' in each
    column'; episode_of: how episode i of a seed comes about, e.g. BabyAI's minigrid seed)."""
    parser.add_argument("--episodes", type=int, default=episodes,
                        help=f"{episodes_help} (default {episodes})")
    parser.add_argument("--seed", type=int, default=DEFAULT_EVAL_SEED,
                        help=f"evaluation seed: episode i is {episode_of}{where} (default "
                             f"{DEFAULT_EVAL_SEED}, an evaluation seed; training uses a "
                             "disjoint stream)")
    parser.add_argument("--seeds", metavar="S1,S2,...", default=None,
                        help="evaluate on several seeds (--episodes each) and report pooled "
                             "rates with 95%% intervals and per-seed values; the README uses "
                             f"{','.join(map(str, EVALUATION_SEEDS))} (evaluation seeds); "
                             f"{VALIDATION_SEED} is the validation seed every choice was made "
                             "on")


# ------------------------------------------------------------------------------- rollout

@functools.lru_cache(maxsize=None)
def policy_runner(task, act_fn, calls_per_move: int, plan_channels, observe):
    """jitted (params, keys, episodes) -> Rollout of one policy
    (diffplan.baselines.rollout.policy_rollout; cached: one compilation per task and
    architecture, in either world)."""
    from diffplan.baselines.rollout import policy_rollout

    return jax.jit(lambda params, keys, episodes: policy_rollout(
        task, act_fn, params, keys, episodes, calls_per_move=calls_per_move,
        plan_channels=plan_channels, observe=observe))


def rollout_fn(task, num_slots: int | None = None, mesh=None, progress: bool = True):
    """jitted (planner, keys (N,), episodes, token) -> Rollout: diffplan.rollout, or with
    num_slots the slot pool (diffplan.rollout_stream, re-planning modes), which reports its
    progress after every move to experiments.harness.progress.RELAY under ``token`` (int32 ());
    with ``progress=False`` it reports nothing (the same results): a program without a host
    callback is one JAX's persistent compilation cache keeps, so a run with no bar
    (``--no-progress``, the tests) compiles it once per machine, not once per process. The
    planner is an argument, so one compilation serves every checkpoint of the same
    architecture and every seed. With a mesh of several devices (of one process or of all,
    diffplan.distributed): the episodes split over them, each device its own rollout (or pool
    of num_slots slots, reporting as part ``token`` + its index) on N / devices episodes
    (diffplan.sharding.PerDevice: it places its arguments; read the output with
    diffplan.distributed.gather)."""
    from diffplan.rollouts import rollout, rollout_stream
    from experiments.harness.progress import RELAY as relay

    relay = relay if progress else None
    if mesh is not None and mesh.size > 1:
        from diffplan import sharding as shd

        def local(planner, keys, episodes, token):
            if num_slots is None:
                return rollout(task, planner, keys, episodes)
            return rollout_stream(task, planner, keys, episodes, num_slots, on_move=relay,
                                  token=token + jax.lax.axis_index(shd.DATA_AXIS))

        return shd.PerDevice(local, mesh, replicated_argnums=(0, 3))
    if num_slots is None:
        return jax.jit(lambda planner, keys, episodes, token: rollout(task, planner, keys,
                                                                      episodes))
    return jax.jit(lambda planner, keys, episodes, token: rollout_stream(
        task, planner, keys, episodes, num_slots, on_move=relay, token=token))


# ------------------------------------------------------------------ rows

def per_seed_values(rows_by_seed: dict, fields) -> dict:
    """{str(seed): the row's values of fields} (a pooled row's "per_seed")."""
    return {str(seed): {k: v for k, v in row.items() if k in fields}
            for seed, row in rows_by_seed.items()}


def machine() -> str:
    """The machine line of a results JSON."""
    return (f"{os.cpu_count()} CPU cores, jax {jax.__version__} on "
            f"{jax.devices()[0].platform}")


# ------------------------------------------------------------------- errors, checkpoints

def fail(message: str, code: int = 2):
    """Ends the program with one line on stderr (a user error, not a bug)."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(code)


def load_model(checkpoint_dir: str):
    """The LoadedDenoiser of a checkpoint (diffplan.load_denoiser) and its metadata; raises
    FileNotFoundError when there is none."""
    from diffplan.checkpoint import read_metadata
    from diffplan.denoiser import load_denoiser

    return load_denoiser(checkpoint_dir), read_metadata(checkpoint_dir)


def vocabulary_mismatch(metadata: dict, vocab_size: int | None, vocabulary) -> str | None:
    """Why a checkpoint (its metadata, its network's vocab_size) cannot read instructions
    tokenised with ``vocabulary`` (the world's word list): its recorded vocabulary differs, or
    (checkpoints that record none) its vocabulary size does. None if it can."""
    stored = (metadata.get("extra") or {}).get("vocabulary", metadata.get("vocabulary"))
    words = list(vocabulary)
    if stored is not None:
        if list(stored) == words:
            return None
        at = next((i for i, (a, b) in enumerate(zip(stored, words)) if a != b),
                  min(len(stored), len(words)))
        return (f"was trained on another vocabulary ({len(stored)} words, this world has "
                f"{len(words)}; first difference at id {at}): retrain it")
    if vocab_size is not None and vocab_size != len(words):
        return (f"reads a vocabulary of {vocab_size} words, this world's has {len(words)}: "
                "retrain it")
    return None


def load_checked(checkpoint: str, train_command: str, mismatch=None, vocabulary=None):
    """The checkpoint's LoadedDenoiser; one-line errors (exit 2) for a missing one (naming
    train_command as the way to get one), an unreadable one, one for which
    ``mismatch(denoiser)`` returns a message (the world's shape check), or one trained on
    another vocabulary than ``vocabulary`` (the world's words; token ids would mean other
    words)."""
    from diffplan.checkpoint import read_metadata
    from diffplan.denoiser import load_denoiser

    try:
        denoiser = load_denoiser(checkpoint)
    except FileNotFoundError:
        fail(f"no checkpoint in {checkpoint}: train one with `{train_command}` (or pass another "
             "checkpoint directory)")
    except ValueError as e:
        fail(f"cannot read the checkpoint {checkpoint}: {e}")
    problem = mismatch(denoiser) if mismatch is not None else None
    if not problem and vocabulary is not None:
        problem = vocabulary_mismatch(read_metadata(checkpoint),
                                      getattr(denoiser.model_config, "vocab_size", None),
                                      vocabulary)
    if problem:
        fail(f"the checkpoint {checkpoint} {problem}")
    return denoiser
