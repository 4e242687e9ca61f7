"""The BabyAI GoTo levels as a planner task: the agent's map as condition channels, psi.

Planning tensor (map_height x map_width x (C + G), C = 8, G = 3), allocentric, [row, col] of
the level's grid, padded at the bottom and right with known walls to the config's multiple:
  channel 0  cell token id (float-valued integer): ``cell_id_base`` + the cell's kind
             (:func:`cell_kinds`: unseen, empty, wall, a door of each colour and state, a key,
             ball or box of each colour) as the agent last saw it,
  channel 1  seen (0/1),
  channel 2  known blocked: a wall, key, ball, box or locked door (0/1),
  channel 3  known closed door (passable by toggling it; 0/1),
  channel 4  the agent's cell (0/1),
  channels 5-6  the agent's heading (d_row, d_col) on its cell, 0 elsewhere,
  channel 7  ruled out: cells the agent has faced after an action without the episode ending
             (no object the mission names is there; 0/1),
  channel 8  path: +1 on the cells of the plan's route, -1 elsewhere,
  channel 9  goal estimate: +1 on the cell of the object the plan believes the mission names,
  channel 10 sub-goal: +1 on the cell to stand on, facing the goal.

What the agent acts on (the trust rule, docs/DESIGN.md): its map (``State.known``, written only
from its 7 x 7 observations, :mod:`envs.babyai.view`), its own pose, what it carries,
``State.ruled_out``, the instruction's tokens and the plan. Never ``State.grid`` (the true
world), ``State.target`` / ``tracked`` / ``carrying_tracked`` or the Episode's
``target_type`` / ``target_color`` (tests/test_babyai_trust.py: decoys and a check over the
source). The agent's pose is its own: minigrid places it, and its cell and heading follow from
its actions and the cell in front, which it always sees.

psi (:func:`psi`): the goal estimate is the goal channel's argmax among cells that may hold an
object (unseen, or seen holding a key, ball or box, and not ruled out) and that the agent can
reach on its map (:func:`reachable`; all of them if it can reach none); the stand cells are its
4-neighbours not known to be blocked. A least-cost route over the cells not known to be blocked
(unseen cells assumed free; a closed door costs a toggle more; a cell the plan's path marks
costs less, ``path_weight``; a stand cell the plan's sub-goal marks is preferred,
``subgoal_weight``), then :func:`envs.babyai.navigate.act`: turn, forward, toggle a closed door
in front, and on a stand cell turn to face the goal and act "done" (the world checks the
mission after every action).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from envs.babyai import env, grammar, navigate
from envs.babyai import objects as O
from envs.babyai.config import BabyAIConfig
from envs.babyai.episode import Episode

NUM_COND_CHANNELS = 8
NUM_GEN_CHANNELS = 3
(ID_CHANNEL, SEEN_CHANNEL, BLOCKED_CHANNEL, DOOR_CHANNEL, AGENT_CHANNEL, HEAD_ROW_CHANNEL,
 HEAD_COL_CHANNEL, RULED_OUT_CHANNEL) = range(NUM_COND_CHANNELS)
PATH, GOAL, SUBGOAL = range(NUM_GEN_CHANNELS)
"""The generated channels' indices within a plan (H, W, G)."""
REFUTED_PLAN_COST = 1e4
FIRST_OBJECT_KIND = 21
"""Kinds FIRST_OBJECT_KIND .. NUM_KINDS - 1 are the keys, balls and boxes (:func:`_kind_table`)."""


def _kind_table() -> np.ndarray:
    """int32 (NUM_TYPES, NUM_COLORS, 3): the kind of each (type, colour, state) encoding."""
    table = np.full((O.NUM_TYPES, O.NUM_COLORS, 3), 2, np.int32)   # anything else: as a wall
    table[O.UNSEEN], table[O.EMPTY] = 0, 1
    for color in range(O.NUM_COLORS):
        for state in (O.OPEN, O.CLOSED, O.LOCKED):
            table[O.DOOR, color, state] = 3 + 3 * color + state
        for i, kind in enumerate((O.KEY, O.BALL, O.BOX)):
            table[kind, color, :] = FIRST_OBJECT_KIND + 6 * i + color
    return table


KIND_TABLE = _kind_table()
NUM_KINDS = 39
WALL_KIND = 2


def cell_kinds(cells):
    """int32 (...): the kind 0..NUM_KINDS-1 of cell encodings uint8 (..., 3)."""
    table = jnp.asarray(KIND_TABLE)
    c = cells.astype(jnp.int32)
    return table[jnp.clip(c[..., 0], 0, O.NUM_TYPES - 1), jnp.clip(c[..., 1], 0, O.NUM_COLORS - 1),
                 jnp.clip(c[..., 2], 0, 2)]


def known_blocked(known):
    """bool (H, W): cells the agent has seen to be a wall, an object or a locked door."""
    kind = known[..., 0]
    return (kind == O.WALL) | O.pickable(known) | ((kind == O.DOOR) & (known[..., 2] == O.LOCKED))


def known_closed_door(known):
    """bool (H, W): cells the agent has seen to be a closed (unlocked) door."""
    return (known[..., 0] == O.DOOR) & (known[..., 2] == O.CLOSED)


def may_hold_object(state: env.State):
    """bool (H, W): cells the mission's object may be in, for all the agent knows: unseen, or
    seen holding a key, ball or box; never a ruled-out cell."""
    known = state.known
    return ((known[..., 0] == O.UNSEEN) | O.pickable(known)) & ~state.ruled_out


def condition(state: env.State, config: BabyAIConfig, cell_id_base: int):
    """float32 (map_height, map_width, C): the condition channels (module docstring)."""
    known = state.known
    h, w = known.shape[:2]
    agent = jnp.zeros((h, w), bool).at[state.pos[0], state.pos[1]].set(True)
    heading = O.DIR_DELTA[state.direction].astype(jnp.float32)
    channels = jnp.stack([
        (cell_id_base + cell_kinds(known)).astype(jnp.float32),
        (known[..., 0] != O.UNSEEN).astype(jnp.float32),
        known_blocked(known).astype(jnp.float32),
        known_closed_door(known).astype(jnp.float32),
        agent.astype(jnp.float32),
        agent * heading[0],
        agent * heading[1],
        state.ruled_out.astype(jnp.float32),
    ], axis=-1)
    pad_h, pad_w = config.map_height - h, config.map_width - w
    wall = jnp.zeros(NUM_COND_CHANNELS, jnp.float32).at[ID_CHANNEL].set(
        cell_id_base + WALL_KIND).at[SEEN_CHANNEL].set(1.0).at[BLOCKED_CHANNEL].set(1.0)
    padded = jnp.broadcast_to(wall, (config.map_height, config.map_width, NUM_COND_CHANNELS))
    return padded.at[:h, :w].set(channels) if (pad_h or pad_w) else channels


def _argmax_cell(values, allowed):
    """int32 (2,): the argmax cell of values float32 (H, W) among allowed (bool (H, W))."""
    w = values.shape[1]
    flat = jnp.argmax(jnp.where(allowed, values, -jnp.inf).ravel())
    return jnp.stack([flat // w, flat % w]).astype(jnp.int32)


def reachable(state: env.State):
    """bool (H, W): cells the agent can walk to or stand beside on its map: a route from its
    cell over cells not known to be blocked (unseen cells assumed free, closed doors passable)
    ends on the cell or on a 4-neighbour of it."""
    blocked = known_blocked(state.known)
    enter = jnp.where(blocked, jnp.inf, 1.0)
    start = jnp.full(blocked.shape, jnp.inf).at[state.pos[0], state.pos[1]].set(0.0)
    return jnp.isfinite(navigate.cost_to_go(enter, start))


def goal_estimate(state: env.State, plan):
    """int32 (2,): the cell psi heads for the object of (plan float32 (H, W, G) cropped to the
    level's grid): the goal channel's argmax among :func:`may_hold_object` cells the agent can
    reach (:func:`reachable`), or among all of them when it can reach none (an unseen cell
    walled in on the agent's map, e.g. inside a wall it has seen around, can never be faced:
    heading for it would leave the agent turning on the spot)."""
    candidates = may_hold_object(state)
    within = candidates & reachable(state)
    return _argmax_cell(plan[..., GOAL], jnp.where(jnp.any(within), within, candidates))


def _route_field(state: env.State, plan, path_weight: float, subgoal_weight: float):
    """(field, enter, goal, stand) of psi's search (see the module docstring), plan cropped."""
    known = state.known
    h, w = known.shape[:2]
    goal_cell = goal_estimate(state, plan)
    goal = jnp.zeros((h, w), bool).at[goal_cell[0], goal_cell[1]].set(True)
    blocked = known_blocked(known)
    stand = navigate.adjacent(goal) & ~blocked & ~goal
    marked = (jnp.clip(plan[..., PATH], -1, 1) + 1) / 2
    enter = jnp.where(blocked | goal, jnp.inf,
                      1.0 + known_closed_door(known) + path_weight * (1 - marked))
    preferred = (jnp.clip(plan[..., SUBGOAL], -1, 1) + 1) / 2
    start = jnp.where(stand, subgoal_weight * (1 - preferred), jnp.inf)
    return navigate.cost_to_go(enter, start), enter, goal, stand, goal_cell


@dataclasses.dataclass(frozen=True)
class BabyAITask:
    """diffplan.Task of a BabyAI GoTo level (see the module docstring).

    config: the level. path_weight: the extra cost of entering a cell the plan's path does not
    mark (0: psi ignores the path). subgoal_weight: the extra cost of ending on a stand cell
    the plan's sub-goal does not mark. cell_id_base: the token id of cell kind 0 (channel 0);
    the default puts cell ids after the GoTo grammar's words, so one embedding table of
    :attr:`vocab_size` rows serves words and cells (a pretrained tokenizer's vocabulary size
    goes here instead).
    """

    config: BabyAIConfig
    path_weight: float = 1.0
    subgoal_weight: float = 2.0
    cell_id_base: int = grammar.VOCAB_SIZE
    num_cond_channels: int = NUM_COND_CHANNELS
    num_gen_channels: int = NUM_GEN_CHANNELS

    def __post_init__(self):
        if self.num_cond_channels != NUM_COND_CHANNELS:
            raise ValueError(f"the BabyAI task has {NUM_COND_CHANNELS} condition channels, got "
                             f"num_cond_channels={self.num_cond_channels}")
        if self.num_gen_channels != NUM_GEN_CHANNELS:
            raise ValueError(f"the BabyAI task has {NUM_GEN_CHANNELS} generated channels (path, "
                             f"goal, sub-goal), got num_gen_channels={self.num_gen_channels}")
        for name in ("path_weight", "subgoal_weight"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not isinstance(self.cell_id_base, int) or self.cell_id_base < 1:
            raise ValueError(f"cell_id_base must be an int >= 1, got {self.cell_id_base!r}")

    @property
    def height(self) -> int:
        return self.config.map_height

    @property
    def width(self) -> int:
        return self.config.map_width

    @property
    def max_steps(self) -> int:
        return self.config.max_steps

    @property
    def vocab_size(self) -> int:
        """Token ids the planning tensor and the default instructions use (cells last)."""
        return self.cell_id_base + NUM_KINDS

    def _crop(self, plan):
        return plan[:self.config.height, :self.config.width]

    def reset(self, episode: Episode) -> env.State:
        return env.reset(episode)

    def condition(self, state: env.State):
        return condition(state, self.config, self.cell_id_base)

    def tokens(self, episode: Episode):
        return episode.tokens

    def psi(self, state: env.State, plan):
        field, enter, goal, stand, _ = _route_field(state, self._crop(plan), self.path_weight,
                                                    self.subgoal_weight)
        return navigate.act(field, enter, goal, stand, known_closed_door(state.known),
                            state.pos, state.direction)

    def step(self, state: env.State, action):
        """env.step; a done state is returned unchanged."""
        stepped = env.step(state, action)
        return jax.tree.map(lambda old, new: jnp.where(state.done, old, new), state, stepped)

    def done(self, state: env.State):
        return state.done

    def position(self, state: env.State):
        return state.pos

    def at_goal_estimate(self, state: env.State, plan):
        """bool (): the agent stands beside the plan's goal estimate."""
        cell = goal_estimate(state, self._crop(plan))
        return jnp.abs(cell - state.pos).sum() == 1

    def new_information(self, old_condition, condition_now):
        """bool (): a cell looks different (newly seen, a door toggled) or an object was ruled
        out (facing an empty cell or a wall tells nothing new: neither could hold the object)."""
        ids = old_condition[..., ID_CHANNEL]
        an_object = ids - self.cell_id_base >= FIRST_OBJECT_KIND
        return (jnp.any(ids != condition_now[..., ID_CHANNEL])
                | jnp.any(an_object & (old_condition[..., RULED_OUT_CHANNEL]
                                       != condition_now[..., RULED_OUT_CHANNEL])))

    def _cost_and_refuted(self, state: env.State, plan):
        """(psi's route cost from the agent float32 (), refuted bool ()) of one search."""
        plan = self._crop(plan)
        field, _, _, _, cell = _route_field(state, plan, self.path_weight, self.subgoal_weight)
        cost = field[state.pos[0], state.pos[1]]
        return cost, (plan[cell[0], cell[1], GOAL] <= 0) | ~jnp.isfinite(cost)

    def plan_refuted(self, state: env.State, plan):
        """bool (): the plan marks no cell that may still hold the object (its goal value is
        <= 0 on every such cell), or psi finds no route to a cell beside its goal estimate."""
        return self._cost_and_refuted(state, plan)[1]

    def plan_cost(self, state: env.State, plan):
        """float32 (): psi's route cost to the plan's goal estimate (moves, toggles and the
        plan's own weights), REFUTED_PLAN_COST for a refuted plan (one route search, not two)."""
        cost, refuted = self._cost_and_refuted(state, plan)
        return jnp.where(refuted, REFUTED_PLAN_COST, cost).astype(jnp.float32)

