"""The trained baselines as policies for :func:`diffplan.baselines.rollout.policy_rollout`:
shipping (training run -> small evaluation checkpoint) and loading.

What is specific to a world (the goal vector of an instruction, the DD-style planner's frame
and plan) comes as a :class:`PolicyWorld` (the grid world's is
``envs.gridworld.baselines.POLICY_WORLD``). The networks are built from the config classes of
this package, never from a class that a checkpoint's metadata names.

Layout of a shipped baseline (``checkpoints/baselines/<name>/``): ``bc/`` and ``cql/`` are
evaluation checkpoints (``diffplan.checkpoint``: the trained network's parameters -- for CQL the
online Q-network, not the target -- and the run's metadata); ``dd/diffusion/`` holds the
diffusion model's EMA parameters and ``dd/inverse_dynamics/`` the inverse dynamics'.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from diffplan import checkpoint as ckpt
from diffplan.baselines import dd, nets

__all__ = ["BASELINES", "METHOD_NAMES", "PolicyWorld", "LoadedPolicy", "load_policy",
           "export_params"]

BASELINES = ("bc", "cql", "dd")
METHOD_NAMES = {"bc": "BC", "cql": "CQL", "dd": "DD-style"}
DD_PARTS = ("diffusion", "inverse_dynamics")


@dataclasses.dataclass(frozen=True)
class PolicyWorld:
    """What the trained baselines need of a world to act in it (hashable: module-level
    functions). goal_fn(tokens (B, L)) -> goal vectors float32 (B, G); goal_dim: the width
    of the network's goal input (G, or what ``decide`` extends the goal vector to); BC's and
    CQL's action: the argmax of each of ``heads`` equal parts of the network's outputs, int32
    (B,) (heads 1) or (B, heads), mapped to the world's actions by action_fn (None: the
    indices are the actions), or decide's (``nets.greedy_act``: an action chosen in several
    greedy decisions); observe(state) -> what the policy sees of one state (None: the task's
    condition; e.g. block poses for a planner over block states); for the DD-style planner
    frame_fn(condition (H, W, C)) -> frame (cells,) and, for its plan metrics,
    plan_fn(trajectory (cells, horizon), condition) -> plan (H, W, plan_channels) (None: no
    plan)."""

    goal_fn: Callable
    goal_dim: int
    heads: int = 1
    action_fn: Optional[Callable] = None
    frame_fn: Optional[Callable] = None
    plan_fn: Optional[Callable] = None
    plan_channels: Optional[int] = None
    decide: Optional[Callable] = None
    observe: Optional[Callable] = None


@dataclasses.dataclass(frozen=True)
class LoadedPolicy:
    """What policy_rollout needs of a policy (a trained baseline or a world's reference agent):
    act_fn, params, calls_per_move, plan_channels (None: no plan), observe (None: the task's
    condition; see policy_rollout), and the row's method name."""

    method: str
    act_fn: Callable
    params: Any
    calls_per_move: int = 0
    plan_channels: int | None = None
    observe: Optional[Callable] = None


def export_params(train_dir: str, out_dir: str, *, ema: bool = False) -> str:
    """Writes the latest training checkpoint of ``train_dir`` as an evaluation checkpoint in
    ``out_dir`` (replacing what is there): its params (ema=False) or EMA params, float32, with
    the run's metadata. Returns the step directory."""
    if ema:
        return ckpt.export_eval_checkpoint(train_dir, out_dir, overwrite=True)
    raw, metadata = ckpt.load_checkpoint(train_dir)
    if "train_state" not in raw:
        raise ValueError(f"{train_dir!r} holds no training state to export params from")
    params = jax.tree.map(lambda x: np.asarray(x, np.float32), raw["train_state"]["params"])
    for s in ckpt.all_steps(out_dir):
        shutil.rmtree(os.path.join(out_dir, str(s)))
    meta = {k: v for k, v in metadata.items() if k not in ("kind", "format", "step")}
    meta["exported_from"] = {"directory": os.path.abspath(train_dir), "step": metadata["step"],
                             "params": "params"}
    return ckpt.save_checkpoint(out_dir, metadata["step"], params, meta, max_to_keep=None)


def _load_checked(directory: str, model, example_args) -> tuple[Any, dict]:
    """Params and metadata of an evaluation checkpoint, checked against the model's shapes."""
    params, metadata = ckpt.load_params_for_eval(directory)
    expected = jax.eval_shape(lambda: model.init(jax.random.PRNGKey(0), *example_args))
    problems = ckpt.compare_param_shapes(params, expected["params"])
    if problems:
        raise ValueError(f"checkpoint {directory!r} does not fit its model: "
                         + "; ".join(problems))
    return params, metadata


def load_policy(name: str, directory: str, world: PolicyWorld, *, dd_num_steps: int = 10,
                dd_guidance: float = 1.0) -> LoadedPolicy:
    """The shipped baseline ``name`` (one of BASELINES) from its directory, acting in world.
    Raises FileNotFoundError when there is no checkpoint, ValueError when it does not fit.

    The networks' shapes are checked against an init on zeros of the checkpoint's condition
    shape and the world's goal vector; the ``input_shapes["tokens"]`` that checkpoints written
    before the goal vector left the networks carry (the instruction's shape) is not used."""
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}; expected one of {BASELINES}")
    goal = jnp.zeros((1, world.goal_dim), jnp.float32)
    if name in ("bc", "cql"):
        meta = ckpt.read_metadata(directory)
        model = nets.GoalConvNet(nets.ConvNetConfig.from_dict(meta["model_config"]))
        condition = jnp.zeros(meta["input_shapes"]["condition"], jnp.float32)
        params, _ = _load_checked(directory, model, (condition, goal))
        return LoadedPolicy(METHOD_NAMES[name], nets.greedy_act(
            model, world.goal_fn, world.heads, world.action_fn, world.decide), params,
            observe=world.observe)
    if world.frame_fn is None:
        raise ValueError("the DD-style planner needs the world's frame_fn; this world gives none")
    diffusion_dir, id_dir = (os.path.join(directory, part) for part in DD_PARTS)
    meta = ckpt.read_metadata(diffusion_dir)
    model_config = dd.DDConfig.from_dict(meta["model_config"])
    x = jnp.zeros((1, 1, model_config.cells, model_config.horizon), jnp.float32)
    diffusion_params, _ = _load_checked(diffusion_dir, dd.DDModel(model_config),
                                        (x, jnp.zeros((1,), jnp.int32), goal))
    train_config = meta["train_config"]
    den = dd.denoiser(diffusion_params, model_config, train_config["prediction"],
                      int(train_config["num_train_timesteps"]))
    id_config = dd.IDConfig.from_dict(ckpt.read_metadata(id_dir)["model_config"])
    z = jnp.zeros((1, model_config.cells), jnp.float32)
    id_params, _ = _load_checked(id_dir, dd.InverseDynamics(id_config), (z, z))
    policy = dd.DDPolicy(model_config, world.goal_fn, world.frame_fn, world.plan_fn,
                         id_config=id_config, num_steps=dd_num_steps, guidance=dd_guidance,
                         heads=world.heads, action_fn=world.action_fn)
    return LoadedPolicy(METHOD_NAMES[name], policy,
                        {"denoiser": den, "inverse_dynamics": id_params},
                        calls_per_move=policy.calls_per_move,
                        plan_channels=None if world.plan_fn is None else world.plan_channels,
                        observe=world.observe)
