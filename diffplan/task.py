"""The protocol through which an environment plugs into the planner.

The planner (diffplan/planner.py) is environment-agnostic: it only needs a :class:`Task`, a set
of pure per-episode functions. Both worlds (the grid world and the Kuka world) implement it.
"""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import jax


@runtime_checkable
class Task(Protocol):
    """Per-episode pure functions (the planner vmaps them over a batch).

    Attributes:
      height, width: the planning map's size.
      num_cond_channels: C, the number of condition channels of the planning tensor.
      num_gen_channels: G, the generated channels (path, goal estimate).
      max_steps: episode length in actions.
    """

    height: int
    width: int
    num_cond_channels: int
    num_gen_channels: int
    max_steps: int

    def reset(self, episode: Any) -> Any:
        """Episode -> state at t=0."""

    def condition(self, state: Any) -> jax.Array:
        """State -> float32 (H, W, C) condition channels (what the agent has observed)."""

    def tokens(self, episode: Any) -> jax.Array:
        """Episode -> int32 (L,) instruction token ids."""

    def psi(self, state: Any, plan: jax.Array) -> jax.Array:
        """Inverse dynamics: state and plan float32 (H, W, G) -> the next action."""

    def step(self, state: Any, action: jax.Array) -> Any:
        """One action in the world; done states are returned unchanged."""

    def done(self, state: Any) -> jax.Array:
        """bool (): the episode is over."""

    def position(self, state: Any) -> jax.Array:
        """int32 (2,) the agent's cell on the planning map (recorded into trajectories)."""

    def at_goal_estimate(self, state: Any, plan: jax.Array) -> jax.Array:
        """bool (): the agent has reached the plan's goal estimate (k-shot re-plan trigger)."""

    def new_information(self, old_condition: jax.Array, condition: jax.Array) -> jax.Array:
        """bool (): ``condition`` (H, W, C) shows something ``old_condition`` (the one the
        current plan was made from) did not (the "on_change" re-planning trigger)."""

    # Optional: ``plan_refuted(state, plan) -> bool ()``: what the plan assumed is contradicted
    # by what the agent now knows (the "on_refuted" re-planning trigger; a task without it
    # refuses that trigger).
    # Optional: a task whose psi only follows the plan's marks sets ``follows_plan = True`` and
    # defines ``unfollowable(state, plan) -> bool ()`` (the plan gives psi no move there); the
    # rollout then plans again once and counts the moves psi still had to make on its own
    # (``diffplan.rollouts.move``).
