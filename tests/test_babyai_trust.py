"""The trust rule (docs/DESIGN.md, "What the agent acts on") in the BabyAI levels: the agent's
side of BabyAITask (condition, psi, the re-planning triggers, the plan ranking) reads its map
(written from its 7 x 7 observations), its pose, what it carries, the cells ruled out by the
episode going on, the instruction's tokens and the plan; never the true grid's cells it has not
seen, never the verifier's positions of the instructed object nor the Episode's description
of it.

The decoy: every agent-side call gets a state whose privileged fields are replaced by decoys
consistent with everything seen (each never-seen cell of the true grid changed: walls become
empty, empty cells balls, objects and doors another colour; the verifier's positions and the
tracked objects moved to other cells, carrying_tracked negated); the world's side keeps the
truth. Rollouts through diffplan.rollout under every mode and trigger must be identical, move
for move. A control plants a read of ``state.target`` in psi; the test catches it. A check
over the syntax tree keeps the agent-side modules free of the privileged names.
"""
from __future__ import annotations

import ast
import dataclasses
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import LoadedDenoiser, Planner, PlannerConfig, rollout
from diffplan.schedule import cosine_schedule
from envs.babyai import episode as E
from envs.babyai import objects as O
from envs.babyai import seeds
from envs.babyai.config import make_config
from envs.babyai.task import BabyAITask, NUM_COND_CHANNELS, SEEN_CHANNEL
from test_privileged_fields import DecoyTask as GridDecoyTask

ROOT = pathlib.Path(__file__).resolve().parents[1]
BATCH = 6
AGENT_SIDE = ("condition", "psi", "plan_refuted", "plan_cost", "at_goal_estimate")
TRUST_SEED = 9
"""The layouts: evaluation_seed(TRUST_SEED, i), no seed any result is reported on."""


def decoy_state(state):
    """The state with its privileged fields replaced by decoys consistent with what the agent
    has seen (module docstring)."""
    grid = jnp.asarray(state.grid)
    unseen = jnp.asarray(state.known[..., 0]) == O.UNSEEN
    kind, color = grid[..., 0], grid[..., 1]
    other = jnp.where((kind == O.WALL)[..., None], jnp.asarray(O.EMPTY_CELL, jnp.uint8),
                      jnp.where((kind == O.EMPTY)[..., None],
                                jnp.stack([jnp.full_like(kind, O.BALL), (color + 2) % 6,
                                           jnp.zeros_like(kind)], -1),
                                grid.at[..., 1].set(((color + 1) % 6).astype(jnp.uint8))))
    flip = lambda m: jnp.roll(jnp.flip(m, (0, 1)), 1, axis=0)
    return state.replace(grid=jnp.where(unseen[..., None], other, grid).astype(jnp.uint8),
                         target=flip(state.target), tracked=flip(state.tracked),
                         carrying_tracked=~state.carrying_tracked)


@dataclasses.dataclass(frozen=True)
class DecoyTask(GridDecoyTask):
    """(state, decoy) pairs (the grid world's DecoyTask: reset, tokens, step, done and position
    are the world's, on the true state); the agent's side sees :func:`decoy_state` of it where
    decoy (bool ()) is set."""

    def __getattr__(self, name):
        attr = getattr(self.task, name)
        if name not in AGENT_SIDE:
            return attr

        def agent_side(pair, *rest):
            state, decoy = pair
            return attr(jax.tree.map(lambda d, s: jnp.where(decoy, d, s), decoy_state(state),
                                     state), *rest)
        return agent_side


@dataclasses.dataclass(frozen=True)
class PeekingTask:
    """The planted defect: psi heads for the instructed object's cell (state.target) instead
    of the plan's goal estimate."""

    task: object

    def __getattr__(self, name):
        return getattr(self.task, name)

    def psi(self, state, plan):
        h, w = state.target.shape
        goal = jnp.pad(jnp.where(state.target, 1.0, -1.0),
                       ((0, plan.shape[0] - h), (0, plan.shape[1] - w)), constant_values=-1.0)
        return self.task.psi(state, plan.at[..., 1].set(goal))


def _guess_apply(params, x_t, t, tokens):
    """A parameter-free "x0 network": plans that follow the sampler's noise, the seen cells and
    the tokens, so that goal estimates land on seen and unseen cells and every trigger fires."""
    del params
    gen = x_t[..., NUM_COND_CHANNELS:]
    seen = x_t[..., SEEN_CHANNEL:SEEN_CHANNEL + 1]
    bias = (tokens.sum(-1) % 5).astype(jnp.float32)[:, None, None, None] / 5.0
    scale = 1.0 + t.astype(jnp.float32)[:, None, None, None] / 100.0
    return jnp.tanh(2.0 * gen * scale - 0.6 * seen + bias - 0.4)


def _planner(task, config):
    den = LoadedDenoiser(params=None, schedule=cosine_schedule(100), apply_fn=_guess_apply,
                         prediction="x0", plan_shape=(task.height, task.width, 3),
                         num_cond_channels=NUM_COND_CHANNELS)
    return Planner(den, config)


CONFIGS = (
    ("one_shot", "always", 1),
    ("k_shot", "always", 1),
    ("on_the_fly", "always", 1),
    ("warm_start", "on_change", 1),
    ("on_the_fly", "on_refuted", 2),
    ("warm_start", "on_refuted", 2),
)
"""(mode, trigger, plans per re-plan): every mode and trigger, one and several plans, so every
agent-side method runs."""


@pytest.fixture(scope="module")
def episodes():
    out = {}
    for level in ("goto_local", "goto_obj_maze"):
        config = make_config(level)
        out[level] = E.layouts(config, [seeds.evaluation_seed(TRUST_SEED, i)
                                        for i in range(BATCH)])
    return out


def _config(mode, replan, samples):
    return PlannerConfig(mode=mode, num_steps=2, warm_start_step=1, warm_num_steps=None,
                         replan=replan, samples=samples, k=2)


def _both_ways(task, config, episodes):
    pairs = (jax.tree.map(lambda x: np.concatenate([x, x]), episodes),
             np.repeat([False, True], BATCH))
    keys = jax.random.split(jax.random.PRNGKey(3), BATCH)
    keys = jnp.concatenate([keys, keys])
    out = jax.device_get(jax.jit(lambda k, e: rollout(DecoyTask(task), _planner(task, config),
                                                      k, e))(keys, pairs))
    out = out.replace(final_state=out.final_state[0])
    half = lambda i: jax.tree.map(lambda x: x[i * BATCH:(i + 1) * BATCH], out)
    return half(0), half(1)


def _assert_same(a, b):
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.steps, b.steps)
    np.testing.assert_array_equal(a.final_state.direction, b.final_state.direction)
    np.testing.assert_array_equal(a.final_state.grid, b.final_state.grid)
    np.testing.assert_array_equal(a.denoiser_calls, b.denoiser_calls)
    np.testing.assert_array_equal(a.num_plans, b.num_plans)


@pytest.mark.parametrize("mode,replan,samples", CONFIGS)
def test_rollouts_do_not_change_when_privileged_fields_are_decoys(mode, replan, samples,
                                                                 episodes):
    task = BabyAITask(make_config("goto_local"))
    plain, decoyed = _both_ways(task, _config(mode, replan, samples), episodes["goto_local"])
    _assert_same(plain, decoyed)
    assert (plain.steps > 0).all()


def test_the_maze_level_too(episodes):
    task = BabyAITask(make_config("goto_obj_maze"))
    plain, decoyed = _both_ways(task, _config("on_the_fly", "on_refuted", 2),
                                episodes["goto_obj_maze"])
    _assert_same(plain, decoyed)
    # the agent toggled doors: the grid changed along the way
    assert (plain.final_state.grid != episodes["goto_obj_maze"].grid).any()


def test_the_decoys_differ_from_the_truth(episodes):
    """The decoys change what they claim to change (else the test above could not fail)."""
    task = BabyAITask(make_config("goto_local"))
    states = jax.vmap(task.reset)(episodes["goto_local"])
    decoys = jax.device_get(jax.vmap(decoy_state)(states))
    states = jax.device_get(states)
    unseen = states.known[..., 0] == O.UNSEEN
    assert unseen.any()
    assert (decoys.grid[unseen] != states.grid[unseen]).any(-1).all()
    np.testing.assert_array_equal(decoys.grid[~unseen], states.grid[~unseen])
    assert (decoys.target != states.target).any(axis=(1, 2)).all()


def test_control_a_planted_read_of_the_target_is_caught(episodes):
    task = PeekingTask(BabyAITask(make_config("goto_local")))
    plain, decoyed = _both_ways(task, _config("on_the_fly", "always", 1),
                                episodes["goto_local"])
    assert not np.array_equal(plain.positions, decoyed.positions)


def test_a_decoy_episode_description_leaves_the_actions_alone(episodes):
    """The Episode's own privileged fields: a description of an object the layout does not
    hold (so the decoyed episode never ends early) and other never-seen cells; the agent's
    moves over the true episode's length are the same."""
    task = BabyAITask(make_config("goto_local"))
    eps = episodes["goto_local"]
    config = _config("on_the_fly", "always", 1)
    planner = _planner(task, config)
    keys = jax.random.split(jax.random.PRNGKey(5), BATCH)
    run = jax.jit(lambda k, e: rollout(task, planner, k, e))
    plain = jax.device_get(run(keys, eps))
    # every cell seen during the true rollout, over the whole episode
    seen = plain.final_state.known[..., 0] != O.UNSEEN
    absent = np.array([next((t, c) for t in (O.KEY, O.BALL, O.BOX) for c in range(6)
                            if not ((g[..., 0] == t) & (g[..., 1] == c)).any())
                       for g in eps.grid], np.int32)
    assert (absent != np.stack([eps.target_type, eps.target_color], -1)).any(-1).all()
    decoyed_eps = eps.replace(
        grid=np.where(seen[..., None], eps.grid,
                      np.asarray(decoy_state(plain.final_state).grid)).astype(np.uint8),
        target_type=absent[:, 0], target_color=absent[:, 1])
    decoyed = jax.device_get(run(keys, decoyed_eps))
    for i in range(BATCH):
        n = int(plain.steps[i])
        np.testing.assert_array_equal(plain.positions[i, :n + 1], decoyed.positions[i, :n + 1])


AGENT_SOURCES = ("envs/babyai/task.py", "envs/babyai/navigate.py", "envs/babyai/view.py")
FORBIDDEN = {"grid", "target", "tracked", "carrying_tracked", "target_type", "target_color"}


def privileged_reads(source: str) -> list[str]:
    """'line: .attr' for every attribute read named in FORBIDDEN."""
    return [f"{node.lineno}: .{node.attr}" for node in ast.walk(ast.parse(source))
            if isinstance(node, ast.Attribute) and node.attr in FORBIDDEN]


@pytest.mark.parametrize("path", AGENT_SOURCES)
def test_the_agent_side_never_names_a_privileged_field(path):
    assert privileged_reads((ROOT / path).read_text()) == []


def test_control_the_name_check_finds_a_planted_read():
    source = (ROOT / "envs/babyai/task.py").read_text()
    planted = source + "\n\ndef peek(state):\n    return state.target\n"
    assert privileged_reads(planted) == [f"{len(planted.splitlines())}: .target"]
