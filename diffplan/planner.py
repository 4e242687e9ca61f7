"""The planner as a library (DESIGN.md, contract 5): one planning step of Algorithm 1 as pure
functions of arrays and PRNG keys.

    den = diffplan.load_denoiser("checkpoints/compile_gridworld")
    planner = diffplan.Planner(den, diffplan.PlannerConfig(mode="warm_start"))
    ps = planner.init(key, tokens)            # one episode; jax.vmap for a batch
    plan, ps = planner.plan(ps, condition)    # condition (H, W, C) -> plan (H, W, G)

``plan`` in-paints the G generated channels (path, goal estimate, ...) of the planning tensor
while holding the C condition channels (what the agent has observed) fixed, and carries in the
:class:`PlannerState` what the next call needs: the previous plan (warm start), the move
counter (the noise of the plan made at move m comes from ``fold_in(key, m)``) and the
denoiser calls spent. The world turns a plan into an action (``task.psi``); one call of
``plan`` per move. ``plan_batch`` does the same for a batch of episodes and spends denoiser
calls only on the episodes that need a new plan (sub-batches of needy episodes); it gives
every episode exactly what ``jax.vmap(plan)`` gives it. ``diffplan.rollouts`` drives a whole
batch of episodes with it.

Modes (``PlannerConfig.mode``), each deciding at every call whether to make a new plan:
  one_shot    plan at the first call only; later calls return that plan.
  k_shot      plan at the first call and when the caller's ``replan`` trigger says so (the
              grid world's: the agent reached the plan's goal estimate), at most k plans.
  on_the_fly  plan from pure noise at every call (the paper's Algorithm 1).
  warm_start  on-the-fly on its own ``warm_num_steps``-step schedule: the first plan
              denoises that schedule from pure noise; every later plan resumes from the
              previous plan re-noised to its step ``warm_start_step``, so it costs
              ``warm_num_steps - warm_start_step`` denoiser calls.
In on_the_fly and warm_start modes ``replan=False`` keeps the current plan for this move (a
re-planning trigger of the caller's, e.g. "only when the observation changed").
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
from flax import struct

from diffplan.denoiser import LoadedDenoiser
from diffplan.sampler import denoiser_calls, sample

__all__ = ["MODES", "REPLAN_TRIGGERS", "MIN_SUB_BATCH", "PlannerConfig", "PlannerState", "Planner", "subset_update"]

MODES = ("one_shot", "k_shot", "on_the_fly", "warm_start")
REPLAN_TRIGGERS = ("always", "on_change", "on_refuted")
MIN_SUB_BATCH = 16
"""``plan_batch`` plans in sub-batches of at least this many episodes (padding rows are
computed and dropped). Measured on the XLA CPU backend of jax 0.6.2: the shipped UNet's output
for a row is bit-identical at every batch size >= 16 (and under any permutation), but differs
by ~1e-6 below 16, which can flip a near-tied argmax of a plan. With sub-batches of >= 16 an
episode's result does not depend on how many episodes are evaluated at once."""
SAMPLE_STREAM = 0x5A3
"""With ``samples`` = K > 1, a plan's draws use its key and ``fold_in(key, SAMPLE_STREAM + j)``
for j = 1..K-1 (so the first draw is the plan a one-sample planner makes)."""
RETRY_STREAM = 0x5E7
"""``retry_batch`` draws a move's second plan with ``fold_in(the move's plan key, RETRY_STREAM)``."""


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """How to plan (hashable; a static argument under jit).

    mode: one of MODES. num_steps: denoising steps of a plan from noise (warm_start mode: see
    warm_num_steps). eta: 0 = DDIM, 1 = DDPM-like.
    k: plans per episode in k_shot mode. warm_num_steps: the sampling schedule of warm_start
    mode (None = num_steps): its first plan runs all of it from noise, its re-plans skip the
    first warm_start_step steps. The defaults, num_steps=10, warm_num_steps=3,
    warm_start_step=1 (chosen on the validation episodes, README): the other modes plan in 10
    steps; warm start plans first in 3 steps, then each re-plan re-noises the previous plan to
    the second of 3 trailing timesteps (t ~ 66 of 100) and denoises it in 2 calls. (The
    experiments' warm-start row is cheaper: warm_num_steps=2 with replan="on_change", one call
    per re-plan, re-planning only on new information; experiments.gridworld_spec.)
    clip_x0: clip the predicted x0 to [-1, 1] during sampling. record_plans: rollouts also
    return the plan used at every move (memory B x T x H x W x G: for figures, small batches
    only).
    fresh_noise: each plan draws new noise (key fold_in(episode key, move)); False reuses the
    episode's noise (key fold_in(episode key, 0)) at every re-plan, so that with eta = 0 plans
    change only where the observation changed.
    replan: in on_the_fly and warm_start modes, "always" re-plans before every move (the
    paper); "on_change" only when the world says the plan is stale (diffplan.rollouts.move
    asks ``task.new_information(condition at the last plan, condition)`` and
    ``task.at_goal_estimate``: new cells seen, or the plan's (sub-)goal reached);
    "on_refuted" only when what the plan assumed is contradicted by what is now known
    (``task.plan_refuted(state, plan)``, a task's optional method: in the grid world the cell
    the plan heads for has been seen and is not the object sought, or that object has come into
    view elsewhere) or the plan's (sub-)goal is reached: the agent keeps its guess of a hidden
    target until it is disproved instead of drawing a new guess at every move.
    """

    mode: str = "on_the_fly"
    num_steps: int = 10
    eta: float = 0.0
    k: int = 2
    warm_start_step: int = 1
    warm_num_steps: int | None = 3
    clip_x0: bool = True
    record_plans: bool = False
    fresh_noise: bool = True
    replan: str = "always"
    samples: int = 1

    def __post_init__(self):
        def is_int(v):
            return isinstance(v, int) and not isinstance(v, bool)

        if self.mode not in MODES:
            raise ValueError(f"unknown planner mode {self.mode!r}; expected one of {MODES}")
        if self.replan not in REPLAN_TRIGGERS:
            raise ValueError(f"unknown replan trigger {self.replan!r}; expected one of "
                             f"{REPLAN_TRIGGERS}")
        for name in ("num_steps", "k", "warm_start_step", "samples"):
            if not is_int(getattr(self, name)):
                raise ValueError(f"{name} must be an int, got {getattr(self, name)!r}")
        if self.warm_num_steps is not None and not is_int(self.warm_num_steps):
            raise ValueError(f"warm_num_steps must be an int or None, got "
                             f"{self.warm_num_steps!r}")
        if self.num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {self.num_steps}")
        if self.samples < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        if self.k < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        if self.warm_num_steps is not None and self.warm_num_steps < 1:
            raise ValueError(f"warm_num_steps must be >= 1, got {self.warm_num_steps}")
        if not 0 <= self.warm_start_step < self.warm_steps:
            raise ValueError(
                f"warm_start_step must be in 0..{self.warm_steps - 1} (the warm schedule has "
                f"{self.warm_steps} steps), got {self.warm_start_step}")
        if not isinstance(self.eta, (int, float)) or isinstance(self.eta, bool) \
                or not self.eta >= 0:
            raise ValueError(f"eta must be a number >= 0, got {self.eta!r}")
        for name in ("clip_x0", "record_plans", "fresh_noise"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")

    @property
    def full_plan_steps(self) -> int:
        """Steps of a plan from pure noise (an episode's first plan; every plan but warm
        re-plans)."""
        return self.warm_steps if self.mode == "warm_start" else self.num_steps

    @property
    def full_plan_calls(self) -> int:
        return self.samples * denoiser_calls(self.full_plan_steps, None)

    @property
    def warm_plan_calls(self) -> int:
        return self.samples * denoiser_calls(self.warm_steps, self.warm_start_step)

    @property
    def warm_steps(self) -> int:
        """Steps of the schedule warm re-plans resume in."""
        return self.num_steps if self.warm_num_steps is None else self.warm_num_steps

    def check_schedule(self, num_train_steps: int) -> None:
        """Raises ValueError if a step count exceeds the schedule's training timesteps."""
        for name, steps in (("num_steps", self.num_steps), ("warm_num_steps", self.warm_steps)):
            if steps > num_train_steps:
                raise ValueError(f"{name}={steps} exceeds the denoiser's schedule of "
                                 f"{num_train_steps} training timesteps")


class PlannerState(struct.PyTreeNode):
    """What the planner carries from one move to the next, for one episode (leading batch
    axes when vmapped).

    key: the episode's PRNG key. tokens: int32 (L,) the instruction; for a denoiser on
      pretrained features (``DenoiserConfig.context_dim`` > 0) the
      ``diffplan.denoiser.TextContext`` its UNet cross-attends to, computed from the (L, D)
      features once, in ``init`` (``LoadedDenoiser.prepare``).
    plan: float32 (H, W, G) the current plan (zeros before the first).
    condition: float32 (H, W, C) the condition it was made from (zeros before the first).
    move: int32 () calls of ``plan`` so far (moves). calls: int32 () denoiser calls spent.
    num_plans: int32 () plans made.
    fallbacks: int32 () moves whose plan gave the task's psi no move even after a second plan
      (tasks whose psi follows the plan's marks, ``task.follows_plan``; see
      ``diffplan.rollouts.move``).
    """

    key: jax.Array
    tokens: jax.Array
    plan: jax.Array
    condition: jax.Array
    move: jax.Array
    calls: jax.Array
    num_plans: jax.Array
    fallbacks: jax.Array


def _take(tree, idx):
    return jax.tree.map(lambda x: x[idx], tree)


def subset_update(need, compute: Callable, current, chunk: int):
    """``current`` (a pytree of (B, ...) arrays) with the rows where ``need`` (bool (B,)) is
    True replaced by ``compute(idx)``, evaluated ``chunk`` rows at a time (idx int32 (chunk,)
    row indices; rows past the needy ones are computed on row 0 and dropped), so the cost
    follows the number of needy rows rather than B. Each row's value must depend on that row
    only (then the result equals computing every row at once where needed)."""
    b = need.shape[0]
    count = jnp.sum(need).astype(jnp.int32)
    order = jnp.argsort(~need, stable=True).astype(jnp.int32)  # needy rows first
    order = jnp.concatenate([order, jnp.full((chunk,), b, jnp.int32)])

    def body(carry):
        i, current = carry
        idx = jax.lax.dynamic_slice(order, (i,), (chunk,))
        valid = (i + jnp.arange(chunk)) < count
        values = compute(jnp.where(valid, idx, 0))
        rows = jnp.where(valid, idx, b)
        return i + chunk, jax.tree.map(lambda c, v: c.at[rows].set(v, mode="drop"), current,
                                       values)

    _, current = jax.lax.while_loop(lambda c: c[0] < count, body, (jnp.int32(0), current))
    return current


class Planner(struct.PyTreeNode):
    """A diffusion planner: a denoiser and how to plan with it (a pytree: pass it to jitted
    functions as an argument; its parameters are leaves, the config is static).

    Attributes:
      denoiser: a :class:`diffplan.denoiser.LoadedDenoiser` (``diffplan.load_denoiser``).
      config: a :class:`PlannerConfig`.
    """

    denoiser: LoadedDenoiser
    config: PlannerConfig = struct.field(pytree_node=False)

    def __post_init__(self):
        if not isinstance(self.config, PlannerConfig):
            raise ValueError(f"config must be a PlannerConfig, got {type(self.config).__name__}")
        if isinstance(self.denoiser, LoadedDenoiser):
            self.config.check_schedule(self.denoiser.schedule.num_train_steps)

    # ------------------------------------------------------------------ one episode

    @property
    def plan_shape(self) -> tuple[int, int, int]:
        """(H, W, G) of a plan."""
        return self.denoiser.plan_shape

    def init(self, key: jax.Array, tokens: jax.Array) -> PlannerState:
        """The state of a new episode: key, a PRNG key (the episode's); tokens int32 (L,), the
        instruction's token ids, or for a denoiser on pretrained features
        (``DenoiserConfig.context_dim`` D > 0) their float32 (L, D) features
        (``diffplan.instruction``: computed once per episode, kept in the state)."""
        tokens = jnp.asarray(tokens)
        config = getattr(self.denoiser, "model_config", None)
        dim = int(getattr(config, "context_dim", 0) or 0)
        # (L, D) features: what a features denoiser reads; without a model config (a
        # hand-written denoiser) only a float array is taken as features, an int one is a
        # batch of token ids and refused.
        features = tokens.ndim == 2 and (bool(dim) or jnp.issubdtype(tokens.dtype, jnp.floating))
        if dim and not (features and tokens.shape[-1] == dim):
            raise ValueError(f"this denoiser reads pretrained features (L, {dim}) (one "
                             f"episode; vmap for a batch), got shape {tokens.shape}")
        if not dim and not (tokens.ndim == 1 or (features and config is None)):
            raise ValueError(f"tokens must be int32 (L,) (one episode; vmap for a batch), got "
                             f"shape {tokens.shape}")
        tokens = tokens.astype(jnp.float32 if features else jnp.int32)
        if isinstance(self.denoiser, LoadedDenoiser):
            tokens = self.denoiser.prepare(tokens)  # features: the text context, once
        zero = jnp.zeros((), jnp.int32)
        h, w, _ = self.plan_shape
        return PlannerState(key=key, tokens=tokens,
                            plan=jnp.zeros(self.plan_shape, jnp.float32),
                            condition=jnp.zeros((h, w, self.denoiser.num_cond_channels),
                                                jnp.float32),
                            move=zero, calls=zero, num_plans=zero, fallbacks=zero)

    def plan(self, state: PlannerState, condition: jax.Array,
             replan: Optional[jax.Array] = None, rank: Optional[Callable] = None
             ) -> tuple[jax.Array, PlannerState]:
        """One move's plan for one episode.

        Args:
          state: the episode's PlannerState.
          condition: float32 (H, W, C), the condition channels (what the agent has observed).
          replan: optional bool (): the caller's re-planning trigger (see the module
            docstring); None: the mode's default (re-plan every move in on_the_fly and
            warm_start, never in k_shot but for the first plan).
          rank: with config.samples = K > 1 (required then): plans float32 (K, H, W, G) ->
            float32 (K,) costs; the cheapest draw is kept.
        Returns:
          (plan float32 (H, W, G), the next PlannerState).
        Under vmap both the fresh and the warm branch of a warm_start plan are computed for
        every episode; ``plan_batch`` computes only what each episode needs.
        """
        self._check_condition(condition, batched=False)
        need, warm = self._decide(state, replan)
        mode = self.config.mode
        key = self._plan_key(state)
        score = rank if self._check_rank(rank) else None
        fresh = lambda: self._draw(key, condition, state.tokens, None, score)  # noqa: E731
        hold = lambda: state.plan  # noqa: E731
        if mode == "on_the_fly" and replan is None:
            new = fresh()
        elif mode == "warm_start":
            warm_fn = lambda: self._draw(key, condition, state.tokens, state.plan, score)  # noqa
            branch = jnp.where(need, jnp.where(warm, 2, 1), 0)
            new = jax.lax.switch(branch, [hold, fresh, warm_fn])
        else:
            new = jax.lax.cond(need, fresh, hold)
        return new, self._advance(state, new, condition, need, warm, jnp.bool_(True))

    # ------------------------------------------------------------------ a batch

    def plan_batch(self, states: PlannerState, conditions: jax.Array,
                   active: Optional[jax.Array] = None, replan: Optional[jax.Array] = None,
                   chunk: Optional[int] = None, fresh_chunk: Optional[int] = None,
                   rank: Optional[Callable] = None) -> tuple[jax.Array, PlannerState]:
        """``jax.vmap(plan)`` over a batch of B episodes, computing plans only where needed.

        Args:
          states: PlannerState with a leading (B,) axis.
          conditions: float32 (B, H, W, C).
          active: optional bool (B,): episodes still running (default all). Inactive ones
            keep their plan and counters (no move is counted).
          replan: optional bool (B,), the caller's trigger (as in ``plan``).
          chunk: episodes per denoiser sub-batch (default B): the plans are computed for the
            needy episodes only, ``chunk`` at a time (at least MIN_SUB_BATCH).
          fresh_chunk: the sub-batch of plans from noise in warm_start mode (default chunk;
            at least MIN_SUB_BATCH).
          rank: with config.samples = K > 1 (required then): (i int32 (), plans float32
            (K, H, W, G)) -> float32 (K,) costs of row i's draws; the cheapest is kept.
        Returns:
          (plans float32 (B, H, W, G), the next states).
        """
        self._check_condition(conditions, batched=True)
        b = conditions.shape[0]
        active = jnp.ones((b,), bool) if active is None else jnp.asarray(active, bool)
        need, warm = jax.vmap(self._decide)(states, replan)
        need = need & active
        chunk = max(MIN_SUB_BATCH, b if chunk is None else int(chunk))
        fresh_chunk = chunk if fresh_chunk is None else max(MIN_SUB_BATCH, int(fresh_chunk))
        keys = jax.vmap(self._plan_key)(states)
        fresh = self._fresh_rows(keys, conditions, states.tokens, rank)
        warm_plans = self._rows(keys, conditions, states.tokens, rank, states.plan)

        plans = states.plan
        if self.config.mode == "warm_start":
            plans = subset_update(need & ~warm, fresh, plans, fresh_chunk)
            plans = subset_update(need & warm, warm_plans, plans, chunk)
        else:
            plans = subset_update(need, fresh, plans, chunk)
        return plans, jax.vmap(self._advance)(states, plans, conditions, need, warm, active)

    def retry_batch(self, states: PlannerState, conditions: jax.Array, need: jax.Array,
                    chunk: Optional[int] = None, rank: Optional[Callable] = None
                    ) -> tuple[jax.Array, PlannerState]:
        """A second plan of this move, from noise with a key of its own, for the episodes
        where ``need`` (bool (B,)); the others keep theirs. It costs a full plan's calls and
        counts as a plan, not as a move. Modes that plan once (one_shot, k_shot) never plan
        again here: their plans are returned unchanged.

        Returns (plans float32 (B, H, W, G), the next states)."""
        self._check_condition(conditions, batched=True)
        if self.config.mode in ("one_shot", "k_shot"):
            return states.plan, states
        need = jnp.asarray(need, bool)
        chunk = max(MIN_SUB_BATCH, need.shape[0] if chunk is None else int(chunk))
        keys = jax.vmap(lambda s: jax.random.fold_in(self._plan_key(s), RETRY_STREAM))(states)
        plans = subset_update(need, self._fresh_rows(keys, conditions, states.tokens, rank),
                              states.plan, chunk)
        n = need.astype(jnp.int32)
        return plans, states.replace(
            plan=plans,
            condition=jnp.where(need[:, None, None, None], conditions.astype(jnp.float32),
                                states.condition),
            calls=states.calls + n * self.config.full_plan_calls,
            num_plans=states.num_plans + n)

    # ------------------------------------------------------------------ internals

    def _fresh_rows(self, keys, conditions, tokens, rank=None):
        """idx -> plans from noise of those rows (subset_update's compute)."""
        return self._rows(keys, conditions, tokens, rank, None)

    def _rows(self, keys, conditions, tokens, rank, previous):
        """idx int32 (n,) -> plans (n, H, W, G) of those rows, from noise (previous None) or
        warm from previous (B, H, W, G); rank: see plan_batch."""
        self._check_rank(rank)

        def row(i):
            score = None if rank is None else (lambda plans: rank(i, plans))
            prev = None if previous is None else previous[i]
            return self._draw(keys[i], conditions[i], jax.tree.map(lambda a: a[i], tokens),
                              prev, score)

        return jax.vmap(row)

    def _check_rank(self, rank) -> bool:
        """True if the config draws several plans (then rank must be given)."""
        if self.config.samples == 1:
            return False
        if rank is None:
            raise ValueError(f"samples={self.config.samples} draws several plans per re-plan; "
                             f"pass rank (plan costs) to choose among them")
        return True

    def _draw(self, key, condition, tokens, previous, score):
        """One plan (H, W, G): the single sample, or of config.samples draws the one with the
        lowest score(plans (K, H, W, G)) -> (K,)."""
        k = self.config.samples
        if k == 1:
            return self._sample(key, condition, tokens, previous)
        keys = jnp.stack([key] + [jax.random.fold_in(key, SAMPLE_STREAM + j)
                                  for j in range(1, k)])
        plans = jax.vmap(lambda kk: self._sample(kk, condition, tokens, previous))(keys)
        return plans[jnp.argmin(score(plans))]

    def _check_condition(self, condition, batched: bool):
        h, w, g = self.plan_shape
        c = self.denoiser.num_cond_channels
        expected = ((None,) if batched else ()) + (h, w, c)
        shape = tuple(jnp.shape(condition))
        if len(shape) != len(expected) or any(e is not None and e != s
                                              for e, s in zip(expected, shape)):
            what = "(B, H, W, C)" if batched else "(H, W, C) (one episode)"
            raise ValueError(f"condition must be {what} = {expected}, got shape {shape}")

    def _decide(self, state: PlannerState, replan):
        """(need, warm) bool (): make a plan at this call; from the previous plan."""
        mode, first = self.config.mode, state.num_plans == 0
        if mode == "one_shot":
            want = jnp.bool_(False)
        elif mode == "k_shot":
            want = (jnp.bool_(False) if replan is None else jnp.asarray(replan, bool)) & (
                state.num_plans < self.config.k)
        else:
            want = jnp.bool_(True) if replan is None else jnp.asarray(replan, bool)
        warm = ~first & (mode == "warm_start")
        return first | want, warm

    def _plan_key(self, state: PlannerState):
        return jax.random.fold_in(state.key, state.move if self.config.fresh_noise else 0)

    def _advance(self, state: PlannerState, plan, condition, need, warm, active
                 ) -> PlannerState:
        cfg = self.config
        cost = jnp.where(warm, cfg.warm_plan_calls, cfg.full_plan_calls)
        condition = jnp.where(need, condition.astype(jnp.float32), state.condition)
        return state.replace(plan=plan, condition=condition,
                             move=state.move + active.astype(jnp.int32),
                             calls=state.calls + jnp.where(need, cost, 0).astype(jnp.int32),
                             num_plans=state.num_plans + need.astype(jnp.int32))

    def _sample(self, key, condition, tokens, previous):
        """One plan (H, W, G) by in-painting; from ``previous`` (H, W, G) if given (warm)."""
        cfg, den = self.config, self.denoiser
        c, g = den.num_cond_channels, den.num_gen_channels
        condition = condition.astype(jnp.float32)
        known_mask = jnp.arange(c + g) < c
        zeros = jnp.zeros(condition.shape[:-1] + (g,), jnp.float32)
        x_known = jnp.concatenate([condition, zeros], axis=-1)[None]
        kwargs: dict[str, Any] = dict(num_steps=cfg.full_plan_steps)
        if previous is not None:
            kwargs = dict(x_init=jnp.concatenate([condition, previous], axis=-1)[None],
                          start_step=cfg.warm_start_step, num_steps=cfg.warm_steps)
        x0 = sample(den.eps_fn(jax.tree.map(lambda a: a[None], tokens)), den.schedule, key,
                    x_known, known_mask,
                    eta=cfg.eta, clip_x0=cfg.clip_x0, **kwargs)
        return x0[0, ..., c:]
