"""Noise schedules for the diffusion planner.

The forward process is the usual variance-preserving one,

    x_t = sqrt(alphas_cumprod[t]) * x0 + sqrt(1 - alphas_cumprod[t]) * eps,   t in [0, T),

with ``T = num_train_steps`` training timesteps. ``cosine_schedule`` reproduces diffusers'
``beta_schedule="squaredcos_cap_v2"`` (Nichol & Dhariwal's cosine schedule, computed through
``betas_for_alpha_bar``) value for value: betas are computed in float64 and stored as float32,
``alphas = 1 - betas`` and ``alphas_cumprod = cumprod(alphas)`` are then computed in float32,
as diffusers does with torch float32 tensors.

``timestep_sequence`` picks the training timesteps a sampler visits when it uses fewer
denoising steps than training timesteps.
"""

from __future__ import annotations

import math
import operator

import flax.struct
import jax.numpy as jnp
import numpy as np

__all__ = ["Schedule", "cosine_schedule", "timestep_sequence"]


@flax.struct.dataclass
class Schedule:
    """A discrete diffusion noise schedule (a pytree; ``num_train_steps`` is static).

    Attributes:
      betas: float32 (T,), the per-step noise variances beta_t.
      alphas: float32 (T,), ``1 - betas``.
      alphas_cumprod: float32 (T,), ``cumprod(alphas)`` (often written alpha-bar_t); strictly
        decreasing, in (0, 1).
      num_train_steps: the number T of training timesteps (a static Python int, not a leaf).
    """

    betas: jnp.ndarray
    alphas: jnp.ndarray
    alphas_cumprod: jnp.ndarray
    num_train_steps: int = flax.struct.field(pytree_node=False)


def _as_int(value, name: str) -> int:
    """Returns ``value`` as a Python int, or raises ValueError (bools and floats rejected)."""
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be an int, got bool {value!r}")
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an int, got {type(value).__name__} {value!r}") from None


def _alpha_bar(t: float) -> float:
    """The squaredcos_cap_v2 signal level at continuous time t in [0, 1]."""
    return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2


def cosine_schedule(num_train_steps: int, max_beta: float = 0.999) -> Schedule:
    """The cosine schedule, identical to diffusers' ``"squaredcos_cap_v2"``.

    ``beta_i = min(1 - alpha_bar((i + 1) / T) / alpha_bar(i / T), max_beta)`` for i in [0, T),
    with ``alpha_bar(t) = cos((t + 0.008) / 1.008 * pi / 2) ** 2``.

    Args:
      num_train_steps: T >= 1, the number of training timesteps (a Python int).
      max_beta: the cap on every beta, 0 < max_beta < 1 (diffusers' default 0.999).

    Returns:
      A ``Schedule`` with float32 arrays of shape (T,).

    Raises:
      ValueError: if T is not an int >= 1 or max_beta is not in (0, 1).
    """
    T = _as_int(num_train_steps, "num_train_steps")
    if T < 1:
        raise ValueError(f"num_train_steps must be >= 1, got {T}")
    if isinstance(max_beta, (bool, np.bool_)):
        raise ValueError(f"max_beta must be a float in (0, 1), got {max_beta!r}")
    try:
        max_beta_f = float(max_beta)
    except (TypeError, ValueError):
        raise ValueError(f"max_beta must be a float in (0, 1), got {max_beta!r}") from None
    if not (0.0 < max_beta_f < 1.0):  # also rejects NaN
        raise ValueError(f"max_beta must be in (0, 1), got {max_beta!r}")

    betas64 = [min(1.0 - _alpha_bar((i + 1) / T) / _alpha_bar(i / T), max_beta_f) for i in range(T)]
    betas = np.asarray(betas64, dtype=np.float64).astype(np.float32)
    alphas = (np.float32(1.0) - betas).astype(np.float32)
    alphas_cumprod = np.cumprod(alphas, dtype=np.float32)
    return Schedule(
        betas=jnp.asarray(betas),
        alphas=jnp.asarray(alphas),
        alphas_cumprod=jnp.asarray(alphas_cumprod),
        num_train_steps=T,
    )


def timestep_sequence(num_train_steps: int, num_steps: int) -> np.ndarray:
    """The training timesteps visited by a ``num_steps``-step sampler, noisiest first.

    Spacing is diffusers' ``timestep_spacing="trailing"`` (Lin et al. 2024, "Common Diffusion
    Noise Schedules and Sample Steps are Flawed"), computed with exact integer arithmetic:

        t_k = floor((num_steps - k) * T / num_steps) - 1,   k = 0 .. num_steps - 1.

    So the sequence is evenly spaced (gaps of T / num_steps, rounded), strictly decreasing,
    always starts at the noisiest timestep ``T - 1`` (so sampling starts from pure noise, also
    for ``num_steps = 1``), and equals ``T-1, T-2, ..., 0`` when ``num_steps == T``. (diffusers'
    "leading" spacing instead starts at ``T - T // num_steps`` and misses the noisiest part of
    the schedule when ``num_steps`` is small.) The step after the last one lands on x0:
    the sampler uses ``alphas_cumprod_prev = 1`` there, like diffusers' DDIM with
    ``set_alpha_to_one=True``.

    Args:
      num_train_steps: T >= 1.
      num_steps: the number of sampling steps, 1 <= num_steps <= T.

    Returns:
      np.ndarray int32 of shape (num_steps,), strictly decreasing, ``[0] == T - 1``.

    Raises:
      ValueError: if T < 1 or num_steps is not in [1, T] (or either is not an int).
    """
    T = _as_int(num_train_steps, "num_train_steps")
    n = _as_int(num_steps, "num_steps")
    if T < 1:
        raise ValueError(f"num_train_steps must be >= 1, got {T}")
    if not 1 <= n <= T:
        raise ValueError(f"num_steps must be in [1, num_train_steps={T}], got {n}")
    k = np.arange(n, dtype=np.int64)
    return ((n - k) * T // n - 1).astype(np.int32)
