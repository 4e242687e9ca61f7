"""Conservative Q-learning (the paper's CQL baseline, appendix), offline, on top of double DQN.

Data: a replay buffer of ``buffer_size`` (300k) transitions collected once, before training,
by an epsilon-greedy behaviour around the expert: with probability 1 - epsilon the expert's
move (the first move of a shortest path on the true grid through the reference, while it is
still due, to the target), else a uniformly random move; epsilon is annealed linearly from 1
to 0.01 over the first 10k frames (env steps, counted over all parallel collectors of a
setting) and then held. Episodes that end are replaced by fresh ones of the training key
stream. The settings are collected in the planner's mixture proportions.

Reward (appendix: "the distance from the agent to the goal", negated): after each move,
minus the Euclidean length, in cells / grid size, of the instructed route that remains: agent
to target, or in P-MO2G, while the reference has not been stood on, agent to reference plus
reference to target (so stepping on the reference is not punished by a jump of the distance).
An episode terminates on the target (no bootstrap); running out of moves is a truncation.

Loss: the double-DQN Huber TD error, target ``r + gamma (1 - terminal) Q_target(s',
argmax_a Q(s', a))``, plus ``alpha * E[logsumexp_a Q(s, a) - Q(s, a_data)]`` (CQL(H), Kumar et
al. 2020); Adam lr 1e-3, gamma 0.99, the target network soft-updated with tau 0.001 after every
step (appendix). The network is the appendix's conv net with 4 Q-value outputs; it acts
greedily.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import optax

from diffplan import checkpoint as ckpt
from diffplan.baselines import common
from diffplan.baselines.bc import init_state, input_shapes
from diffplan.baselines.loop import fit, run_metadata
from diffplan.train import TrainState
from envs.gridworld import bfs, env
from envs.gridworld.config import make_config
from envs.gridworld.episode import OBSTACLE_CELL, generate
from envs.gridworld.task import condition_from_observation
from envs.gridworld.training import training_episode_keys

__all__ = ["CQLTrainConfig", "epsilon_at", "expert_move", "route_reward", "collect_buffer",
           "cql_loss", "make_cql_step", "train_cql", "act_fn"]


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
    mixture: tuple = common.TRAINING_MIXTURE
    checkpoint_every: int = 2000
    log_every: int = 100


def epsilon_at(frame, start: float = 1.0, end: float = 0.01, frames: int = 10_000):
    """Linear annealing from start to end over ``frames`` frames, then end."""
    frac = jnp.clip(jnp.asarray(frame, jnp.float32) / frames, 0.0, 1.0)
    return start + (end - start) * frac


def _sub_goal(state: env.State, config):
    """The cell the instruction asks for next: the reference until stood on, then the
    target."""
    if not config.has_reference:
        return state.target
    return jnp.where(state.reached_reference, state.target, state.reference)


def expert_move(state: env.State, config):
    """int32 (): the first move of a shortest path on the true grid to the sub-goal."""
    passable = state.grid != OBSTACLE_CELL
    field = bfs.cost_to_go(passable, _sub_goal(state, config))
    return bfs.best_move(field, passable, state.agent)


def route_reward(state: env.State, config):
    """float32 (): minus the Euclidean length (cells / size) of the route still to go."""
    def dist(a, b):
        return jnp.sqrt(jnp.sum(jnp.square((a - b).astype(jnp.float32))))

    remaining = dist(state.agent, state.target)
    if config.has_reference:
        via = dist(state.agent, state.reference) + dist(state.reference, state.target)
        remaining = jnp.where(state.reached_reference, remaining, via)
    return -remaining / config.size


def _compact(obs: env.Observation):
    """The observation stored in the buffer: cells int8, visited bool, agent int8."""
    return {"cells": obs.cells, "visited": obs.visited, "agent": obs.agent.astype(jnp.int8)}


def expand(compact) -> jax.Array:
    """float32 (..., H, W, C) condition channels of stored observations."""
    obs = env.Observation(cells=compact["cells"], visited=compact["visited"],
                          agent=compact["agent"].astype(jnp.int32))
    return condition_from_observation(obs)


def _collect_setting(key, config, collectors: int, moves: int, cfg: CQLTrainConfig):
    """Transitions (moves, collectors, ...) of one setting (its own epsilon schedule: frame
    f = move * collectors + collector)."""
    v_generate = jax.vmap(lambda k: generate(k, config))
    v_reset = jax.vmap(lambda e: env.reset(e, config))
    v_step = jax.vmap(lambda s, a: env.step(s, a, config))
    v_observe = jax.vmap(lambda s: _compact(env.observe(s, config)))
    episodes = v_generate(training_episode_keys(jax.random.fold_in(key, 0), collectors))
    states = v_reset(episodes)

    def body(carry, t):
        states, tokens = carry
        k_explore, k_action, k_new = jax.random.split(jax.random.fold_in(key, t + 1), 3)
        frame = t * collectors + jnp.arange(collectors)
        eps = epsilon_at(frame, cfg.epsilon_start, cfg.epsilon_end, cfg.epsilon_frames)
        explore = jax.random.uniform(k_explore, (collectors,)) < eps
        random_moves = jax.random.randint(k_action, (collectors,), 0, 4)
        moves_ = jnp.where(explore, random_moves,
                           jax.vmap(lambda s: expert_move(s, config))(states))
        nxt = v_step(states, moves_)
        record = {"obs": v_observe(states), "next_obs": v_observe(nxt),
                  "tokens": tokens.astype(jnp.int8), "action": moves_.astype(jnp.int8),
                  "reward": jax.vmap(lambda s: route_reward(s, config))(nxt),
                  "terminal": nxt.success}
        fresh = v_generate(training_episode_keys(k_new, collectors))
        states = jax.tree.map(
            lambda a, b: jnp.where(nxt.done.reshape((-1,) + (1,) * (a.ndim - 1)), a, b),
            v_reset(fresh), nxt)
        tokens = jnp.where(nxt.done[:, None], fresh.tokens, tokens)
        return (states, tokens), record

    _, records = jax.lax.scan(body, (states, episodes.tokens), jnp.arange(moves))
    return records


_collect_jit = jax.jit(_collect_setting, static_argnums=(1, 2, 3, 4))


def collect_buffer(key, cfg: CQLTrainConfig = CQLTrainConfig()):
    """The replay buffer: a dict of arrays with a leading axis of cfg.buffer_size transitions
    (obs / next_obs compact observations, tokens int8 (L,), action int8, reward float32,
    terminal bool). Settings are collected in the mixture's proportions, collectors split
    alike (each setting anneals epsilon over its own first epsilon_frames frames); a pure
    function of key and cfg."""
    total = sum(count for _, count in cfg.mixture)
    moves = math.ceil(cfg.buffer_size / cfg.collectors)
    parts = []
    for i, (setting, count) in enumerate(cfg.mixture):
        collectors = max(1, round(cfg.collectors * count / total))
        records = _collect_jit(jax.random.fold_in(key, i), make_config(setting), collectors,
                               moves, cfg)
        parts.append(jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), records))
    buffer = jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts)
    n = jax.tree.leaves(buffer)[0].shape[0]
    if n > cfg.buffer_size:  # drop evenly spaced surplus rows so every setting keeps its share
        keep = jnp.round(jnp.linspace(0, n - 1, cfg.buffer_size)).astype(jnp.int32)
        buffer = jax.tree.map(lambda x: x[keep], buffer)
    return buffer


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


def grid_q_fn(model):
    """q_fn(params, obs) of the conv network on buffer observations {"obs": compact,
    "tokens"}."""
    def q_fn(params, obs):
        return model.apply({"params": params}, expand(obs["compact"]),
                           obs["tokens"].astype(jnp.int32))
    return q_fn


def _as_q_batch(buffer):
    """The buffer with obs / next_obs as q_fn observations (compact arrays + tokens)."""
    out = dict(buffer)
    out["obs"] = {"compact": buffer["obs"], "tokens": buffer["tokens"]}
    out["next_obs"] = {"compact": buffer["next_obs"], "tokens": buffer["tokens"]}
    del out["tokens"]
    return out


def train_cql(out_dir: str, config: CQLTrainConfig = CQLTrainConfig(),
              net: common.ConvNetConfig = common.ConvNetConfig(), progress: bool = True,
              buffer=None):
    """Collects the buffer (a pure function of config.seed: rebuilt identically on resume)
    and trains CQL into out_dir (resuming). Returns diffplan.baselines.loop.FitResult."""
    model = common.GoalConvNet(net)
    optimizer = optax.adam(config.lr)
    metadata = run_metadata(model, net, common.config_dict(config), input_shapes(),
                            {"baseline": "cql"})
    finished = (ckpt.latest_step(out_dir) or 0) >= config.steps
    if buffer is None and not finished:
        buffer = collect_buffer(jax.random.fold_in(jax.random.PRNGKey(config.seed), 0x0C01),
                                config)
    step = make_cql_step(grid_q_fn(model), optimizer, config.batch_size, config.gamma,
                         config.alpha, config.tau)
    return fit(step, lambda: init_state(model, optimizer, config.seed), steps=config.steps,
               seed=config.seed, out_dir=out_dir, metadata=metadata,
               data=None if buffer is None else _as_q_batch(buffer),
               checkpoint_every=config.checkpoint_every, log_every=config.log_every,
               progress=progress, desc="CQL")


def act_fn(net: common.ConvNetConfig = common.ConvNetConfig()):
    """The greedy policy of a CQL Q-network (for policy_rollout)."""
    return common.greedy_act(common.GoalConvNet(net))
