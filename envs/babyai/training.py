"""Training data of the BabyAI denoiser: minigrid's layouts, cached, and examples labelled by
the expert's shortest route on the full map.

Layouts (:class:`Layouts`): minigrid resets with the training seeds
``seeds.training_seed(j)``, j = start .. start + count - 1 (a stream disjoint from every
evaluation seed, ``seeds.check_disjoint``; :func:`check_training_seeds` checks a cache), with
the expert's actions on each (:mod:`envs.babyai.expert`, run in the port), written once to an
``.npz`` (:func:`cached_layouts`) so that training never calls minigrid.

An example (:func:`training_example`): the state after the expert's first k actions (k uniform
over its route), then, with ``detour_prob``, 1..MAX_DETOUR random turns, moves and toggles;
its condition channels are the Task's (the agent's map from its own observations); the targets
of the generated channels come from the expert's route from that state on the true map: path
+1 on the route's cells (the agent's cell to the stand cell), goal +1 on the object it faces
there, sub-goal +1 on the stand cell, -1 elsewhere. The loss covers the level's cells (not the
padding), the goal and sub-goal channels weighted ``goal_loss_weight``.
"""
from __future__ import annotations

import dataclasses
import os
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from envs.babyai import episode as E
from envs.babyai import env, expert, seeds
from envs.babyai import objects as O
from envs.babyai.config import make_config
from envs.babyai.task import BabyAITask, NUM_GEN_CHANNELS, GOAL, SUBGOAL

CACHE_VERSION = 1
MAX_DETOUR = 6
DETOUR_ACTIONS = jnp.array([O.LEFT, O.RIGHT, O.FORWARD, O.FORWARD, O.TOGGLE], jnp.int32)
"""Actions a detour draws from (forward twice as often)."""


@dataclasses.dataclass
class Layouts:
    """N training layouts of a level (numpy).

    episodes: Episode (leading axis N); seeds int64 (N,) the minigrid seeds; missions str (N,);
    actions int8 (N, T) the expert's actions (padded with 'done'); lengths int32 (N,) how many
    of them it takes to succeed."""

    level: str
    episodes: E.Episode
    seeds: np.ndarray
    missions: np.ndarray
    actions: np.ndarray
    lengths: np.ndarray

    def __len__(self) -> int:
        return len(self.seeds)


@jax.jit
def _expert_run(episodes: E.Episode, steps: jnp.ndarray):
    """(actions int32 (N, T), lengths int32 (N,) actions to success, -1 if none) of the expert
    over T = steps.shape[0] steps of the port."""

    def one(episode):
        def body(s, _):
            a = jnp.where(s.done, O.DONE, expert.expert_action(s))
            nxt = env.step(s, a)
            return jax.tree.map(lambda x, y: jnp.where(s.done, x, y), s, nxt), a

        state, actions = jax.lax.scan(body, env.reset(episode), steps)
        return actions, jnp.where(state.terminated, state.step_count, -1)

    return jax.vmap(one)(episodes)


def build_layouts(level: str, count: int, start: int = 0, env_=None,
                  max_expert_steps: int = 256) -> Layouts:
    """Training layouts start .. start + count - 1 of a level (minigrid resets), with the
    expert's actions; a ValueError if the expert fails one within max_expert_steps."""
    config = make_config(level)
    env_ = E.make_env(config) if env_ is None else env_
    seed_list = np.array([seeds.training_seed(j) for j in range(start, start + count)], np.int64)
    pairs = [E.layout(env_, config, s) for s in seed_list]
    episodes = jax.tree.map(lambda *xs: np.stack(xs), *[p[0] for p in pairs])
    actions, lengths = jax.device_get(_expert_run(episodes, jnp.arange(max_expert_steps)))
    if (lengths < 0).any():
        raise ValueError(f"the expert did not finish {level} layout(s) "
                         f"{seed_list[lengths < 0].tolist()} in {max_expert_steps} steps")
    actions = actions[:, :int(lengths.max())].astype(np.int8)
    return Layouts(config.level, episodes, seed_list, np.array([p[1] for p in pairs]), actions,
                   lengths.astype(np.int32))


def check_training_seeds(layouts: Layouts, evaluation_seeds=(1000, 2001, 2002, 2003),
                         episodes: int = 10_000) -> None:
    """A ValueError if a layout's minigrid seed is the seed of evaluation episode i < episodes
    of one of evaluation_seeds, or outside the training stream."""
    low, high = seeds.seed_range(*seeds.STREAMS["training"])
    outside = [int(s) for s in layouts.seeds if not low <= s <= high]
    evaluation = {seeds.evaluation_seed(s, i) for s in evaluation_seeds for i in range(episodes)}
    shared = sorted(set(int(s) for s in layouts.seeds) & evaluation)
    if outside or shared:
        raise ValueError(f"training layouts reset with evaluation seeds {shared[:5]} or seeds "
                         f"outside the training stream {outside[:5]}")


def save_layouts(path, layouts: Layouts) -> None:
    """Writes the layouts to an .npz (atomically: a temporary file, then renamed)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = {f"episode_{f.name}": np.asarray(getattr(layouts.episodes, f.name))
              for f in dataclasses.fields(layouts.episodes)}
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, version=CACHE_VERSION, level=layouts.level, seeds=layouts.seeds,
                        missions=layouts.missions.astype(str), actions=layouts.actions,
                        lengths=layouts.lengths, **fields)
    os.replace(tmp, path)


def load_layouts(path) -> Layouts:
    """The layouts of an .npz written by :func:`save_layouts` (no pickles)."""
    with np.load(path, allow_pickle=False) as data:
        if int(data["version"]) != CACHE_VERSION:
            raise ValueError(f"{path} is a layout cache of version {int(data['version'])}, "
                             f"expected {CACHE_VERSION}")
        episodes = E.Episode(**{f.name: data[f"episode_{f.name}"]
                                for f in dataclasses.fields(E.Episode)})
        return Layouts(str(data["level"]), episodes, data["seeds"], data["missions"],
                       data["actions"], data["lengths"])


def default_cache_dir() -> pathlib.Path:
    """$DIFFPLAN_BABYAI_CACHE, else ~/.cache/diffplan-babyai."""
    return pathlib.Path(os.environ.get("DIFFPLAN_BABYAI_CACHE",
                                       pathlib.Path.home() / ".cache" / "diffplan-babyai"))


def cached_layouts(level: str, count: int, start: int = 0, cache_dir=None) -> Layouts:
    """The layouts of :func:`build_layouts`, read from ``<cache_dir>/<level>_<start>_<count>
    .npz`` if it is there (and holds those seeds), else built and written there."""
    level = make_config(level).level
    path = pathlib.Path(cache_dir or default_cache_dir()) / f"{level}_{start}_{count}.npz"
    want = np.array([seeds.training_seed(j) for j in range(start, start + count)], np.int64)
    if path.exists():
        layouts = load_layouts(path)
        if layouts.level == level and np.array_equal(layouts.seeds, want):
            return layouts
    layouts = build_layouts(level, count, start)
    save_layouts(path, layouts)
    return layouts


def _padded_labels(mask, shape):
    """float32 (Hp, Wp): +1 on mask (bool (H, W)), -1 elsewhere and on the padding."""
    h, w = mask.shape
    return jnp.pad(jnp.where(mask, 1.0, -1.0), ((0, shape[0] - h), (0, shape[1] - w)),
                   constant_values=-1.0)


def training_example(task: BabyAITask, episode: E.Episode, actions, length, key,
                     detour_prob: float = 0.5, goal_loss_weight: float = 3.0):
    """(x0 float32 (Hp, Wp, C + G), tokens int32 (L,), loss_mask float32 (Hp, Wp, G)) of one
    layout (episode, the expert's actions int (T,) and their number length int32 ()); see the
    module docstring."""
    k_key, d_key, n_key, a_key = jax.random.split(key, 4)
    k = jax.random.randint(k_key, (), 0, jnp.maximum(length, 1))
    detour = jnp.where(jax.random.uniform(d_key) < detour_prob,
                       jax.random.randint(n_key, (), 1, MAX_DETOUR + 1), 0)
    random_actions = DETOUR_ACTIONS[jax.random.randint(a_key, (MAX_DETOUR,), 0,
                                                       DETOUR_ACTIONS.shape[0])]
    i = jnp.arange(actions.shape[0] + MAX_DETOUR)
    expert_first = jnp.concatenate([actions.astype(jnp.int32), random_actions])
    sequence = jnp.where(i < k, expert_first, random_actions[jnp.clip(i - k, 0, MAX_DETOUR - 1)])
    state = play(task, episode, sequence, k + detour)
    path, goal, subgoal, cost = expert.expert_plan(state)
    shape = (task.height, task.width)
    gen = jnp.stack([_padded_labels(path, shape), _padded_labels(goal, shape),
                     _padded_labels(subgoal, shape)], axis=-1)
    x0 = jnp.concatenate([task.condition(state), gen], axis=-1)
    h, w = path.shape
    inside = jnp.zeros(shape, jnp.float32).at[:h, :w].set(1.0)
    weights = jnp.ones(NUM_GEN_CHANNELS).at[GOAL].set(goal_loss_weight).at[SUBGOAL].set(
        goal_loss_weight)
    usable = ~state.done & jnp.isfinite(cost)
    loss_mask = inside[..., None] * weights * usable
    return x0, episode.tokens, loss_mask


def play(task: BabyAITask, episode: E.Episode, actions, count):
    """The state after the first ``count`` (int32 ()) of ``actions`` (int (T,)) from the
    episode's reset (a ``lax.scan`` over all T; the rest leave the state as it is)."""

    def body(s, i):
        moved = task.step(s, actions[i].astype(jnp.int32))
        return jax.tree.map(lambda x, y: jnp.where(i < count, y, x), s, moved), None

    state, _ = jax.lax.scan(body, task.reset(episode), jnp.arange(actions.shape[0]))
    return state


def layout_sampler(layouts: Layouts):
    """sample(key, batch_size) -> (episodes, expert actions int32 (B, T), lengths int32 (B,))
    of batch_size layouts drawn uniformly, under ``jit``; the cache stays on the host (a
    ``jax.pure_callback`` fetches the drawn layouts), so a compiled step holds none of it and
    draws only these layouts (the denoiser's batches and BC's, ``envs.babyai.baselines``)."""
    host = jax.tree.map(np.asarray, layouts.episodes)
    actions, lengths = np.asarray(layouts.actions), np.asarray(layouts.lengths)
    n = len(layouts)

    def fetch(idx):
        idx = np.asarray(idx)
        return (jax.tree.map(lambda x: x[idx], host), actions[idx].astype(np.int32),
                lengths[idx])

    def sample(key, batch_size):
        idx = jax.random.randint(key, (batch_size,), 0, n)
        shapes = (jax.tree.map(lambda x: jax.ShapeDtypeStruct((batch_size,) + x.shape[1:],
                                                              x.dtype), host),
                  jax.ShapeDtypeStruct((batch_size, actions.shape[1]), jnp.int32),
                  jax.ShapeDtypeStruct((batch_size,), jnp.int32))
        return jax.pure_callback(fetch, shapes, idx)

    return sample


def make_batch_fn(task: BabyAITask, layouts: Layouts, detour_prob: float = 0.5,
                  goal_loss_weight: float = 3.0):
    """batch_fn(key, batch_size) -> (x0, tokens, loss_mask) with leading axis batch_size, the
    layouts drawn uniformly (:func:`layout_sampler`)."""
    sample = layout_sampler(layouts)

    def batch_fn(key, batch_size):
        pick_key, example_key = jax.random.split(key)
        episodes, acts, lens = sample(pick_key, batch_size)
        keys = jax.random.split(example_key, batch_size)
        return jax.vmap(lambda e, a, l, k: training_example(
            task, e, a, l, k, detour_prob, goal_loss_weight))(episodes, acts, lens, keys)

    return batch_fn


@dataclasses.dataclass(frozen=True)
class Recipe:
    """A BabyAI level's training-data recipe: ``num_layouts`` training layouts (from
    ``start``), cached in ``cache_dir`` (None: :func:`default_cache_dir`); detour_prob and
    goal_loss_weight: see :func:`training_example`."""

    level: str = "goto_local"
    num_layouts: int = 1000
    start: int = 0
    detour_prob: float = 0.5
    goal_loss_weight: float = 3.0
    cache_dir: str | None = None

    def task(self) -> BabyAITask:
        return BabyAITask(make_config(self.level))

    def layouts(self) -> Layouts:
        return cached_layouts(self.level, self.num_layouts, self.start, self.cache_dir)

    def batch_fn(self):
        return make_batch_fn(self.task(), self.layouts(), self.detour_prob,
                             self.goal_loss_weight)

    @property
    def batch_multiple(self) -> int:
        return 1

    def init_batch(self):
        fn = self.batch_fn()
        return jax.eval_shape(lambda k: fn(k, 1), jax.random.PRNGKey(0))

    def metadata(self) -> dict:
        task = self.task()
        return {"level": make_config(self.level).level, "num_layouts": self.num_layouts,
                "start": self.start, "detour_prob": self.detour_prob,
                "goal_loss_weight": self.goal_loss_weight, "vocab_size": task.vocab_size,
                "num_gen_channels": NUM_GEN_CHANNELS}
