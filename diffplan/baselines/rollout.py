"""The baselines' evaluation loop: a policy acts in the world exactly as our planner's agent
does (``task.reset``, ``task.step`` with collisions, at most ``task.max_steps`` moves), and the
result is the same :class:`diffplan.rollouts.Rollout`, built with the helpers of
``diffplan.rollouts``, so a world's evaluation measures both alike on the executed
trajectories.

A policy is ``act_fn(params, conditions, tokens, keys)`` over a batch of B episodes:
conditions float32 (B, H, W, C) = ``task.condition`` of each state (what the agent has seen),
tokens int32 (B, L) the instructions (``task.tokens``: a policy turns them into what its network
reads, e.g. the world's goal vector), keys (B,) the episodes' keys of this move
(``fold_in(keys[i], move)``); it returns the moves int32 (B,), or (moves, plans float32
(B, H, W, G)) for a policy that plans (the plan of the first move is kept as ``first_plan``, the
paper's plan metrics). The loop never gives a policy anything but these.
"""
from __future__ import annotations

from typing import Callable, Optional

import jax
import jax.numpy as jnp
from flax import struct

from diffplan.rollouts import Rollout, _result, _start_positions, _where_rows

__all__ = ["policy_rollout", "PolicyCounters"]


@struct.dataclass
class PolicyCounters:
    """Per-episode counters of a policy rollout, in the fields ``diffplan.rollouts._result``
    reads of a PlannerState: moves taken, denoiser calls spent, plans made."""

    move: jax.Array
    calls: jax.Array
    num_plans: jax.Array


def policy_rollout(task, act_fn: Callable, params, keys, episodes, *,
                   calls_per_move: int = 0, plan_channels: Optional[int] = None,
                   observe: Optional[Callable] = None) -> Rollout:
    """Runs a batch of episodes with a policy; pure and jit-able (task, act_fn,
    calls_per_move, plan_channels and observe static).

    Args:
      task: a diffplan.task.Task (e.g. envs.gridworld.task.GridTask).
      act_fn: the policy (see the module docstring).
      params: its parameters (any pytree; passed through to act_fn).
      keys: (B,) PRNG keys, one per episode.
      episodes: the task's episode pytree with a leading batch axis B.
      calls_per_move: denoiser calls one move of the policy costs (0 for BC / CQL).
      plan_channels: G of the plans act_fn returns (None: it returns moves only; first_plan
        is then zeros with one channel).
      observe: state -> what act_fn sees of one episode (None: ``task.condition``, what the
        agent has seen; a privileged reference agent passes e.g. the identity).
    Returns: a Rollout (denoiser_calls = calls_per_move x moves; num_plans = moves when
      calls_per_move > 0, else 0).
    """
    states = jax.vmap(task.reset)(episodes)
    tokens = jax.vmap(task.tokens)(episodes)
    batch = keys.shape[0]
    positions = _start_positions(task, states, batch)
    first_plan = jnp.zeros((batch, task.height, task.width, plan_channels or 1), jnp.float32)
    zeros = jnp.zeros((batch,), jnp.int32)
    counters = PolicyCounters(move=zeros, calls=zeros, num_plans=zeros)
    v_done = jax.vmap(task.done)
    v_observe = jax.vmap(task.condition if observe is None else observe)

    def body(carry):
        t, states, counters, positions, first_plan = carry
        active = ~v_done(states)
        conditions = v_observe(states)
        move_keys = jax.vmap(lambda k: jax.random.fold_in(k, t))(keys)
        out = act_fn(params, conditions, tokens, move_keys)
        if plan_channels is None:
            actions = out
        else:
            actions, plans = out
            first_plan = jnp.where(t == 0, plans, first_plan)
        states = _where_rows(active, jax.vmap(task.step)(states, actions), states)
        moved = active.astype(jnp.int32)
        counters = PolicyCounters(move=counters.move + moved,
                                  calls=counters.calls + calls_per_move * moved,
                                  num_plans=counters.num_plans + (calls_per_move > 0) * moved)
        positions = positions.at[:, t + 1].set(jax.vmap(task.position)(states))
        return t + 1, states, counters, positions, first_plan

    def cond(carry):
        return (carry[0] < task.max_steps) & ~jnp.all(v_done(carry[1]))

    carry = (jnp.int32(0), states, counters, positions, first_plan)
    _, states, counters, positions, first_plan = jax.lax.while_loop(cond, body, carry)
    return _result(task, states, positions, counters, first_plan)
