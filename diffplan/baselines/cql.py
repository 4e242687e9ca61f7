"""Conservative Q-learning (the paper's CQL baseline, appendix), offline, on top of double DQN.

Data: a replay buffer of ``buffer_size`` (300k) transitions collected once, before training,
by an epsilon-greedy behaviour around the world's expert: with probability 1 - epsilon the
expert's action, else a uniformly random one; epsilon is annealed linearly from 1 to 0.01 over
the first 10k frames (env steps, counted over all parallel collectors of a world) and then
held. Episodes that end are replaced by fresh ones of the world's training stream. Several
worlds (e.g. the grid world's settings) are collected in fixed proportions.

The world comes as a :class:`Collector`, per-episode pure functions (vmapped here): what a
transition stores (``observe``, ``instruction``), the expert, the reward and the ends of an
episode. The grid world's is ``envs.gridworld.baselines.GridCollector`` (the expert's
shortest-path move, minus the instructed route still to go as the reward).

Loss: the double-DQN Huber TD error, target ``r + gamma (1 - terminal) Q_target(s',
argmax_a Q(s', a))``, plus ``alpha * E[logsumexp_a Q(s, a) - Q(s, a_data)]`` (CQL(H), Kumar et
al. 2020); Adam lr 1e-3, gamma 0.99, the target network soft-updated with tau 0.001 after every
step (appendix). The network is the appendix's conv net with one Q-value per action; it acts
greedily.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping, Protocol, Sequence

import jax
import jax.numpy as jnp
import optax

from diffplan import checkpoint as ckpt
from diffplan.baselines import nets
from diffplan.train import TrainState, fit, run_metadata

__all__ = ["CQLTrainConfig", "Collector", "epsilon_at", "action_dtype", "collect",
           "collect_buffer",
           "as_q_batch", "network_q_fn", "cql_loss", "make_cql_step", "train_cql"]


@dataclasses.dataclass(frozen=True)
class CQLTrainConfig:
    """Hyper-parameters (the appendix's where it gives them: buffer 300k, epsilon 1 -> 0.01
    over 10k frames, tau 0.001, gamma 0.99, lr 1e-3; alpha, batch size, the number of parallel
    collectors and steps are ours)."""

    seed: int = 0
    steps: int = 10000
    batch_size: int = 128
    lr: float = 1e-3
    gamma: float = 0.99
    tau: float = 0.001
    alpha: float = 1.0
    buffer_size: int = 300_000
    epsilon_start: float = 1.0
    epsilon_end: float = 0.01
    epsilon_frames: int = 10_000
    collectors: int = 256
    checkpoint_every: int = 2000
    log_every: int = 100


class Collector(Protocol):
    """A world for the epsilon-greedy collection (hashable: a static argument of the compiled
    collection). Every method but ``episodes`` acts on ONE episode / state."""

    num_actions: int

    def episodes(self, key, n: int) -> Any:
        """n fresh training episodes (leading axis n) from key."""

    def reset(self, episode) -> Any:
        """The state at t = 0."""

    def instruction(self, episode) -> Any:
        """What a transition stores of the instruction (e.g. token ids)."""

    def step(self, state, action) -> Any:
        """The state after an action int32 ()."""

    def observe(self, state) -> Any:
        """What a transition stores of a state (a compact observation pytree)."""

    def expert_action(self, state) -> jax.Array:
        """int32 (): the expert's action."""

    def reward(self, state) -> jax.Array:
        """float32 (): the reward of arriving in state."""

    def terminal(self, state) -> jax.Array:
        """bool (): the episode ended in a way that stops bootstrapping (success)."""

    def done(self, state) -> jax.Array:
        """bool (): the episode is over (terminal or out of time)."""


def epsilon_at(frame, start: float = 1.0, end: float = 0.01, frames: int = 10_000):
    """Linear annealing from start to end over ``frames`` frames, then end."""
    frac = jnp.clip(jnp.asarray(frame, jnp.float32) / frames, 0.0, 1.0)
    return start + (end - start) * frac


def action_dtype(num_actions: int):
    """The narrowest integer type the buffer stores actions in: int8 up to 127 actions, else
    int16 (up to 32767)."""
    if num_actions > 32767:
        raise ValueError(f"the buffer stores actions as int16: at most 32767, got {num_actions}")
    return jnp.int8 if num_actions <= 127 else jnp.int16


def _where_done(done, fresh, old):
    return jax.tree.map(lambda a, b: jnp.where(done.reshape((-1,) + (1,) * (a.ndim - 1)), a, b),
                        fresh, old)


def _collect(key, world: Collector, collectors: int, moves: int, cfg: CQLTrainConfig):
    """Transitions (moves, collectors, ...) of one world (its own epsilon schedule: frame
    f = move * collectors + collector)."""
    v = jax.vmap
    episodes = world.episodes(jax.random.fold_in(key, 0), collectors)
    states = v(world.reset)(episodes)

    def body(carry, t):
        states, instructions = carry
        k_explore, k_action, k_new = jax.random.split(jax.random.fold_in(key, t + 1), 3)
        frame = t * collectors + jnp.arange(collectors)
        eps = epsilon_at(frame, cfg.epsilon_start, cfg.epsilon_end, cfg.epsilon_frames)
        explore = jax.random.uniform(k_explore, (collectors,)) < eps
        random_actions = jax.random.randint(k_action, (collectors,), 0, world.num_actions)
        actions = jnp.where(explore, random_actions, v(world.expert_action)(states))
        nxt = v(world.step)(states, actions)
        record = {"obs": v(world.observe)(states), "next_obs": v(world.observe)(nxt),
                  "instruction": instructions,
                  "action": actions.astype(action_dtype(world.num_actions)),
                  "reward": v(world.reward)(nxt), "terminal": v(world.terminal)(nxt)}
        fresh = world.episodes(k_new, collectors)
        done = v(world.done)(nxt)
        states = _where_done(done, v(world.reset)(fresh), nxt)
        instructions = _where_done(done, v(world.instruction)(fresh), instructions)
        return (states, instructions), record

    carry = (states, v(world.instruction)(episodes))
    _, records = jax.lax.scan(body, carry, jnp.arange(moves))
    return records


collect = jax.jit(_collect, static_argnums=(1, 2, 3, 4))
"""collect(key, world, collectors, moves, cfg) -> transitions (moves, collectors, ...) of one
world, jitted (world, collectors, moves and cfg static)."""


def collect_buffer(key, worlds: Sequence[tuple[Collector, int]],
                   cfg: CQLTrainConfig = CQLTrainConfig()):
    """The replay buffer: a dict of arrays with a leading axis of cfg.buffer_size transitions
    (obs / next_obs as the world observes them, instruction, action int8 (int16 beyond 127
    actions: :func:`action_dtype`), reward float32,
    terminal bool). worlds: (collector, count) pairs, collected in the counts' proportions,
    cfg.collectors split alike (each world anneals epsilon over its own first epsilon_frames
    frames; world i collects with fold_in(key, i)); a pure function of key, worlds and cfg."""
    dtypes = {action_dtype(world.num_actions) for world, _ in worlds}
    if len(dtypes) > 1:
        raise ValueError("the worlds of one buffer must store their actions alike (all at "
                         "most 127 actions, or all more)")
    total = sum(count for _, count in worlds)
    moves = math.ceil(cfg.buffer_size / cfg.collectors)
    parts = []
    for i, (world, count) in enumerate(worlds):
        collectors = max(1, round(cfg.collectors * count / total))
        records = collect(jax.random.fold_in(key, i), world, collectors, moves, cfg)
        parts.append(jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), records))
    buffer = jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)
    n = jax.tree.leaves(buffer)[0].shape[0]
    if n > cfg.buffer_size:  # drop evenly spaced surplus rows so every world keeps its share
        keep = jnp.round(jnp.linspace(0, n - 1, cfg.buffer_size)).astype(jnp.int32)
        buffer = jax.tree.map(lambda x: x[keep], buffer)
    return buffer


def as_q_batch(buffer):
    """The buffer with obs / next_obs as Q-function observations {"obs", "instruction"} (the
    instruction's arrays shared, not copied)."""
    out = {k: v for k, v in buffer.items() if k != "instruction"}
    out["obs"] = {"obs": buffer["obs"], "instruction": buffer["instruction"]}
    out["next_obs"] = {"obs": buffer["next_obs"], "instruction": buffer["instruction"]}
    return out


def network_q_fn(model, inputs_fn: Callable):
    """q_fn(params, obs) of a (condition, goal) network on Q-function observations:
    inputs_fn(obs, instruction) -> (conditions (B, H, W, C), goals (B, G)) is the world's."""
    def q_fn(params, obs):
        return model.apply({"params": params}, *inputs_fn(obs["obs"], obs["instruction"]))
    return q_fn


def cql_loss(q_fn, params, target_params, batch, gamma: float, alpha: float):
    """(loss, metrics) of a batch {obs, action, reward, next_obs, terminal}.

    q_fn(params, obs) -> Q-values (B, A) for any observation pytree. The double-DQN target
    uses the online network's argmax at s' and the target network's value of it (no gradient
    through the target); the TD error is Huber; the conservative term is
    alpha * mean(logsumexp_a Q(s, a) - Q(s, a_data)).
    """
    q = q_fn(params, batch["obs"])
    action = batch["action"].astype(jnp.int32)
    q_data = jnp.take_along_axis(q, action[:, None], axis=-1)[:, 0]
    best_next = jnp.argmax(q_fn(params, batch["next_obs"]), axis=-1)
    q_next = jnp.take_along_axis(q_fn(target_params, batch["next_obs"]), best_next[:, None],
                                 axis=-1)[:, 0]
    not_terminal = 1.0 - batch["terminal"].astype(jnp.float32)
    target = jax.lax.stop_gradient(batch["reward"] + gamma * not_terminal * q_next)
    td = optax.huber_loss(q_data, target).mean()
    conservative = jnp.mean(jax.nn.logsumexp(q, axis=-1) - q_data)
    loss = td + alpha * conservative
    return loss, {"td": td, "conservative": conservative, "q_data": q_data.mean()}


def make_cql_step(q_fn, optimizer, batch_size: int, gamma: float, alpha: float, tau: float):
    """step(state, key, buffer) -> (state, metrics): a uniformly drawn minibatch, one Adam
    step on cql_loss, then target <- (1 - tau) target + tau params (state.ema_params holds the
    target network)."""

    def step(state: TrainState, key, buffer):
        n = jax.tree.leaves(buffer)[0].shape[0]
        idx = jax.random.randint(key, (batch_size,), 0, n)
        batch = jax.tree.map(lambda x: x[idx], buffer)
        (loss, metrics), grads = jax.value_and_grad(cql_loss, argnums=1, has_aux=True)(
            q_fn, state.params, state.ema_params, batch, gamma, alpha)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        target = jax.tree.map(lambda t, p: (1.0 - tau) * t + tau * p, state.ema_params, params)
        return (TrainState(params=params, ema_params=target, opt_state=opt_state,
                           step=state.step + 1), {"loss": loss, **metrics})

    return step


BUFFER_STREAM = 0x0C01
"""The buffer of a run is collect_buffer(fold_in(PRNGKey(seed), BUFFER_STREAM), ...)."""


def train_cql(out_dir: str, worlds: Sequence[tuple[Collector, int]], inputs_fn: Callable,
              input_shapes: Mapping[str, tuple], config: CQLTrainConfig = CQLTrainConfig(),
              net: nets.ConvNetConfig = nets.ConvNetConfig(), *, data: Mapping | None = None,
              progress: bool = True, buffer=None):
    """Collects the buffer (a pure function of config.seed: rebuilt identically on resume;
    not collected when the run is finished) and trains CQL into out_dir (resuming). Returns
    diffplan.train.FitResult.

    worlds, inputs_fn: see collect_buffer and network_q_fn. input_shapes: {"condition":
    (1, H, W, C), "goal": (1, G)}. data: the world's description of the buffer's worlds,
    stored in the run's train config. buffer: an already collected buffer (collect_buffer's)."""
    model = nets.GoalConvNet(net)
    optimizer = optax.adam(config.lr)
    metadata = run_metadata(model, net, nets.config_dict(config, data), dict(input_shapes),
                            {"baseline": "cql"})
    finished = (ckpt.latest_step(out_dir) or 0) >= config.steps
    if buffer is None and not finished:
        buffer = collect_buffer(jax.random.fold_in(jax.random.PRNGKey(config.seed),
                                                   BUFFER_STREAM), worlds, config)
    step = make_cql_step(network_q_fn(model, inputs_fn), optimizer, config.batch_size,
                         config.gamma, config.alpha, config.tau)
    return fit(step, lambda: nets.init_state(model, optimizer, config.seed, input_shapes),
               steps=config.steps, seed=config.seed, out_dir=out_dir, metadata=metadata,
               data=None if buffer is None else as_q_batch(buffer),
               checkpoint_every=config.checkpoint_every, log_every=config.log_every,
               progress=progress, desc="CQL")
