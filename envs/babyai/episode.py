"""Episodes: minigrid's own layouts as arrays.

An :class:`Episode` is a reset minigrid level turned into arrays (:func:`from_env`): the grid
of cell encodings, the agent's cell and heading, the described object (privileged: only the
world's verifier reads it), the step limit and the mission's token ids. Layouts come from
minigrid's level generators, which are Python: :func:`layout` resets minigrid with a seed on
the host. Unlike the grid world's pure ``generate(key)``, the registry's ``generate`` here
(:func:`make_generate`) calls minigrid through ``jax.pure_callback`` (it runs under ``jit``
and ``vmap``, one host reset per episode, the seed taken from the key's bits:
``envs.babyai.seeds.key_seed``); evaluation and training use :func:`layout` with the seeds of
``envs.babyai.seeds`` instead.
"""
from __future__ import annotations

import contextlib
import io
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.babyai import grammar, seeds
from envs.babyai import objects as O
from envs.babyai.config import BabyAIConfig


@struct.dataclass
class Episode:
    """One episode's fixed content (leading batch axes allowed).

    grid: uint8 (H, W, 3) minigrid's cell encodings (type, colour, state), [row, col].
    agent: int32 (2,) the agent's (row, col) at reset; agent_dir: int32 () 0..3 (east, south,
      west, north).
    target_type, target_color: int32 () the mission's object description (minigrid's type and
      colour indices). Privileged: the world's success check reads them, the agent never does.
    max_steps: int32 () minigrid's step limit.
    tokens: int32 (L,) the mission's token ids (``BabyAIConfig.tokenize``; 0 = padding).
    """

    grid: jax.Array
    agent: jax.Array
    agent_dir: jax.Array
    target_type: jax.Array
    target_color: jax.Array
    max_steps: jax.Array
    tokens: jax.Array


def make_env(config: BabyAIConfig):
    """A minigrid environment of the level (unwrapped: stepping skips gymnasium's checks)."""
    import gymnasium
    import minigrid  # noqa: F401  (registers the BabyAI levels)
    from minigrid.envs.babyai.core import verifier

    if verifier.use_done_actions:
        raise ValueError("BABYAI_DONE_ACTIONS is set: the port models minigrid's default, "
                         "where 'done' does nothing")
    return gymnasium.make(config.env_id).unwrapped


def reset_quietly(env, seed: int):
    """env.reset(seed=seed) without the level generator's 'Sampling rejected' prints."""
    with contextlib.redirect_stdout(io.StringIO()):
        return env.reset(seed=int(seed))


def from_env(env, config: BabyAIConfig) -> Episode:
    """The Episode (numpy arrays) of a reset minigrid level; a ValueError of one line when the
    level is not one the port and the Task handle (another mission, a grid with other types, a
    box holding something, something carried, another size)."""
    from minigrid.envs.babyai.core.verifier import GoToInstr

    if not isinstance(getattr(env, "instrs", None), GoToInstr):
        raise ValueError(f"the mission {getattr(env, 'mission', None)!r} is not a GoTo mission")
    desc = env.instrs.desc
    if desc.loc is not None or desc.type not in grammar.TYPES or desc.color is None:
        raise ValueError(f"the mission {env.mission!r} names no single colour and type")
    color, kind = grammar.parse(env.mission)
    if (grammar.COLORS[color], kind) != (desc.color, grammar.TYPE_INDEX[desc.type]):
        raise ValueError(f"the mission {env.mission!r} does not say what the verifier checks")
    if (env.height, env.width) != (config.height, config.width):
        raise ValueError(f"the level's grid is {env.height} x {env.width}, the config's "
                         f"{config.height} x {config.width}")
    if env.max_steps != config.max_steps or env.carrying is not None:
        raise ValueError(f"max_steps {env.max_steps} (expected {config.max_steps}) or carrying "
                         f"{env.carrying} differs from the level's")
    grid = np.transpose(env.grid.encode(), (1, 0, 2)).astype(np.uint8)  # [x, y] -> [row, col]
    if not np.isin(grid[..., 0], O.LEVEL_TYPES).all():
        raise ValueError("the grid holds a cell type the port does not model")
    for obj in env.grid.grid:
        if obj is not None and obj.type == "box" and obj.contains is not None:
            raise ValueError("a box holds an object (toggling it would not empty the cell)")
    x, y = (int(v) for v in env.agent_pos)
    return Episode(grid=grid, agent=np.array([y, x], np.int32),
                   agent_dir=np.int32(env.agent_dir),
                   target_type=np.int32(grammar.TYPE_INDEX[desc.type]),
                   target_color=np.int32(grammar.COLORS.index(desc.color)),
                   max_steps=np.int32(env.max_steps), tokens=config.tokenize(env.mission))


def layout(env, config: BabyAIConfig, seed: int) -> tuple[Episode, str]:
    """(Episode, mission) of the level reset with a minigrid seed (env: :func:`make_env`)."""
    reset_quietly(env, seed)
    return from_env(env, config), env.mission


def layouts(config: BabyAIConfig, seed_list, env=None) -> Episode:
    """The Episodes of several seeds stacked (numpy, leading axis len(seed_list))."""
    env = make_env(config) if env is None else env
    episodes = [layout(env, config, s)[0] for s in seed_list]
    return jax.tree.map(lambda *xs: np.stack(xs), *episodes)


def episode_shapes(config: BabyAIConfig) -> Episode:
    """jax.ShapeDtypeStruct of each field of one Episode of the level."""
    h, w = config.height, config.width
    scalar = jax.ShapeDtypeStruct((), jnp.int32)
    return Episode(grid=jax.ShapeDtypeStruct((h, w, 3), jnp.uint8),
                   agent=jax.ShapeDtypeStruct((2,), jnp.int32), agent_dir=scalar,
                   target_type=scalar, target_color=scalar, max_steps=scalar,
                   tokens=jax.ShapeDtypeStruct((config.max_tokens,), jnp.int32))


def make_generate(config: BabyAIConfig) -> Callable[[jax.Array], Episode]:
    """generate(key) -> Episode of a minigrid layout seeded with ``seeds.key_seed`` of the
    key's 32 random bits; jit- and vmap-able (``jax.pure_callback``, one host reset per
    episode). The minigrid environment is made on the first call and kept by this closure."""
    envs = []

    def host(bits):
        if not envs:
            envs.append(make_env(config))
        return layout(envs[0], config, seeds.key_seed(int(bits)))[0]

    def generate(key) -> Episode:
        bits = jax.random.bits(key, (), jnp.uint32)
        return jax.pure_callback(host, episode_shapes(config), bits, vmap_method="sequential")

    return generate
