"""Which minigrid seed each episode is reset with: three streams, disjoint by construction.

- evaluation episode ``i`` of seed ``S``: ``S * 2**20 + i`` (S < 2**11, i < 2**20), in
  [0, 2**31);
- training layout ``j``: ``2**31 + j`` (j < 2**31), in [2**31, 2**32);
- ``generate(key)`` (the registry's key -> Episode): ``2**32 + bits``, bits the key's 32
  random bits, in [2**32, 2**33).

:func:`check_disjoint` checks any set of streams against each other from their functions (it
raises on an overlap; tests/test_babyai_seeds.py plants one).
"""
from __future__ import annotations

from typing import Callable, Mapping

EPISODE_BITS = 20
SEED_BITS = 11
TRAINING_BASE = 2 ** 31
KEY_BASE = 2 ** 32


def _check(name: str, value: int, limit: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool):
        value = int(value)  # numpy ints
    if not 0 <= value < limit:
        raise ValueError(f"{name} must be in [0, {limit}), got {value}")
    return value


def evaluation_seed(seed: int, index: int) -> int:
    """The minigrid seed of evaluation episode ``index`` of seed ``seed``."""
    return _check("seed", seed, 2 ** SEED_BITS) * 2 ** EPISODE_BITS + _check(
        "episode index", index, 2 ** EPISODE_BITS)


def training_seed(index: int) -> int:
    """The minigrid seed of training layout ``index``."""
    return TRAINING_BASE + _check("training layout index", index, 2 ** 31)


def key_seed(bits: int) -> int:
    """The minigrid seed of ``generate(key)``, from the key's 32 random bits."""
    return KEY_BASE + _check("key bits", bits, 2 ** 32)


STREAMS: Mapping[str, tuple[Callable[..., int], tuple[int, ...]]] = {
    "evaluation": (evaluation_seed, (2 ** SEED_BITS, 2 ** EPISODE_BITS)),
    "training": (training_seed, (2 ** 31,)),
    "key": (key_seed, (2 ** 32,)),
}
"""name -> (seed function, the exclusive upper bound of each argument)."""


def seed_range(fn: Callable[..., int], limits: tuple[int, ...]) -> tuple[int, int]:
    """[low, high] of a seed function over its arguments in [0, limit) each, read at its
    corners; the function must be non-decreasing in each argument (checked on each axis's
    ends and middle, raises otherwise)."""
    lows = tuple(0 for _ in limits)
    highs = tuple(limit - 1 for limit in limits)
    for axis, limit in enumerate(limits):
        points = sorted({0, (limit - 1) // 2, limit - 1})
        values = [fn(*(lows[:axis] + (p,) + lows[axis + 1:])) for p in points]
        if values != sorted(values) or len(set(values)) != len(values):
            raise ValueError(f"{getattr(fn, '__name__', fn)} is not increasing in argument "
                             f"{axis}")
    return fn(*lows), fn(*highs)


def check_disjoint(streams: Mapping[str, tuple[Callable[..., int], tuple[int, ...]]] = STREAMS
                   ) -> dict[str, tuple[int, int]]:
    """{name: (low, high)} of each stream; a ValueError naming two streams whose ranges
    overlap."""
    ranges = {name: seed_range(fn, limits) for name, (fn, limits) in streams.items()}
    names = sorted(ranges, key=lambda n: ranges[n])
    for a, b in zip(names, names[1:]):
        if ranges[b][0] <= ranges[a][1]:
            raise ValueError(f"the seed streams {a!r} {ranges[a]} and {b!r} {ranges[b]} overlap")
    return ranges
