"""What the BabyAI rows report, measured in minigrid itself.

The jitted port plans and acts (``envs.babyai.env``); :class:`ActionLog` records every action
an episode executed. :func:`replay` then resets minigrid with each episode's seed and steps
those actions in it: minigrid's own reward, termination and truncation are what a row reports
(success: reward > 0), and :func:`mismatches` counts the episodes where the port and minigrid
disagree (outcome, step of the end, reward, final pose), which must be none. The BabyAI bot
(``minigrid.utils.baby_ai_bot.BabyAIBot``) runs in minigrid directly (:func:`bot_episodes`).
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.babyai import episode as E
from envs.babyai import env

NO_ACTION = -1
"""The action log's padding after an episode's last action."""


@struct.dataclass
class Logged:
    """A task state and the actions executed so far: actions int8 (max_steps,), action t of
    the episode at index t, NO_ACTION after the last."""

    state: env.State
    actions: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class ActionLog:
    """A BabyAI task (``BabyAITask``) whose states also log every action its ``step``
    executes; every other function is the task's, on the state it wraps. Hashable (a static
    argument of the rollouts)."""

    task: object

    def __getattr__(self, name):  # height, width, max_steps, tokens, new_information, ...
        if name == "task":
            raise AttributeError(name)
        attr = getattr(self.task, name)
        if name in ("condition", "psi", "done", "position", "at_goal_estimate",
                    "plan_refuted", "plan_cost"):
            return lambda logged, *rest: attr(logged.state, *rest)
        return attr

    def reset(self, episode) -> Logged:
        return Logged(self.task.reset(episode),
                      jnp.full((self.task.max_steps,), NO_ACTION, jnp.int8))

    def step(self, logged: Logged, action) -> Logged:
        """The task's step; the action is logged where the episode was still running."""
        state = logged.state
        at = jnp.where(state.done, self.task.max_steps, state.step_count)
        return Logged(self.task.step(state, action),
                      logged.actions.at[at].set(jnp.asarray(action, jnp.int8), mode="drop"))


def port_outcome(final: Logged) -> dict:
    """What the port says of episodes (numpy, leading axis N) at their end: actions, steps,
    reward, terminated, truncated, pos (row, col), direction."""
    s = jax.device_get(final.state)
    return {"actions": np.asarray(jax.device_get(final.actions)),
            "steps": np.asarray(s.step_count), "reward": np.asarray(s.reward, np.float64),
            "terminated": np.asarray(s.terminated), "truncated": np.asarray(s.truncated),
            "pos": np.asarray(s.pos), "direction": np.asarray(s.direction)}


def _outcome(n: int) -> dict:
    return {"steps": np.zeros(n, np.int32), "reward": np.zeros(n), "terminated":
            np.zeros(n, bool), "truncated": np.zeros(n, bool), "pos": np.zeros((n, 2), np.int32),
            "direction": np.zeros(n, np.int32)}


def _record(out: dict, i: int, minigrid_env, steps: int, reward, terminated, truncated):
    x, y = (int(v) for v in minigrid_env.agent_pos)
    out["steps"][i], out["reward"][i] = steps, float(reward)
    out["terminated"][i], out["truncated"][i] = bool(terminated), bool(truncated)
    out["pos"][i], out["direction"][i] = (y, x), int(minigrid_env.agent_dir)


def replay(config, seed_list, actions, minigrid_env=None,
           tick: Optional[Callable[[], None]] = None) -> dict:
    """Each episode's logged actions (int (N, T), NO_ACTION-padded) stepped in minigrid reset
    with its seed (``seed_list`` (N,)), until minigrid ends the episode or the log does: the
    keys of :func:`port_outcome` but the actions, as minigrid saw them. ``tick()`` after each
    episode (a progress bar)."""
    minigrid_env = E.make_env(config) if minigrid_env is None else minigrid_env
    actions = np.asarray(actions)
    out = _outcome(len(seed_list))
    for i, seed in enumerate(seed_list):
        E.reset_quietly(minigrid_env, seed)
        steps, reward, terminated, truncated = 0, 0.0, False, False
        for a in actions[i]:
            if a == NO_ACTION or terminated or truncated:
                break
            _, reward, terminated, truncated, _ = minigrid_env.step(int(a))
            steps += 1
        _record(out, i, minigrid_env, steps, reward, terminated, truncated)
        if tick is not None:
            tick()
    return out


def mismatches(port: dict, minigrid: dict, atol: float = 1e-6) -> np.ndarray:
    """bool (N,): the episodes whose end differs between the port and minigrid (the step
    count, reward, terminated, truncated, the agent's cell or heading)."""
    same = ((port["steps"] == minigrid["steps"])
            & (np.abs(port["reward"] - minigrid["reward"]) <= atol)
            & (port["terminated"] == minigrid["terminated"])
            & (port["truncated"] == minigrid["truncated"])
            & np.all(port["pos"] == minigrid["pos"], axis=-1)
            & (port["direction"] == minigrid["direction"]))
    return ~same


def bot_episodes(config, seed_list, minigrid_env=None,
                 tick: Optional[Callable[[], None]] = None) -> dict:
    """The BabyAI bot (``minigrid.utils.baby_ai_bot.BabyAIBot``) on each seed's episode in
    minigrid, until the episode ends: the keys of :func:`replay`'s result, and "errors" (N,)
    bool where the bot raised (its episode ends there, unsuccessful)."""
    from minigrid.utils.baby_ai_bot import BabyAIBot

    minigrid_env = E.make_env(config) if minigrid_env is None else minigrid_env
    out = _outcome(len(seed_list))
    out["errors"] = np.zeros(len(seed_list), bool)
    for i, seed in enumerate(seed_list):
        E.reset_quietly(minigrid_env, seed)
        bot = BabyAIBot(minigrid_env)
        steps, reward, terminated, truncated = 0, 0.0, False, False
        while not (terminated or truncated):
            try:
                action = bot.replan()
            except Exception:  # noqa: BLE001  the bot's own failure ends its episode
                out["errors"][i] = True
                break
            _, reward, terminated, truncated, _ = minigrid_env.step(action)
            steps += 1
        _record(out, i, minigrid_env, steps, reward, terminated, truncated)
        if tick is not None:
            tick()
    return out


def success_metrics(outcome: dict) -> dict:
    """SR (% of episodes with minigrid's reward > 0), mean_reward (minigrid's return,
    0 for a failure), mean_steps (actions per episode) and successful_steps (per success)."""
    success = outcome["reward"] > 0
    return {"episodes": int(len(success)), "successes": int(success.sum()),
            "SR": 100.0 * float(success.mean()) if len(success) else 0.0,
            "mean_reward": float(np.mean(outcome["reward"])) if len(success) else 0.0,
            "mean_steps": float(np.mean(outcome["steps"])) if len(success) else 0.0,
            "successful_steps": (float(np.mean(outcome["steps"][success]))
                                 if success.any() else None)}
