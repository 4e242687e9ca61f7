"""The port against minigrid, step for step: ``python -m envs.babyai.check_port`` runs
10,000 random action sequences over the three levels (layouts from minigrid resets with the
seeds ``seeds.evaluation_seed(CHECK_SEED, i)``; CHECK_SEED is no seed any result is reported on)
in minigrid and in the port (``jit(vmap)`` of a ``lax.scan`` over ``env.step``), and prints how
many steps agree on the observation image, reward, terminated and truncated, and the timings.
tests/test_babyai_port.py runs a slice of the same sequences (see its docstring).

Actions are drawn per step from :data:`ACTION_PROBS` (forward most often, every action
present), each sequence from a generator of its own (:func:`draw_sequence`), and a quarter of
the sequences get a step limit inside the sequence (minigrid's
``max_steps`` set after reset, the Episode's likewise), so truncation is exercised; sequences
go on after the episode ends, as minigrid does.
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from diffplan.jax_cache import enable_compilation_cache
from envs.babyai import env as port
from envs.babyai import episode as E
from envs.babyai import objects as O
from envs.babyai import seeds
from envs.babyai.config import LEVELS, make_config

CHECK_SEED = 7
ACTION_PROBS = np.array([0.15, 0.15, 0.35, 0.1, 0.08, 0.12, 0.05])
"""left, right, forward, pickup, drop, toggle, done."""
MIN_LEN, MAX_LEN = 20, 40


@dataclasses.dataclass
class Recorded:
    """N sequences of T actions on one level, as minigrid played them.

    episodes: Episode (numpy, leading axis N); actions int32 (N, T); images uint8
    (N, T + 1, 7, 7, 3) the observation after reset and after each action; rewards float64
    (N, T); terminated, truncated bool (N, T); length int32 (N,) the actions of each
    sequence that count (the rest of the row is padding)."""

    episodes: E.Episode
    actions: np.ndarray
    images: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    length: np.ndarray


def draw_sequence(seed: int, level: str, index: int, max_steps: int):
    """Sequence ``index`` of a level: (actions int32 (MAX_LEN,), length int (the actions that
    count), step limit int); its own generator, so a slice of the sequences is the same
    whatever the number drawn."""
    rng = np.random.default_rng([seed, list(LEVELS).index(level), index])
    actions = rng.choice(len(ACTION_PROBS), size=MAX_LEN, p=ACTION_PROBS).astype(np.int32)
    length = int(rng.integers(MIN_LEN, MAX_LEN + 1))
    limit = int(rng.integers(5, MAX_LEN + 1)) if rng.random() < 0.25 else max_steps
    return actions, length, limit


def record(level: str, n: int, start: int = 0, seed: int = CHECK_SEED) -> Recorded:
    """Plays sequences start .. start + n - 1 of a level in minigrid."""
    config = make_config(level)
    env = E.make_env(config)
    actions = np.zeros((n, MAX_LEN), np.int32)
    length = np.zeros(n, np.int32)
    images = np.zeros((n, MAX_LEN + 1, 7, 7, 3), np.uint8)
    rewards = np.zeros((n, MAX_LEN))
    terminated = np.zeros((n, MAX_LEN), bool)
    truncated = np.zeros((n, MAX_LEN), bool)
    episodes = []
    for i in range(n):
        actions[i], length[i], limit = draw_sequence(seed, level, start + i, config.max_steps)
        episode, _ = E.layout(env, config, seeds.evaluation_seed(seed, start + i))
        env.max_steps = limit
        episodes.append(episode.replace(max_steps=np.int32(limit)))
        images[i, 0] = env.gen_obs()["image"]
        for t in range(length[i]):
            obs, rewards[i, t], terminated[i, t], truncated[i, t], _ = env.step(actions[i, t])
            images[i, t + 1] = obs["image"]
    episodes = jax.tree.map(lambda *xs: np.stack(xs), *episodes)
    return Recorded(episodes, actions, images, rewards, terminated, truncated, length)


@jax.jit
def play(episodes: E.Episode, actions):
    """The port's (images uint8 (N, T + 1, 7, 7, 3), rewards float32 (N, T), terminated,
    truncated bool (N, T), changed bool (N, T) the action changed the grid) for episodes
    (N, ...) and actions int32 (N, T)."""

    def one(episode, acts):
        state = port.reset(episode)

        def body(s, a):
            new = port.step(s, a)
            changed = jnp.any(new.grid != s.grid)
            return new, (new.image, new.reward, new.terminated, new.truncated, changed)

        _, (images, rewards, term, trunc, changed) = jax.lax.scan(body, state, acts)
        return jnp.concatenate([state.image[None], images]), rewards, term, trunc, changed

    return jax.vmap(one)(episodes, actions)


def compare(rec: Recorded) -> dict[str, int]:
    """Counts over the steps within each sequence's length: "steps", and those where the port
    agrees with minigrid on the "image", "reward", "terminated", "truncated" and on "all" four;
    "resets" the initial observations that agree (of "sequences"); what the sequences
    exercised: minigrid's "successes" and "truncations", and the steps whose action changed the
    grid by "pickup", "drop", "toggle" (door or box)."""
    images, rewards, term, trunc, changed = jax.device_get(play(rec.episodes, rec.actions))
    valid = np.arange(rec.actions.shape[1])[None, :] < rec.length[:, None]
    same_image = (images[:, 1:] == rec.images[:, 1:]).all(axis=(2, 3, 4))
    same_reward = np.abs(rewards - rec.rewards) <= 1e-6
    same_term = term == rec.terminated
    same_trunc = trunc == rec.truncated
    every = same_image & same_reward & same_term & same_trunc
    return {"sequences": len(valid), "steps": int(valid.sum()),
            "resets": int((images[:, 0] == rec.images[:, 0]).all(axis=(1, 2, 3)).sum()),
            "image": int((same_image & valid).sum()), "reward": int((same_reward & valid).sum()),
            "terminated": int((same_term & valid).sum()),
            "truncated": int((same_trunc & valid).sum()), "all": int((every & valid).sum()),
            "successes": int((rec.terminated & valid).sum()),
            "truncations": int((rec.truncated & valid).sum()),
            **{O.ACTION_NAMES[a]: int((changed & valid & (rec.actions == a)).sum())
               for a in (O.PICKUP, O.DROP, O.TOGGLE)}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=10_000,
                        help="action sequences in all, spread evenly over the levels")
    args = parser.parse_args(argv)
    enable_compilation_cache()
    per_level = -(-args.sequences // len(LEVELS))
    ok = True
    for level in LEVELS:
        t0 = time.perf_counter()
        rec = record(level, per_level)
        t1 = time.perf_counter()
        counts = compare(rec)
        t2 = time.perf_counter()
        ok &= counts["all"] == counts["steps"] and counts["resets"] == counts["sequences"]
        print(f"{level}: {counts}  minigrid {t1 - t0:.1f} s ({per_level / (t1 - t0):.0f} "
              f"sequences/s), port {t2 - t1:.1f} s with compilation")
    print("port matches minigrid" if ok else "MISMATCH")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
