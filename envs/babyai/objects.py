"""minigrid's cell encoding and directions, as constants (the format, not minigrid's code).

A cell is uint8 (3,) = (type, colour, state), minigrid's ``WorldObj.encode``: types
:data:`UNSEEN` .. :data:`AGENT`, colours 0..5 (red, green, blue, purple, yellow, grey), a door's
state :data:`OPEN`, :data:`CLOSED` or :data:`LOCKED` (0 for every other type). An empty cell is
(EMPTY, 0, 0).
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

UNSEEN, EMPTY, WALL, FLOOR, DOOR, KEY, BALL, BOX, GOAL, LAVA, AGENT = range(11)
TYPE_NAMES = ("unseen", "empty", "wall", "floor", "door", "key", "ball", "box", "goal", "lava",
              "agent")
NUM_TYPES = len(TYPE_NAMES)
NUM_COLORS = 6
GREY = 5
OPEN, CLOSED, LOCKED = 0, 1, 2
LEVEL_TYPES = (EMPTY, WALL, DOOR, KEY, BALL, BOX)
"""The types the GoTo levels' grids hold (the port handles these; layouts with others are
refused)."""

EMPTY_CELL = (EMPTY, 0, 0)
WALL_CELL = (WALL, GREY, 0)

LEFT, RIGHT, FORWARD, PICKUP, DROP, TOGGLE, DONE = range(7)
ACTION_NAMES = ("left", "right", "forward", "pickup", "drop", "toggle", "done")
NUM_ACTIONS = 7

DIR_DELTA = jnp.asarray(np.array([[0, 1], [1, 0], [0, -1], [-1, 0]], np.int32))
"""(4, 2) (d_row, d_col) of directions 0..3 = east, south, west, north (minigrid's
``DIR_TO_VEC`` as (dy, dx))."""


def opaque(cells):
    """bool (...): cells (..., 3) the agent cannot see past: walls and closed or locked doors."""
    kind = cells[..., 0]
    return (kind == WALL) | ((kind == DOOR) & (cells[..., 2] != OPEN))


def enterable(cells):
    """bool (...): cells (..., 3) the agent can move into: empty cells and open doors."""
    kind = cells[..., 0]
    return (kind == EMPTY) | ((kind == DOOR) & (cells[..., 2] == OPEN))


def pickable(cells):
    """bool (...): keys, balls and boxes."""
    kind = cells[..., 0]
    return (kind == KEY) | (kind == BALL) | (kind == BOX)
