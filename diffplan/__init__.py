"""diffplan: Planning as In-Painting (Yang et al., CVPR 2024) in JAX/Flax.

Public entry points (DESIGN.md, contract 3): ``diffplan.sample`` and ``diffplan.cosine_schedule``.
"""
from diffplan.sampler import denoiser_calls, sample
from diffplan.schedule import Schedule, cosine_schedule, timestep_sequence

__all__ = ["sample", "cosine_schedule", "Schedule", "timestep_sequence", "denoiser_calls"]
