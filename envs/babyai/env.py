"""minigrid's dynamics of the BabyAI GoTo levels in jax.numpy: pure functions over a
:class:`State` pytree (``reset``, ``step``; tested step for step against minigrid in
tests/test_babyai_port.py).

``step`` is ``RoomGridLevel.step`` of a ``GoToInstr`` mission for the seven actions:
- left / right turn; forward moves into an empty cell or an open door, else stays;
- pickup takes a key, ball or box in front if nothing is carried (the cell becomes empty);
- drop puts the carried object into an empty cell in front;
- toggle opens or closes an unlocked door in front, opens a locked one with a key of its
  colour carried, and empties a box (a box in these levels contains nothing);
- done does nothing (``BABYAI_DONE_ACTIONS`` unset, minigrid's default).
Then ``step_count`` counts the action; truncated when ``step_count >= max_steps``; the mission
succeeds when the cell in front of the agent is one of the verifier's positions
(``GoToInstr.verify``): the cells of the objects the mission described at reset, re-read after
every drop action (``RoomGridLevel.update_objs_poss``: where those same objects now lie in the
grid; one carried or emptied out of its box is gone). Success: terminated, reward
``1 - 0.9 * step_count / max_steps``. Before the first success the positions never change (an
object cannot be picked up or emptied without the agent facing it, which succeeds first); like
minigrid, ``step`` keeps acting after the end, where they can. ``envs.babyai.task`` freezes done
states.

The State also holds the agent's map (``known``): what its observations have shown of each
cell, written from the 7 x 7 observation image only (:func:`envs.babyai.view.remember`).
"""
from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from envs.babyai import objects as O
from envs.babyai import view
from envs.babyai.episode import Episode


@struct.dataclass
class State:
    """One episode's state (leading batch axes allowed when vmapped).

    The world (minigrid's): grid uint8 (H, W, 3) the cells' encodings; pos int32 (2,) the
    agent's (row, col); direction int32 () 0..3 (east, south, west, north); carrying uint8 (3,)
    the carried object's encoding, EMPTY_CELL when nothing; step_count int32 ();
    max_steps int32 (); target bool (H, W) the verifier's positions (the cells of the objects
    the mission describes, as of reset or the last drop action); tracked bool (H, W) where
    those objects lie now; carrying_tracked bool () one of them is carried. target, tracked
    and carrying_tracked are privileged: the agent side never reads them.
    The last step's outcome: reward float32 (), terminated bool (), truncated bool ().
    The agent's side: known uint8 (H, W, 3) each cell as last observed, 0 (unseen) where never
    seen; image uint8 (7, 7, 3) the last observation (minigrid's ``obs["image"]``); ruled_out
    bool (H, W) the cells the agent has faced after an action without the episode ending (so
    they hold no object the mission names: what the episode's going on told it).
    """

    grid: jnp.ndarray
    pos: jnp.ndarray
    direction: jnp.ndarray
    carrying: jnp.ndarray
    step_count: jnp.ndarray
    max_steps: jnp.ndarray
    target: jnp.ndarray
    tracked: jnp.ndarray
    carrying_tracked: jnp.ndarray
    reward: jnp.ndarray
    terminated: jnp.ndarray
    truncated: jnp.ndarray
    known: jnp.ndarray
    image: jnp.ndarray
    ruled_out: jnp.ndarray

    @property
    def done(self):
        """bool (): the episode is over (terminated or truncated)."""
        return self.terminated | self.truncated

    @property
    def front(self):
        """int32 (2,): the cell in front of the agent."""
        return self.pos + O.DIR_DELTA[self.direction]


def _observe(state: State) -> State:
    image, visible, cells = view.observe(state.grid, state.pos, state.direction, state.carrying)
    return state.replace(image=image, known=view.remember(state.known, image, visible, cells))


def target_cells(grid, target_type, target_color):
    """bool (H, W): the cells holding an object of the described type and colour (what
    ``ObjDesc.find_matching_objs`` finds at reset; no location in these levels)."""
    return (grid[..., 0] == target_type) & (grid[..., 1] == target_color)


def reset(episode: Episode) -> State:
    """The state at t = 0: minigrid's layout, nothing carried, the first observation taken;
    the agent's own cell is known to be empty (minigrid places the agent on an empty cell)."""
    grid = jnp.asarray(episode.grid, jnp.uint8)
    h, w = grid.shape[:2]
    pos = jnp.asarray(episode.agent, jnp.int32)
    known = jnp.zeros((h, w, 3), jnp.uint8).at[pos[0], pos[1]].set(
        jnp.asarray(O.EMPTY_CELL, jnp.uint8))
    target = target_cells(grid, episode.target_type, episode.target_color)
    state = State(grid=grid, pos=pos, direction=jnp.asarray(episode.agent_dir, jnp.int32),
                  carrying=jnp.asarray(O.EMPTY_CELL, jnp.uint8), step_count=jnp.int32(0),
                  max_steps=jnp.asarray(episode.max_steps, jnp.int32), target=target,
                  tracked=target, carrying_tracked=jnp.array(False),
                  reward=jnp.float32(0), terminated=jnp.array(False),
                  truncated=jnp.array(False), known=known,
                  image=jnp.zeros((view.VIEW, view.VIEW, 3), jnp.uint8),
                  ruled_out=jnp.zeros((h, w), bool))
    return _observe(state)


def step(state: State, action) -> State:
    """One minigrid step (action int32 () in 0..6, :data:`envs.babyai.objects.ACTION_NAMES`);
    see the module docstring. Acts on done states too (as minigrid does)."""
    h, w = state.grid.shape[:2]
    front = state.front
    fr, fc = jnp.clip(front[0], 0, h - 1), jnp.clip(front[1], 0, w - 1)
    cell = state.grid[fr, fc]
    kind = cell[0]
    empty_cell = jnp.asarray(O.EMPTY_CELL, jnp.uint8)
    carrying_nothing = state.carrying[0] == O.EMPTY

    direction = jnp.where(action == O.LEFT, (state.direction + 3) % 4,
                          jnp.where(action == O.RIGHT, (state.direction + 1) % 4,
                                    state.direction)).astype(jnp.int32)
    moves = (action == O.FORWARD) & O.enterable(cell)
    pos = jnp.where(moves, front, state.pos).astype(jnp.int32)

    picks = (action == O.PICKUP) & O.pickable(cell) & carrying_nothing
    drops = (action == O.DROP) & (kind == O.EMPTY) & ~carrying_nothing
    toggles = action == O.TOGGLE
    is_door = kind == O.DOOR
    unlocks = (cell[2] == O.LOCKED) & (state.carrying[0] == O.KEY) & (state.carrying[1] == cell[1])
    door_state = jnp.where(cell[2] == O.LOCKED, jnp.where(unlocks, O.OPEN, O.LOCKED),
                           jnp.where(cell[2] == O.OPEN, O.CLOSED, O.OPEN)).astype(jnp.uint8)
    toggled = jnp.where(is_door, cell.at[2].set(door_state),
                        jnp.where(kind == O.BOX, empty_cell, cell))
    new_cell = jnp.where(picks, empty_cell,
                         jnp.where(drops, state.carrying, jnp.where(toggles, toggled, cell)))
    grid = state.grid.at[fr, fc].set(new_cell)
    carrying = jnp.where(picks, cell, jnp.where(drops, empty_cell, state.carrying))
    here = state.tracked[fr, fc]
    tracked = state.tracked.at[fr, fc].set(
        jnp.where(picks | (toggles & (kind == O.BOX)), False,
                  jnp.where(drops, state.carrying_tracked, here)))
    carrying_tracked = jnp.where(picks, here, jnp.where(drops, False, state.carrying_tracked))
    target = jnp.where(action == O.DROP, tracked, state.target)

    step_count = state.step_count + 1
    new_front = pos + O.DIR_DELTA[direction]
    success = target[jnp.clip(new_front[0], 0, h - 1), jnp.clip(new_front[1], 0, w - 1)]
    reward = jnp.where(success, 1.0 - 0.9 * (step_count.astype(jnp.float32)
                                             / state.max_steps.astype(jnp.float32)), 0.0)
    faced = (new_front[0] >= 0) & (new_front[0] < h) & (new_front[1] >= 0) & (new_front[1] < w)
    ruled_out = state.ruled_out.at[jnp.where(faced & ~success, new_front[0], h),
                                   new_front[1]].set(True, mode="drop")
    state = state.replace(grid=grid, pos=pos, direction=direction, carrying=carrying,
                          target=target, tracked=tracked, carrying_tracked=carrying_tracked,
                          step_count=step_count, reward=reward.astype(jnp.float32),
                          terminated=success, truncated=step_count >= state.max_steps,
                          ruled_out=ruled_out)
    return _observe(state)
