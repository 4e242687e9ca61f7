"""Helpers shared by the Kuka tests: one batch size everywhere (so each jitted library function,
e.g. env.reset_batch, env.step_batch, expert.run_expert, physics.simulate_batch, compiles once
per test session and is reused from the persistent cache afterwards), and memoised episodes."""
from __future__ import annotations

import functools
import warnings

import jax
import numpy as np

MJX_CAST_WARNING = "ignore:overflow encountered in cast:RuntimeWarning"
"""Lowering MJX programs casts some of MuJoCo's float64 "unbounded" constants to float32; the
tests' pytestmark filters it (harmless)."""
warnings.filterwarnings("ignore", "overflow encountered in cast")

BATCH = 4
"""Episodes per jitted call in every Kuka test (the CLI tests pass --batch-size BATCH)."""


@functools.lru_cache(maxsize=None)
def _generator():
    from envs.kuka.config import COLUMNS
    from envs.kuka.episode import episode_keys, generate

    return jax.jit(jax.vmap(generate, in_axes=(0, None)), static_argnums=1)


@functools.lru_cache(maxsize=32)
def episodes(column: str, seed: int, language: str = "canonical"):
    """BATCH episodes (numpy Episode) of a Table 2 column: episodes 0..BATCH-1 of seed."""
    import dataclasses

    from envs.kuka.config import COLUMNS
    from envs.kuka.episode import episode_keys, generate

    spec = dataclasses.replace(COLUMNS[column], language=language)
    return jax.device_get(_generator()(episode_keys(seed, BATCH), spec))


@functools.lru_cache(maxsize=32)
def expert_run(column: str, seed: int):
    """(final env.State, frames) of the expert on episodes(column, seed), as numpy."""
    from envs.kuka import env, expert

    return jax.device_get(expert.run_expert(env.reset_batch(episodes(column, seed))))


def numpy_on(pos, held, top, bottom) -> bool:
    """Contract 4's "top on bottom" in plain numpy (pos (4, 3), held (4,), block half height
    0.03 m): xy distance < 0.1, |bottom of top - top of bottom| < 0.015, neither held."""
    pos = np.asarray(pos, np.float64)
    xy = np.hypot(*(pos[top, :2] - pos[bottom, :2]))
    gap = (pos[top, 2] - 0.03) - (pos[bottom, 2] + 0.03)
    return bool(xy < 0.1 and abs(gap) < 0.015 and not held[top] and not held[bottom])


@functools.lru_cache(maxsize=None)
def training_tokens(broad: bool, step: int) -> np.ndarray:
    """Token ids (4 x 16, ...) of a batch of the shipped Kuka recipe (envs.kuka.training.Recipe,
    its 16 shares; broad: its paraphrased shares drawing the language "broad", the grammar's
    extra phrasings too) under PRNGKey(step). One compiled batch function per recipe serves
    every test that reads training batches (tests/test_language_split.py,
    tests/test_kuka_heldout.py)."""
    import dataclasses

    from diffplan import language
    from envs.kuka.training import Recipe

    recipe = Recipe()
    if broad:
        recipe = Recipe(specs=tuple(dataclasses.replace(s, language=language.BROAD)
                                    if s.language == "paraphrased" else s
                                    for s in recipe.specs))
    return np.asarray(_batch_fn(recipe)(jax.random.PRNGKey(step), 4 * recipe.batch_multiple)
                      .tokens)


@functools.lru_cache(maxsize=None)
def _batch_fn(recipe):
    return jax.jit(recipe.batch_fn(), static_argnums=1)


def strict_counts(episodes, final, strict) -> tuple[int, int]:
    """(held, total) instructed constraints of a batch, each strict success (``strict`` bool
    (N, K), experiments.kuka.eval.constraint_success) checked against the final physical poses
    in plain numpy (:func:`numpy_on`); padding constraints (top < 0) left out."""
    held = total = 0
    for i, constraints in enumerate(np.asarray(episodes.constraints)):
        for (top, bottom), ok in zip(constraints, strict[i]):
            if top >= 0:
                assert ok == numpy_on(final["block_pos"][i], final["held"][i], top, bottom)
                held, total = held + int(ok), total + 1
    return held, total
