"""Algorithm 1 of the paper over batches of episodes: the planner step of
:class:`diffplan.planner.Planner`, ``task.psi``, ``task.step``, in a loop.

``rollout(task, planner, keys, episodes)`` runs a batch of episodes to the end in one
``lax.while_loop`` over moves (at most ``task.max_steps``; it stops when every episode is
done). :class:`StreamRollout` runs the same moves on a pool of episode slots that are refilled
as episodes end, so an evaluation's work is the sum of its episodes' lengths rather than
(batches) x (longest episode of a batch). Both are built on one move, :func:`move`
(plan -> psi -> step), and give every episode exactly the same result: each episode plans
with its own key (``Planner.init(keys[i], ...)``), so nothing depends on what else is in the
batch or on how an evaluation is chunked.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
from flax import struct

from diffplan.planner import Planner, PlannerState

__all__ = ["Rollout", "default_chunk", "move", "rollout", "rollout_stream", "StreamRollout",
           "StreamCarry"]


@struct.dataclass
class Rollout:
    """What happened in a batch of N episodes.

    final_state: the task's state pytree (N, ...) at the end.
    positions: int32 (N, T + 1, 2) the agent's cell after each move (held after the end).
    steps: int32 (N,) moves taken.  done: bool (N,) episode over.
    denoiser_calls: int32 (N,) denoiser evaluations spent on the episode.
    num_plans: int32 (N,) plans made.
    first_plan: float32 (N, H, W, G) the plan followed at the first move (the paper's plan
      metrics).
    plans: float32 (N, T, H, W, G) the plan followed at each move, if the planner's
      config.record_plans (else None).
    fallback_moves: int32 (N,) moves whose plan gave psi no move even after a second plan
      (a task with ``follows_plan``; None otherwise).
    """

    final_state: Any
    positions: jax.Array
    steps: jax.Array
    done: jax.Array
    denoiser_calls: jax.Array
    num_plans: jax.Array
    first_plan: jax.Array
    plans: Any = None
    fallback_moves: Any = None


def _where_rows(mask, new, old):
    """Per-row select between two pytrees with leading axis B (mask bool (B,))."""
    return jax.tree.map(lambda n, o: jnp.where(mask.reshape((-1,) + (1,) * (n.ndim - 1)), n, o),
                        new, old)


def move(task, planner: Planner, states, planner_states: PlannerState, active,
         chunk: Optional[int] = None, fresh_chunk: Optional[int] = None):
    """One move of Algorithm 1 for a batch of B episodes: plan (where the planner's mode asks
    for it; in k_shot mode when ``task.at_goal_estimate`` of the current plan; with the
    "on_change" trigger when ``task.new_information`` or ``task.at_goal_estimate``; with
    "on_refuted" when ``task.plan_refuted`` or ``task.at_goal_estimate``), act with
    ``task.psi``, step the world. Inactive episodes (active bool (B,) False) are left as they
    are. chunk / fresh_chunk: see ``Planner.plan_batch``.

    A task whose psi only follows the plan's marks (``task.follows_plan`` True) also says
    where a plan gives it no move (``task.unfollowable(state, plan) -> bool ()``): there the
    planner plans again once (``Planner.retry_batch``; not in one_shot / k_shot), psi acts on
    the second plan, and a move that is still unfollowable (psi's own fallback acts) is
    counted in ``PlannerState.fallbacks``.

    Returns (states, planner_states, plans float32 (B, H, W, G) followed at this move)."""
    config = planner.config
    conditions = jax.vmap(task.condition)(states)
    replan = None
    if config.mode == "k_shot":
        replan = jax.vmap(task.at_goal_estimate)(states, planner_states.plan)
    elif config.replan != "always" and config.mode != "one_shot":
        if config.replan == "on_change":
            stale = jax.vmap(task.new_information)(planner_states.condition, conditions)
        else:  # on_refuted
            if not callable(getattr(task, "plan_refuted", None)):
                raise ValueError(f"replan='on_refuted' needs a task that says when a plan is "
                                 f"refuted (task.plan_refuted); {type(task).__name__} has none")
            stale = jax.vmap(task.plan_refuted)(states, planner_states.plan)
        replan = stale | jax.vmap(task.at_goal_estimate)(states, planner_states.plan)
    rank = _rank(task, config, states)
    plans, planner_states = planner.plan_batch(planner_states, conditions, active, replan,
                                               chunk=chunk, fresh_chunk=fresh_chunk, rank=rank)
    actions = jax.vmap(task.psi)(states, plans)
    if getattr(task, "follows_plan", False):
        stuck = jax.vmap(task.unfollowable)(states, plans) & active
        plans, planner_states = planner.retry_batch(planner_states, conditions, stuck, chunk,
                                                    rank=rank)
        actions = jnp.where(stuck, jax.vmap(task.psi)(states, plans), actions)
        fallback = stuck & jax.vmap(task.unfollowable)(states, plans)
        planner_states = planner_states.replace(
            fallbacks=planner_states.fallbacks + fallback.astype(jnp.int32))
    states = _where_rows(active, jax.vmap(task.step)(states, actions), states)
    return states, planner_states, plans


def _rank(task, config, states):
    """Planner.plan_batch's ``rank`` for a planner that draws several plans per re-plan
    (``config.samples`` > 1): row i's plans are scored by ``task.plan_cost(states[i], plan)``
    and the cheapest is kept. None when one plan is drawn."""
    if config.samples == 1:
        return None
    if not callable(getattr(task, "plan_cost", None)):
        raise ValueError(f"samples={config.samples} needs a task that scores a plan "
                         f"(task.plan_cost); {type(task).__name__} has none")
    cost = jax.vmap(task.plan_cost, in_axes=(None, 0))
    return lambda i, plans: cost(jax.tree.map(lambda x: x[i], states), plans)


def _result(task, final_states, positions, planner_states: PlannerState, first_plan,
            plans=None) -> Rollout:
    """The Rollout of finished episodes; positions after an episode's end repeat its final
    cell."""
    steps = planner_states.move
    final = jax.vmap(task.position)(final_states)
    idx = jnp.arange(positions.shape[1])[None, :]
    positions = jnp.where((idx > steps[:, None])[..., None], final[:, None, :], positions)
    return Rollout(final_state=final_states, positions=positions, steps=steps,
                   done=jax.vmap(task.done)(final_states), denoiser_calls=planner_states.calls,
                   num_plans=planner_states.num_plans, first_plan=first_plan, plans=plans,
                   fallback_moves=(getattr(planner_states, "fallbacks", None)
                                   if getattr(task, "follows_plan", False) else None))


def _start_positions(task, states, n: int):
    start = jax.vmap(task.position)(states)
    return jnp.broadcast_to(start[:, None, :], (n, task.max_steps + 1, 2)).astype(jnp.int32)


def default_chunk(batch: int) -> int:
    """The denoiser sub-batch of :func:`rollout` for B episodes: max(32, B // 8), at most B
    (and at least MIN_SUB_BATCH, see Planner.plan_batch). Plans are computed for the episodes
    that need one, a sub-batch at a time, so small sub-batches stop finished episodes and
    episodes that need no plan from costing forwards; on this CPU the UNet's calls/s is flat
    from 32 to 256 rows (experiments/bench_planner's "bound" rows), so 32 costs nothing per
    call. Per-episode results do not depend on it."""
    return min(batch, max(32, batch // 8))


def rollout(task, planner: Planner, keys, episodes, chunk: Optional[int] = None) -> Rollout:
    """Runs a batch of episodes with the planner; pure and jit-able.

    Args:
      task: a diffplan.task.Task (static: close over it or pass it as a static argument).
      planner: a diffplan.Planner.
      keys: (B,) PRNG keys, one per episode (each episode's planner key).
      episodes: the task's episode pytree with a leading batch axis B.
      chunk: episodes per denoiser sub-batch (default: default_chunk(B)).
    Returns: a Rollout.
    """
    config = planner.config
    states = jax.vmap(task.reset)(episodes)
    planner_states = jax.vmap(planner.init)(keys, jax.vmap(task.tokens)(episodes))
    batch = keys.shape[0]
    if chunk is None:
        chunk = default_chunk(batch)
    positions = _start_positions(task, states, batch)
    plan_shape = (batch,) + tuple(planner.plan_shape)
    first_plan = jnp.zeros(plan_shape, jnp.float32)
    plans = (jnp.zeros((batch, task.max_steps) + plan_shape[1:], jnp.float32)
             if config.record_plans else None)

    def body(carry):
        t, states, planner_states, positions, first_plan, plans = carry
        active = ~jax.vmap(task.done)(states)
        states, planner_states, plan = move(task, planner, states, planner_states, active,
                                            chunk)
        first_plan = jnp.where(t == 0, plan, first_plan)
        if plans is not None:
            plans = plans.at[:, t].set(plan)
        positions = positions.at[:, t + 1].set(jax.vmap(task.position)(states))
        return t + 1, states, planner_states, positions, first_plan, plans

    def cond(carry):
        return (carry[0] < task.max_steps) & ~jnp.all(jax.vmap(task.done)(carry[1]))

    carry = (jnp.int32(0), states, planner_states, positions, first_plan, plans)
    _, states, planner_states, positions, first_plan, plans = jax.lax.while_loop(
        cond, body, carry)
    return _result(task, states, positions, planner_states, first_plan, plans)


def rollout_stream(task, planner: Planner, keys, episodes, num_slots: int,
                   num_fresh: Optional[int] = None, plan_chunks: int = 4,
                   on_move: Optional[Callable] = None, token=None) -> Rollout:
    """:func:`rollout` on a pool of ``num_slots`` episode slots refilled as episodes end (see
    :class:`StreamRollout`); the same per-episode results. keys (N,), episodes (N, ...) for
    any N. on_move / token: see StreamRollout (progress reports)."""
    stream = StreamRollout(task, planner.config, num_slots, num_fresh, plan_chunks, on_move)
    carry = stream.advance(planner, keys, episodes, stream.start(planner, keys, episodes),
                           token=token)
    return stream.result(carry)


class StreamCarry(struct.PyTreeNode):
    """The state of a slot pool (see :class:`StreamRollout`); S slots, N episodes.

    next_ep: int32 () next episode to load.  slot_ep: int32 (S,) episode in each slot (N: empty).
    states: task states (S, ...).  planner_states: PlannerState (S,) of each slot's episode.
    final_states: task states (N, ...) of retired episodes.  positions: int32 (N, T + 1, 2).
    retired: PlannerState (N,) of retired episodes (moves, calls, plans).
    first_plan: float32 (N, H, W, G).
    """

    next_ep: jax.Array
    slot_ep: jax.Array
    states: Any
    planner_states: PlannerState
    final_states: Any
    positions: jax.Array
    retired: PlannerState
    first_plan: jax.Array

    @property
    def finished(self) -> jax.Array:
        """bool (): every episode has been run and retired."""
        n = self.positions.shape[0]
        return (self.next_ep >= n) & ~jnp.any(self.slot_ep < n)

    @property
    def episodes_retired(self) -> jax.Array:
        """int32 (): episodes finished so far."""
        n = self.positions.shape[0]
        return self.next_ep - jnp.sum(self.slot_ep < n).astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class StreamRollout:
    """:func:`rollout` on a pool of ``num_slots`` slots, refilled as episodes end, in pure,
    jit-able pieces (so a caller can run the pool a few moves at a time, e.g. to update a
    progress bar, without paying a new pool's tail):

        stream = StreamRollout(task, planner.config, num_slots)
        carry = stream.start(planner, keys, episodes)
        while not carry.finished:
            carry = stream.advance(planner, keys, episodes, carry, max_moves=8)
        result = stream.result(carry)

    gives exactly ``rollout(task, planner, keys, episodes)`` for the re-planning modes
    (on_the_fly, warm_start). Each move plans the active slots in ``plan_chunks`` sub-batches
    of ceil(num_slots / plan_chunks) (fewer when fewer slots are active). In warm_start at
    most ``num_fresh`` new episodes (default num_slots // 8) start per move, and their first
    (full) plans form one sub-batch of that size; further free slots wait for the next move.
    planner, keys and episodes must be the same in every call.

    on_move: optional host function ``on_move(token, episodes_retired)`` called (through
    ``jax.debug.callback``, unordered) after every move of the pool, e.g. to move a progress
    bar while one jitted call runs the whole pool; ``token`` is the int32 scalar given to
    ``advance`` (which bar). It does not change the results.
    """

    task: Any
    config: Any
    num_slots: int
    num_fresh: Optional[int] = None
    plan_chunks: int = 4
    on_move: Optional[Callable] = None

    def __post_init__(self):
        if self.config.mode not in ("on_the_fly", "warm_start"):
            raise ValueError("StreamRollout supports on_the_fly and warm_start, not "
                             f"{self.config.mode}")
        if self.config.record_plans:
            raise ValueError("record_plans is not supported by StreamRollout; use rollout")
        if self.num_slots < 1 or self.fresh_cap < 1 or self.plan_chunks < 1:
            raise ValueError(f"num_slots, num_fresh and plan_chunks must be >= 1, got "
                             f"{self.num_slots}, {self.num_fresh}, {self.plan_chunks}")

    @property
    def fresh_cap(self) -> int:
        """New episodes started per move."""
        if self.config.mode != "warm_start":
            return self.num_slots
        cap = max(1, self.num_slots // 8) if self.num_fresh is None else int(self.num_fresh)
        return min(cap, self.num_slots)

    def _check(self, planner: Planner):
        if planner.config != self.config:
            raise ValueError("the planner's config differs from the StreamRollout's")

    def start(self, planner: Planner, keys, episodes) -> StreamCarry:
        """An empty pool over the N episodes (keys (N,), episodes (N, ...))."""
        self._check(planner)
        task, slots, n = self.task, int(self.num_slots), keys.shape[0]
        final_states = jax.vmap(task.reset)(episodes)
        tokens = jax.vmap(task.tokens)(episodes)
        retired = jax.vmap(planner.init)(keys, tokens)
        placeholder = jnp.zeros((slots,), jnp.int32)  # empty slots hold episode 0, unused
        return StreamCarry(
            next_ep=jnp.int32(0), slot_ep=jnp.full((slots,), n, jnp.int32),
            states=jax.tree.map(lambda x: x[placeholder], final_states),
            planner_states=jax.tree.map(lambda x: x[placeholder], retired),
            final_states=final_states, positions=_start_positions(task, final_states, n),
            retired=retired,
            first_plan=jnp.zeros((n,) + tuple(planner.plan_shape), jnp.float32))

    def advance(self, planner: Planner, keys, episodes, carry: StreamCarry,
                max_moves: Optional[int] = None, token=None) -> StreamCarry:
        """Runs the pool for at most max_moves moves (None: until every episode is done).
        token: int32 () passed to on_move."""
        self._check(planner)
        task, slots, n = self.task, int(self.num_slots), keys.shape[0]
        chunk = max(1, -(-slots // self.plan_chunks))
        fresh_cap = self.fresh_cap
        tokens_all = jax.vmap(task.tokens)(episodes)
        v_done = jax.vmap(task.done)

        def body(c: StreamCarry) -> StreamCarry:
            slot_ep = c.slot_ep
            # 1. Retire finished episodes.
            finished = (slot_ep < n) & v_done(c.states)
            write = jnp.where(finished, slot_ep, n)
            final_states = _put(c.final_states, write, c.states)
            retired = _put(c.retired, write, c.planner_states)
            slot_ep = jnp.where(finished, n, slot_ep)
            # 2. Refill free slots, in episode order, at most fresh_cap of them.
            free = slot_ep >= n
            rank = jnp.cumsum(free) - 1
            new_ep = c.next_ep + rank
            load = free & (rank < fresh_cap) & (new_ep < n)
            slot_ep = jnp.where(load, new_ep, slot_ep)
            next_ep = c.next_ep + jnp.sum(load).astype(jnp.int32)
            src = jnp.clip(new_ep, 0, n - 1)
            states = _where_rows(load, jax.vmap(task.reset)(_take(episodes, src)), c.states)
            planner_states = _where_rows(
                load, jax.vmap(planner.init)(keys[src], tokens_all[src]), c.planner_states)
            # 3. Plan, act, record.
            active = (slot_ep < n) & ~v_done(states)
            states, planner_states, plans = move(task, planner, states, planner_states,
                                                 active, chunk, fresh_chunk=fresh_cap)
            first_plan = c.first_plan.at[jnp.where(load, slot_ep, n)].set(plans, mode="drop")
            row = jnp.where(active, slot_ep, n)
            positions = c.positions.at[row, planner_states.move].set(
                jax.vmap(task.position)(states), mode="drop")
            out = StreamCarry(next_ep=next_ep, slot_ep=slot_ep, states=states,
                              planner_states=planner_states, final_states=final_states,
                              positions=positions, retired=retired, first_plan=first_plan)
            if self.on_move is not None:
                jax.debug.callback(self.on_move, jnp.int32(0) if token is None else token,
                                   out.episodes_retired)
            return out

        if max_moves is None:
            return jax.lax.while_loop(lambda c: ~c.finished, body, carry)
        _, carry = jax.lax.while_loop(lambda ic: (ic[0] < max_moves) & ~ic[1].finished,
                                      lambda ic: (ic[0] + 1, body(ic[1])),
                                      (jnp.int32(0), carry))
        return carry

    def result(self, carry: StreamCarry) -> Rollout:
        """The Rollout over the N episodes of a finished pool, in their order."""
        return _result(self.task, carry.final_states, carry.positions, carry.retired,
                       carry.first_plan)


def _take(tree, idx):
    return jax.tree.map(lambda x: x[idx], tree)


def _put(tree, idx, values):
    """tree[idx] = values for each leaf; out-of-range idx entries are dropped."""
    return jax.tree.map(lambda x, v: x.at[idx].set(v, mode="drop"), tree, values)
