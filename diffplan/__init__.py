"""diffplan: Planning as In-Painting (Yang et al., CVPR 2024) in JAX/Flax.

Public entry points (DESIGN.md, contracts 3 and 5):
  ``diffplan.sample``, ``diffplan.cosine_schedule``: the in-painting sampler and its schedule;
  ``diffplan.load_denoiser(dir)``: a trained denoiser (network, params, schedule, target);
  the network is a registered class (``diffplan.models``), never one imported by the name a
  checkpoint stores (docs/checkpoints.md);
  ``diffplan.Planner(denoiser, diffplan.PlannerConfig(...))``: pure ``init`` / ``plan`` /
  ``plan_batch`` steps; ``diffplan.rollout``: Algorithm 1 over a batch of episodes of a
  ``diffplan.Task``.
"""
from diffplan.denoiser import LoadedDenoiser, load_denoiser
from diffplan.baselines import goal as _goal  # noqa: F401  registers GoalClassifier (a Denoiser)
from diffplan.planner import MODES, Planner, PlannerConfig, PlannerState
from diffplan.rollouts import Rollout, StreamRollout, rollout, rollout_stream
from diffplan.sampler import denoiser_calls, sample
from diffplan.schedule import Schedule, cosine_schedule, timestep_sequence
from diffplan.task import Task

__all__ = ["sample", "cosine_schedule", "Schedule", "timestep_sequence", "denoiser_calls",
           "LoadedDenoiser", "load_denoiser", "MODES", "Planner", "PlannerConfig",
           "PlannerState", "Rollout", "StreamRollout", "rollout", "rollout_stream", "Task"]
