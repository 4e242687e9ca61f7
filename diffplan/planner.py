"""On-the-fly planning (Algorithm 1 of the paper) as one pure, jit-able JAX function.

``rollout(task, apply_fn, params, schedule, keys, episodes, config)`` runs a batch of episodes to
the end: at each move the planner may (re-)plan by in-painting the path and goal channels given
the current condition channels and the instruction, ``task.psi`` turns the plan into the next
action, the world steps and the agent observes more. The loop is a ``lax.while_loop`` over moves
(at most ``task.max_steps``) that stops as soon as every episode is done; finished episodes are
frozen by the task's ``step``. Planning is skipped (``lax.cond``) on moves where no episode needs a
plan, so one-shot and k-shot modes do not pay for plans they do not make.

Modes (``PlannerConfig.mode``):
  one_shot    plan once at t=0 and follow that plan with psi to the end.
  k_shot      plan at t=0 and again each time the agent reaches the current goal estimate, at
              most k plans in all.
  on_the_fly  re-plan from pure noise before every move (the paper's Algorithm 1).
  warm_start  on-the-fly on its own ``warm_num_steps``-step schedule (default: ``num_steps``):
              an episode's first plan denoises that schedule from pure noise
              (``warm_num_steps`` calls); every later re-plan resumes from the previous plan
              re-noised to its step ``warm_start_step``, so it costs
              ``warm_num_steps - warm_start_step`` denoiser calls instead of ``num_steps``.

Every episode uses its own PRNG key: an episode's result does not depend on what else is in the
batch (or on how an evaluation is chunked).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from diffplan.sampler import denoiser_calls, sample
from diffplan.schedule import Schedule

MODES = ("one_shot", "k_shot", "on_the_fly", "warm_start")


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """How to plan (hashable; a static argument of the jitted rollout).

    mode: one of MODES. num_steps: denoising steps of a plan from noise (warm_start mode: see
    warm_num_steps). eta: 0 = DDIM, 1 = DDPM-like.
    k: plans per episode in k_shot mode. warm_num_steps: the sampling schedule of warm_start
    mode (None = num_steps): its first plan runs all of it from noise, its re-plans skip the
    first warm_start_step steps. E.g. num_steps=10, warm_num_steps=3, warm_start_step=1: the
    other modes plan in 10 steps; warm start plans first in 3 steps, then each re-plan
    re-noises the previous plan to the second of 3 trailing timesteps (t ~ 66 of 100) and
    denoises it in 2 calls.
    clip_x0: clip the predicted x0 to [-1, 1] during sampling. record_plans: also return the
    plan used at every move (memory B x T x H x W x G: for figures, small batches only).
    fresh_noise: each re-plan draws new noise (key fold_in(episode key, move)); False reuses the
    episode's noise (key fold_in(episode key, 0)) at every re-plan, so that with eta = 0 plans
    change only where the observation changed (common random numbers: the goal estimate does
    not jump between equally plausible guesses from one move to the next).
    """

    mode: str = "on_the_fly"
    num_steps: int = 10
    eta: float = 0.0
    k: int = 2
    warm_start_step: int = 8
    warm_num_steps: int | None = None
    clip_x0: bool = True
    record_plans: bool = False
    fresh_noise: bool = True

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"unknown planner mode {self.mode!r}; expected one of {MODES}")
        if self.num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {self.num_steps}")
        if self.k < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        if self.warm_num_steps is not None and self.warm_num_steps < 1:
            raise ValueError(f"warm_num_steps must be >= 1, got {self.warm_num_steps}")
        if not 0 <= self.warm_start_step < self.warm_steps:
            raise ValueError(
                f"warm_start_step must be in 0..{self.warm_steps - 1} (the warm schedule has "
                f"{self.warm_steps} steps), got {self.warm_start_step}")
        if self.eta < 0:
            raise ValueError(f"eta must be >= 0, got {self.eta}")

    @property
    def full_plan_steps(self) -> int:
        """Steps of a plan from pure noise (an episode's first plan; every plan but warm
        re-plans)."""
        return self.warm_steps if self.mode == "warm_start" else self.num_steps

    @property
    def full_plan_calls(self) -> int:
        return denoiser_calls(self.full_plan_steps, None)

    @property
    def warm_plan_calls(self) -> int:
        return denoiser_calls(self.warm_steps, self.warm_start_step)

    @property
    def warm_steps(self) -> int:
        """Steps of the schedule warm re-plans resume in."""
        return self.num_steps if self.warm_num_steps is None else self.warm_num_steps


@struct.dataclass
class Rollout:
    """What happened in a batch of episodes.

    final_state: the task's state pytree (B, ...) at the end.
    positions: int32 (B, T + 1, 2) the agent's cell after each move (held after the end).
    steps: int32 (B,) moves taken.  done: bool (B,) episode over.
    denoiser_calls: int32 (B,) denoiser evaluations spent on the episode.
    num_plans: int32 (B,) plans made.
    first_plan: float32 (B, H, W, G) the plan made at t=0 (for the paper's plan metrics).
    plans: float32 (B, T, H, W, G) the plan followed at each move, if record_plans (else None).
    """

    final_state: Any
    positions: jax.Array
    steps: jax.Array
    done: jax.Array
    denoiser_calls: jax.Array
    num_plans: jax.Array
    first_plan: jax.Array
    plans: Any = None


def make_planner(task, apply_fn: Callable, params, schedule: Schedule, config: PlannerConfig):
    """Returns plan(keys (B,), states, tokens (B, L), x_prev (B,H,W,G) or None, warm: bool)
    -> plans float32 (B, H, W, G): in-paints path and goal given each state's condition."""
    c = task.num_cond_channels
    g = task.num_gen_channels
    known_mask = (jnp.arange(c + g) < c)

    def plan_one(key, condition, tokens, x_prev, warm):
        def denoise(x_t, t):
            eps = apply_fn(params, x_t, t, tokens[None])
            return jnp.concatenate([jnp.zeros(x_t.shape[:-1] + (c,), eps.dtype), eps], axis=-1)

        x_known = jnp.concatenate(
            [condition, jnp.zeros(condition.shape[:-1] + (g,), condition.dtype)], axis=-1)[None]
        kwargs = dict(num_steps=config.full_plan_steps)
        if warm:
            kwargs = dict(x_init=jnp.concatenate([condition, x_prev], axis=-1)[None],
                          start_step=config.warm_start_step, num_steps=config.warm_steps)
        x0 = sample(denoise, schedule, key, x_known, known_mask, eta=config.eta,
                    clip_x0=config.clip_x0, **kwargs)
        return x0[0, ..., c:]

    def plan(keys, states, tokens, x_prev=None, warm=False):
        conditions = jax.vmap(task.condition)(states)
        if x_prev is None:
            x_prev = jnp.zeros(conditions.shape[:-1] + (g,), conditions.dtype)
        return jax.vmap(lambda k, cond, tok, xp: plan_one(k, cond, tok, xp, warm))(
            keys, conditions, tokens, x_prev)

    return plan


def rollout(task, apply_fn: Callable, params, schedule: Schedule, keys, episodes,
            config: PlannerConfig) -> Rollout:
    """Runs a batch of episodes with the diffusion planner; pure and jit-able.

    Args:
      task: a diffplan.task.Task (static).
      apply_fn: (params, x_t (B,H,W,C+G), t (B,), tokens (B,L)) -> eps (B,H,W,G).
      params: the denoiser's parameters.
      schedule: the diffusion schedule.
      keys: (B,) PRNG keys, one per episode.
      episodes: the task's episode pytree with a leading batch axis B.
      config: PlannerConfig (static).
    Returns: a Rollout.
    """
    plan_fn = make_planner(task, apply_fn, params, schedule, config)
    v_done = jax.vmap(task.done)
    states = jax.vmap(task.reset)(episodes)
    tokens = jax.vmap(task.tokens)(episodes)
    batch = tokens.shape[0]
    t_max = task.max_steps

    def keys_at(t):
        t = t if config.fresh_noise else 0
        return jax.vmap(lambda k: jax.random.fold_in(k, t))(keys)

    plan = first_plan = plan_fn(keys_at(0), states, tokens)
    done = v_done(states)
    calls = jnp.where(done, 0, config.full_plan_calls).astype(jnp.int32)
    num_plans = (~done).astype(jnp.int32)
    start = jax.vmap(task.position)(states)
    positions = jnp.broadcast_to(start[:, None, :], (batch, t_max + 1, 2)).astype(jnp.int32)
    plans = (jnp.zeros((batch, t_max) + plan.shape[1:], plan.dtype)
             if config.record_plans else None)

    warm = config.mode == "warm_start"
    per_replan_calls = config.warm_plan_calls if warm else config.full_plan_calls
    plan_chunk = max(1, batch // 8) if config.mode == "k_shot" else batch

    def needs_plan(t, states, plan, num_plans):
        active = ~v_done(states)
        if config.mode in ("on_the_fly", "warm_start"):
            return active & (t > 0)
        if config.mode == "k_shot":
            reached = jax.vmap(task.at_goal_estimate)(states, plan)
            return active & (t > 0) & reached & (num_plans < config.k)
        return jnp.zeros_like(active)  # one_shot

    def body(carry):
        t, states, plan, positions, calls, num_plans, steps, plans = carry
        need = needs_plan(t, states, plan, num_plans)
        # k-shot: few episodes re-plan at once, so plan only those, in small sub-batches.
        plan = _plan_subset(plan_fn, need, keys_at(t), states, tokens, plan,
                            plan_chunk, warm)
        calls = calls + need * per_replan_calls
        num_plans = num_plans + need
        if plans is not None:
            plans = plans.at[:, t].set(plan)
        actions = jax.vmap(task.psi)(states, plan)
        steps = steps + ~v_done(states)
        states = jax.vmap(task.step)(states, actions)
        positions = positions.at[:, t + 1].set(jax.vmap(task.position)(states))
        return t + 1, states, plan, positions, calls, num_plans, steps, plans

    def cond(carry):
        t, states = carry[0], carry[1]
        return (t < t_max) & ~jnp.all(v_done(states))

    steps = jnp.zeros((batch,), jnp.int32)
    carry = (jnp.int32(0), states, plan, positions, calls, num_plans, steps, plans)
    _, states, _, positions, calls, num_plans, steps, plans = jax.lax.while_loop(cond, body, carry)
    # Positions after an episode ended repeat its final cell.
    final = jax.vmap(task.position)(states)
    idx = jnp.arange(t_max + 1)[None, :]
    positions = jnp.where((idx > steps[:, None])[..., None], final[:, None, :], positions)
    return Rollout(final_state=states, positions=positions, steps=steps.astype(jnp.int32),
                   done=v_done(states), denoiser_calls=calls.astype(jnp.int32),
                   num_plans=num_plans.astype(jnp.int32), first_plan=first_plan, plans=plans)


def _plan_subset(plan_fn, need, keys, states, tokens, plan, chunk: int, warm: bool = False):
    """plan with the entries where need (bool (B,)) replaced by fresh plans, computed
    ``chunk`` episodes at a time (a while_loop over the needy ones only), so the cost follows
    the number of episodes that re-plan rather than the batch size. Each episode uses its own
    key and state, exactly as a full-batch plan_fn would. warm: re-plan from the current plan
    (warm start)."""
    b = need.shape[0]
    count = jnp.sum(need).astype(jnp.int32)
    order = jnp.argsort(~need, stable=True).astype(jnp.int32)  # needy episodes first
    order = jnp.concatenate([order, jnp.full((chunk,), b, jnp.int32)])

    def body(carry):
        i, plan = carry
        idx = jax.lax.dynamic_slice(order, (i,), (chunk,))
        valid = (i + jnp.arange(chunk)) < count
        safe = jnp.where(valid, idx, 0)
        sub = plan_fn(keys[safe], _take(states, safe), tokens[safe],
                      plan[safe] if warm else None, warm)
        return i + chunk, plan.at[jnp.where(valid, idx, b)].set(sub, mode="drop")

    _, plan = jax.lax.while_loop(lambda c: c[0] < count, body, (jnp.int32(0), plan))
    return plan


def _take(tree, idx):
    return jax.tree.map(lambda x: x[idx], tree)


def _put(tree, idx, values):
    """tree[idx] = values for each leaf; out-of-range idx entries are dropped."""
    return jax.tree.map(lambda x, v: x.at[idx].set(v, mode="drop"), tree, values)


def rollout_stream(task, apply_fn: Callable, params, schedule: Schedule, keys, episodes,
                   config: PlannerConfig, num_slots: int, num_fresh: int | None = None,
                   plan_chunks: int = 4) -> Rollout:
    """Like :func:`rollout` for the re-planning modes, but with a pool of ``num_slots`` episode
    slots refilled as episodes end, so the work is the sum of the episodes' lengths instead of
    (number of batches) x (longest episode of a batch): a single 100-move failure no longer
    makes a whole batch plan for 100 moves.

    Each episode sees exactly what it would see in :func:`rollout` (its own key, re-planning
    before each of its moves with key fold_in(key, move)), so the results are the same.
    Modes "on_the_fly" and "warm_start" only. In "warm_start", the first (full) plans of newly
    started episodes are made for at most ``num_fresh`` slots per move (default num_slots // 8);
    further free slots wait for the next move. Re-plans are computed for the active slots only,
    in ``plan_chunks`` sub-batches of ceil(num_slots / plan_chunks) (fewer when fewer slots are
    active).

    Args: as :func:`rollout`, with keys (N,) and episodes (N, ...) for any N.
    Returns: a Rollout over the N episodes, in their order.
    The same computation in resumable pieces (to report progress between them):
    :class:`StreamRollout`.
    """
    stream = StreamRollout(task, apply_fn, schedule, config, num_slots, num_fresh, plan_chunks)
    carry = stream.advance(params, keys, episodes, stream.start(params, keys, episodes))
    return stream.result(carry)


class StreamCarry(struct.PyTreeNode):
    """The state of a slot pool (see :class:`StreamRollout`); S slots, N episodes.

    next_ep: int32 () next episode to load.  slot_ep: int32 (S,) episode in each slot (N: empty).
    states: task states (S, ...).  plans: float32 (S, H, W, G) each slot's current plan.
    slot_t / slot_calls / slot_plans: int32 (S,) moves, denoiser calls, plans of each slot's
    episode.  final_states: task states (N, ...) of retired episodes.  positions: int32
    (N, T + 1, 2).  out: dict of per-episode results (steps, calls, num_plans (N,), first_plan
    (N, H, W, G)).
    """

    next_ep: jax.Array
    slot_ep: jax.Array
    states: Any
    plans: jax.Array
    slot_t: jax.Array
    slot_calls: jax.Array
    slot_plans: jax.Array
    final_states: Any
    positions: jax.Array
    out: dict

    @property
    def finished(self) -> jax.Array:
        """bool (): every episode has been run and retired."""
        return (self.next_ep >= self.positions.shape[0]) & ~jnp.any(
            self.slot_ep < self.positions.shape[0])

    @property
    def episodes_retired(self) -> jax.Array:
        """int32 (): episodes finished so far."""
        return self.next_ep - jnp.sum(self.slot_ep < self.positions.shape[0]).astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class StreamRollout:
    """:func:`rollout_stream` split into pure, jit-able pieces, so a caller can run the pool a
    few moves at a time (e.g. to update a progress bar) without paying a new pool's tail:

        stream = StreamRollout(task, apply_fn, schedule, config, num_slots)
        carry = stream.start(params, keys, episodes)
        while not carry.finished:
            carry = stream.advance(params, keys, episodes, carry, max_moves=8)
        rollout = stream.result(carry)

    gives exactly ``rollout_stream(task, apply_fn, params, schedule, keys, episodes, config,
    num_slots)``. params, keys and episodes must be the same in every call.
    """

    task: Any
    apply_fn: Callable
    schedule: Schedule
    config: PlannerConfig
    num_slots: int
    num_fresh: int | None = None
    plan_chunks: int = 4

    def __post_init__(self):
        if self.config.mode not in ("on_the_fly", "warm_start"):
            raise ValueError("rollout_stream supports on_the_fly and warm_start, not "
                             f"{self.config.mode}")
        if self.config.record_plans:
            raise ValueError("record_plans is not supported by rollout_stream; use rollout")
        if self.num_slots < 1 or self._fresh_cap < 1:
            raise ValueError(f"num_slots and num_fresh must be >= 1, got {self.num_slots}, "
                             f"{self.num_fresh}")

    @property
    def _warm(self) -> bool:
        return self.config.mode == "warm_start"

    @property
    def _fresh_cap(self) -> int:
        cap = max(1, self.num_slots // 8) if self.num_fresh is None else int(self.num_fresh)
        return min(cap, self.num_slots) if self._warm else self.num_slots

    def _plan_fn(self, params):
        return make_planner(self.task, self.apply_fn, params, self.schedule, self.config)

    def start(self, params, keys, episodes) -> StreamCarry:
        """An empty pool over the N episodes (keys (N,), episodes (N, ...))."""
        task, slots, n = self.task, int(self.num_slots), keys.shape[0]
        plan_fn = self._plan_fn(params)
        v_reset = jax.vmap(task.reset)
        tokens_all = jax.vmap(task.tokens)(episodes)
        # Per-slot state (placeholders for empty slots: episode 0, never recorded).
        states = v_reset(_take(episodes, jnp.zeros((slots,), jnp.int32)))
        plan_shape = jax.eval_shape(lambda: plan_fn(keys[:1], _take(states, jnp.arange(1)),
                                                    tokens_all[:1])).shape[1:]
        final_states = v_reset(episodes)
        start = jax.vmap(task.position)(final_states)
        positions = jnp.broadcast_to(start[:, None, :],
                                     (n, task.max_steps + 1, 2)).astype(jnp.int32)
        zeros = jnp.zeros((slots,), jnp.int32)
        out = dict(steps=jnp.zeros((n,), jnp.int32), calls=jnp.zeros((n,), jnp.int32),
                   num_plans=jnp.zeros((n,), jnp.int32),
                   first_plan=jnp.zeros((n,) + plan_shape, jnp.float32))
        return StreamCarry(next_ep=jnp.int32(0), slot_ep=jnp.full((slots,), n, jnp.int32),
                           states=states, plans=jnp.zeros((slots,) + plan_shape, jnp.float32),
                           slot_t=zeros, slot_calls=zeros, slot_plans=zeros,
                           final_states=final_states, positions=positions, out=out)

    def advance(self, params, keys, episodes, carry: StreamCarry,
                max_moves: int | None = None) -> StreamCarry:
        """Runs the pool for at most max_moves moves (None: until every episode is done)."""
        task, config, slots, n = self.task, self.config, int(self.num_slots), keys.shape[0]
        warm, fresh_cap = self._warm, self._fresh_cap
        # Re-plans run in sub-batches of the active slots only, so a pool's tail (few episodes
        # still running) does not pay for planning every slot.
        chunk = max(1, -(-slots // self.plan_chunks))
        plan_fn = self._plan_fn(params)
        v_done = jax.vmap(task.done)
        v_reset = jax.vmap(task.reset)
        tokens_all = jax.vmap(task.tokens)(episodes)

        def slot_keys(slot_ep, slot_t):
            ep_keys = keys[jnp.clip(slot_ep, 0, n - 1)]
            return jax.vmap(jax.random.fold_in)(ep_keys, slot_t if config.fresh_noise
                                                else jnp.zeros_like(slot_t))

        def body(c: StreamCarry) -> StreamCarry:
            slot_ep, states, out, final_states = c.slot_ep, c.states, c.out, c.final_states
            slot_t, slot_calls, slot_plans = c.slot_t, c.slot_calls, c.slot_plans
            occupied = slot_ep < n
            # 1. Retire finished episodes.
            finished = occupied & v_done(states)
            write = jnp.where(finished, slot_ep, n)
            final_states = _put(final_states, write, states)
            out = dict(out, steps=out["steps"].at[write].set(slot_t, mode="drop"),
                       calls=out["calls"].at[write].set(slot_calls, mode="drop"),
                       num_plans=out["num_plans"].at[write].set(slot_plans, mode="drop"))
            slot_ep = jnp.where(finished, n, slot_ep)
            free = slot_ep >= n
            # 2. Refill free slots, in episode order, at most fresh_cap of them.
            rank = jnp.cumsum(free) - 1
            new_ep = c.next_ep + rank
            load = free & (rank < fresh_cap) & (new_ep < n)
            slot_ep = jnp.where(load, new_ep, slot_ep)
            next_ep = c.next_ep + jnp.sum(load).astype(jnp.int32)
            loaded = v_reset(_take(episodes, jnp.clip(new_ep, 0, n - 1)))
            states = jax.tree.map(lambda old, new: jnp.where(
                load.reshape((-1,) + (1,) * (old.ndim - 1)), new, old), states, loaded)
            slot_t = jnp.where(load, 0, slot_t)
            slot_calls = jnp.where(load, 0, slot_calls)
            slot_plans = jnp.where(load, 0, slot_plans)
            tokens = tokens_all[jnp.clip(slot_ep, 0, n - 1)]
            active = (slot_ep < n) & ~v_done(states)
            k = slot_keys(slot_ep, slot_t)
            # 3. Plan.
            plans = c.plans
            if warm:
                # Full first plans for the newly loaded slots (a sub-batch of fresh_cap
                # slots) ...
                order = jnp.argsort(~load, stable=True)[:fresh_cap]
                sub_load = load[order]
                full = jax.lax.cond(
                    jnp.any(load),
                    lambda: plan_fn(k[order], _take(states, order), tokens[order]),
                    lambda: plans[order])
                # ... and warm re-plans for the others.
                rewarm = active & ~load
                plans = _plan_subset(plan_fn, rewarm, k, states, tokens, plans, chunk,
                                     warm=True)
                plans = plans.at[jnp.where(sub_load, order, slots)].set(full, mode="drop")
                calls = jnp.where(load & active, config.full_plan_calls,
                                  jnp.where(rewarm, config.warm_plan_calls, 0))
            else:
                plans = _plan_subset(plan_fn, active, k, states, tokens, plans, chunk)
                calls = jnp.where(active, config.full_plan_calls, 0)
            slot_calls = slot_calls + calls
            slot_plans = slot_plans + (calls > 0)
            out = dict(out, first_plan=out["first_plan"].at[jnp.where(load, slot_ep, n)].set(
                plans, mode="drop"))
            # 4. Act.
            actions = jax.vmap(task.psi)(states, plans)
            stepped = jax.vmap(task.step)(states, actions)
            states = jax.tree.map(lambda old, new: jnp.where(
                active.reshape((-1,) + (1,) * (old.ndim - 1)), new, old), states, stepped)
            slot_t = slot_t + active
            pos = jax.vmap(task.position)(states)
            row = jnp.where(active, slot_ep, n)
            positions = c.positions.at[row, slot_t].set(pos, mode="drop")
            return StreamCarry(next_ep=next_ep, slot_ep=slot_ep, states=states, plans=plans,
                               slot_t=slot_t, slot_calls=slot_calls, slot_plans=slot_plans,
                               final_states=final_states, positions=positions, out=out)

        if max_moves is None:
            return jax.lax.while_loop(lambda c: ~c.finished, body, carry)
        _, carry = jax.lax.while_loop(lambda ic: (ic[0] < max_moves) & ~ic[1].finished,
                                      lambda ic: (ic[0] + 1, body(ic[1])),
                                      (jnp.int32(0), carry))
        return carry

    def result(self, carry: StreamCarry) -> Rollout:
        """The Rollout over the N episodes of a finished pool, in their order."""
        task = self.task
        steps, t_max = carry.out["steps"], task.max_steps
        final = jax.vmap(task.position)(carry.final_states)
        idx = jnp.arange(t_max + 1)[None, :]
        positions = jnp.where((idx > steps[:, None])[..., None], final[:, None, :],
                              carry.positions)
        return Rollout(final_state=carry.final_states, positions=positions, steps=steps,
                       done=jax.vmap(task.done)(carry.final_states),
                       denoiser_calls=carry.out["calls"], num_plans=carry.out["num_plans"],
                       first_plan=carry.out["first_plan"], plans=None)
