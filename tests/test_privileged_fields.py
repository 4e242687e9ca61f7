"""What the agent acts on (docs/DESIGN.md, "What the agent acts on"): the cells it has seen, the
instruction's tokens and what the denoiser returns; never the world's record of which object the
instruction names (``state.target``, ``state.reference``, ``state.reached_reference``), never an
unseen cell of ``state.grid``, never a hand-written parse of the instruction.

The proof is a decoy: every function of the agent's side of a task (condition, psi, the
re-planning triggers, the ranking of several plans) is handed a state whose privileged fields
are replaced by decoys that agree with everything the agent has seen (unseen obstacles become
free cells and free cells obstacles, unseen objects change class, the target and reference move,
the reference is marked reached when it is not and the other way round); the world's own side
(step, done, success) keeps the true state. Rollouts under every planner configuration the CLIs
expose must be identical, move for move. A control plants a read of ``state.target`` in psi
and shows the test catches it. A grep-like check (over the syntax tree) keeps the agent's side
of both worlds free of the privileged fields by name.
"""
from __future__ import annotations

import ast
import dataclasses
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import Planner, PlannerConfig, rollout
from envs.gridworld import grammar
from envs.gridworld.config import make_config
from envs.gridworld.episode import EMPTY_CELL, OBSTACLE_CELL, generate_batch
from envs.gridworld.task import GridTask, NUM_COND_CHANNELS
from test_planner import as_denoiser

ROOT = pathlib.Path(__file__).resolve().parents[1]
BATCH = 8
AGENT_SIDE = ("condition", "psi", "unfollowable", "plan_refuted", "plan_cost",
              "at_goal_estimate")
"""The task methods the planner's agent calls with the state (diffplan.rollouts.move);
reset, step, done and position are the world's (position is the agent's own cell)."""


def decoy_state(state):
    """The state with every privileged field replaced by a decoy that agrees with what the
    agent has seen: unseen obstacles and free cells swapped, unseen objects of another class,
    the target and reference mirrored to other cells, reached_reference negated."""
    grid = state.grid
    classes = len(grammar.OBJECT_NAMES)
    other = jnp.where(grid == OBSTACLE_CELL, EMPTY_CELL,
                      jnp.where(grid == EMPTY_CELL, OBSTACLE_CELL, grid % classes + 1))
    size = state.seen.shape[0]
    mirror = lambda cell: jnp.stack([size - 1 - cell[1], size - 1 - cell[0]]).astype(cell.dtype)
    return state.replace(grid=jnp.where(state.seen, grid, other).astype(grid.dtype),
                         target=mirror(state.reference), reference=mirror(state.target),
                         reached_reference=~state.reached_reference)


@dataclasses.dataclass(frozen=True)
class DecoyTask:
    """A task over (state, decoy) pairs: the world's methods see the true state; the agent's
    side sees :func:`decoy_state` of it where decoy (bool ()) is set. Episodes are (episode,
    decoy) pairs, so one compiled rollout runs every episode both ways side by side (each
    episode plans with its own key, so the two halves of a batch cannot influence each
    other)."""

    task: object

    def __getattr__(self, name):
        attr = getattr(self.task, name)
        if name in AGENT_SIDE:
            def agent_side(pair, *rest):
                state, decoy = pair
                seen_as = jax.tree.map(lambda d, s: jnp.where(decoy, d, s),
                                       decoy_state(state), state)
                return attr(seen_as, *rest)
            return agent_side
        return attr

    def reset(self, pair):
        episode, decoy = pair
        return self.task.reset(episode), decoy

    def tokens(self, pair):
        return self.task.tokens(pair[0])

    def step(self, pair, action):
        return self.task.step(pair[0], action), pair[1]

    def done(self, pair):
        return self.task.done(pair[0])

    def position(self, pair):
        return self.task.position(pair[0])


@dataclasses.dataclass(frozen=True)
class PeekingTask:
    """The planted defect of the control: psi steps toward ``state.target`` whenever the
    target is within 3 cells, as a planner that knew the instruction's object would."""

    task: object

    def __getattr__(self, name):
        return getattr(self.task, name)

    def psi(self, state, plan):
        delta = state.target - state.agent
        toward = jnp.where(delta[0] < 0, 0, jnp.where(delta[0] > 0, 2,
                                                      jnp.where(delta[1] > 0, 1, 3)))
        near = jnp.abs(delta).sum() <= 3
        return jnp.where(near, toward, self.task.psi(state, plan)).astype(jnp.int32)


def _guess_apply(params, x_t, t, tokens):
    """A parameter-free "x0 network" whose plans follow the sampler's noise and the seen
    cells: drawn paths and guesses all over the map, so that every trigger fires, psi falls
    back, several plans differ, and plans head for unseen cells."""
    del params
    gen = x_t[..., NUM_COND_CHANNELS:]
    seen = x_t[..., 4:5]
    bias = (tokens.sum(-1) % 5).astype(jnp.float32)[:, None, None, None] / 5.0
    scale = 1.0 + t.astype(jnp.float32)[:, None, None, None] / 100.0
    return jnp.tanh(2.0 * gen * scale - 0.6 * seen + bias - 0.4)


def _planner(config):
    return Planner(as_denoiser(_guess_apply, "x0"), config)


CLI_CONFIGS = (
    ("one_shot", "always", "search", 1),
    ("k_shot", "always", "follow", 1),
    ("on_the_fly", "always", "search", 1),
    ("warm_start", "on_change", "follow", 1),
    ("on_the_fly", "on_refuted", "follow", 2),
    ("warm_start", "on_refuted", "search", 2),
)
"""(mode, re-planning trigger, psi, plans drawn per re-plan), from what --modes, --replan,
--psi and --samples of the grid-world CLIs combine to (k_shot is the two-shot row): every mode,
every trigger, both psi and both one and several plans occur, and with them every agent-side
method (psi, unfollowable with the follow psi, at_goal_estimate in k_shot and with every
trigger but "always", plan_refuted with "on_refuted", plan_cost with several plans)."""


@pytest.fixture(scope="module")
def episodes():
    return {s: jax.tree.map(np.asarray, generate_batch(jax.random.PRNGKey(11),
                                                       make_config(s), BATCH))
            for s in ("p_mo2g", "p_mo2g_far", "mo1g")}


def _both_ways(task, config, episodes):
    """(plain, decoyed): the Rollouts of BATCH episodes with the true state on the agent's side
    and with decoys (numpy), from one compiled rollout of 2 x BATCH (episode, decoy) pairs."""
    pairs = (jax.tree.map(lambda x: np.concatenate([x, x]), episodes),
             np.repeat([False, True], BATCH))
    keys = jax.random.split(jax.random.PRNGKey(3), BATCH)
    keys = jnp.concatenate([keys, keys])
    out = jax.device_get(jax.jit(lambda k, e: rollout(DecoyTask(task), _planner(config), k, e))(
        keys, pairs))
    out = out.replace(final_state=out.final_state[0])
    half = lambda i: jax.tree.map(lambda x: x[i * BATCH:(i + 1) * BATCH], out)
    return half(0), half(1)


def _config(mode, replan, samples):
    return PlannerConfig(mode=mode, num_steps=2, warm_start_step=1, warm_num_steps=None,
                         replan=replan, samples=samples, k=2)


def _assert_same(a, b):
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.steps, b.steps)
    np.testing.assert_array_equal(a.denoiser_calls, b.denoiser_calls)
    np.testing.assert_array_equal(a.num_plans, b.num_plans)
    if a.fallback_moves is not None:
        np.testing.assert_array_equal(a.fallback_moves, b.fallback_moves)


@pytest.mark.parametrize("mode,replan,psi,samples", CLI_CONFIGS)
def test_rollouts_do_not_change_when_privileged_fields_are_decoys(mode, replan, psi, samples,
                                                                 episodes):
    setting = "p_mo2g_far"
    task = GridTask(make_config(setting), psi_kind=psi)
    plain, decoyed = _both_ways(task, _config(mode, replan, samples), episodes[setting])
    _assert_same(plain, decoyed)
    # The rollouts ran: the agent moved, and episodes ended both ways.
    assert (plain.steps > 0).all()


@pytest.mark.parametrize("setting", ("p_mo2g", "mo1g"))
def test_the_paper_settings_too(setting, episodes):
    task = GridTask(make_config(setting), psi_kind="follow")
    config = _config("on_the_fly", "on_refuted", 2)
    _assert_same(*_both_ways(task, config, episodes[setting]))


def test_the_decoys_differ_from_the_truth(episodes):
    """The decoys change what they claim to change (else the test above could not fail)."""
    eps = episodes["p_mo2g_far"]
    task = GridTask(make_config("p_mo2g_far"))
    states = jax.vmap(task.reset)(eps)
    decoys = jax.vmap(decoy_state)(states)
    assert (np.asarray(decoys.target) != np.asarray(states.target)).any(-1).all()
    assert (np.asarray(decoys.reference) != np.asarray(states.reference)).any(-1).all()
    unseen = ~np.asarray(states.seen)
    assert (np.asarray(decoys.grid)[unseen] != np.asarray(states.grid)[unseen]).all()
    seen = np.asarray(states.seen)
    np.testing.assert_array_equal(np.asarray(decoys.grid)[seen], np.asarray(states.grid)[seen])


def test_control_a_planted_read_of_the_target_is_caught(episodes):
    """The same comparison on a psi that peeks at state.target: the rollouts differ."""
    eps = episodes["p_mo2g_far"]
    task = PeekingTask(GridTask(make_config("p_mo2g_far")))
    config = _config("on_the_fly", "on_refuted", 1)
    plain, decoyed = _both_ways(task, config, eps)
    assert not np.array_equal(plain.positions, decoyed.positions)


# ------------------------------------------------------------------ by name, over the source

AGENT_SOURCES = {
    "envs/gridworld/task.py": {"target", "reference", "reached_reference"},
    "envs/kuka/task.py": {"constraints", "goal", "tower", "episode"},
    "diffplan/planner.py": {"target", "reference", "reached_reference", "constraints"},
    "diffplan/rollouts.py": {"target", "reference", "reached_reference", "constraints"},
}
"""Modules of the agent's side and the attributes they may never read."""


def privileged_reads(source: str, forbidden: set[str]) -> list[str]:
    """'line: attr' for every attribute access named in forbidden, and (the grid world) every
    read of ``<x>.grid`` outside ``known_grid``, which masks it with what was seen."""
    tree = ast.parse(source)
    found = []

    class Visitor(ast.NodeVisitor):
        function = None

        def visit_FunctionDef(self, node):
            outer, self.function = self.function, node.name
            self.generic_visit(node)
            self.function = outer

        def visit_Attribute(self, node):
            if node.attr in forbidden:
                found.append(f"{node.lineno}: .{node.attr}")
            if (node.attr == "grid" and isinstance(node.ctx, ast.Load)
                    and isinstance(node.value, ast.Name) and node.value.id == "state"
                    and self.function != "known_grid"):
                found.append(f"{node.lineno}: state.grid in {self.function}")
            self.generic_visit(node)

    Visitor().visit(tree)
    return found


@pytest.mark.parametrize("path", sorted(AGENT_SOURCES))
def test_the_agent_side_never_names_a_privileged_field(path):
    source = (ROOT / path).read_text()
    assert privileged_reads(source, AGENT_SOURCES[path]) == []


def test_control_the_source_check_finds_a_planted_read():
    planted = "def psi(state, plan):\n    return state.target[0] + state.grid[0, 0]\n"
    assert privileged_reads(planted, {"target"}) == ["2: .target", "2: state.grid in psi"]
    masked = "def known_grid(state):\n    return state.grid\n"
    assert privileged_reads(masked, {"target"}) == []
