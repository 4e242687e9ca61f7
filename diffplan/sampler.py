"""Generalised DDIM sampling with in-painting (DESIGN contract 3).

``sample`` draws x0 from a noise-prediction model ``denoise_fn(x_t, t) -> eps`` with the
generalised DDIM update of Song et al. (2021), ``eta = 0`` being DDIM and ``eta = 1``
DDPM-like ancestral sampling, while holding the entries marked by ``known_mask`` fixed at
``x_known`` (in-painting: the planner's condition channels). It can also resume from a partly
noised plan (warm start), which is how re-plans are made cheap.

One step from training timestep t to the next visited timestep (see
``diffplan.schedule.timestep_sequence``), with ab = alphas_cumprod:

    x0_hat  = (x_t - sqrt(1 - ab_t) * eps) / sqrt(ab_t)        optionally clipped to
              [-clip_range, clip_range]; then eps <- (x_t - sqrt(ab_t) x0_hat) / sqrt(1 - ab_t)
    sigma   = eta * sqrt((1 - ab_prev) / (1 - ab_t)) * sqrt(1 - ab_t / ab_prev)
    x_prev  = sqrt(ab_prev) * x0_hat + sqrt(1 - ab_prev - sigma^2) * eps + sigma * z

with ab_prev = 1 after the last step (so the last step returns x0_hat and adds no noise), and
known entries reset to x_known after every step. The loop is a single ``lax.scan`` with a
static trip count; everything is a pure function of its array arguments and the PRNG key, so
``sample`` works under ``jit``, ``vmap`` and inside a caller's ``lax.scan``.
"""

from __future__ import annotations

from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .schedule import Schedule, _as_int, timestep_sequence

__all__ = ["sample", "denoiser_calls"]

DenoiseFn = Callable[[jnp.ndarray, jnp.ndarray], jnp.ndarray]


def _check_start_step(num_steps: int, start_step) -> int:
    n = _as_int(num_steps, "num_steps")
    if n < 1:
        raise ValueError(f"num_steps must be >= 1, got {n}")
    if start_step is None:
        return 0
    s = _as_int(start_step, "start_step")
    if not 0 <= s < n:
        raise ValueError(f"start_step must be in [0, num_steps={n}), got {s}")
    return s


def denoiser_calls(num_steps: int, start_step: Optional[int] = None) -> int:
    """The number of ``denoise_fn`` evaluations ``sample`` makes: ``num_steps - start_step``.

    Args:
      num_steps: the number of sampling steps (>= 1).
      start_step: the number of leading steps a warm start skips (None means 0, a cold start),
        0 <= start_step < num_steps.

    Raises:
      ValueError: on an out-of-range argument.
    """
    n = _as_int(num_steps, "num_steps")
    return n - _check_start_step(n, start_step)


def _is_concrete(value) -> bool:
    return not isinstance(value, jax.core.Tracer)


def _check_nonneg_scalar(value, name: str, strictly_positive: bool = False) -> None:
    """Validates a scalar hyper-parameter when it is concrete (it may be traced under jit)."""
    if not _is_concrete(value):
        return
    arr = np.asarray(value)
    if arr.shape != () or not np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_:
        raise ValueError(f"{name} must be a real scalar, got {value!r}")
    v = float(arr)
    if not np.isfinite(v) or v < 0 or (strictly_positive and v == 0):
        bound = "> 0" if strictly_positive else ">= 0"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r}")


def sample(
    denoise_fn: DenoiseFn,
    schedule: Schedule,
    key: jax.Array,
    x_known: jnp.ndarray,
    known_mask: jnp.ndarray,
    *,
    num_steps: int,
    eta: float = 0.0,
    x_init: Optional[jnp.ndarray] = None,
    start_step: Optional[int] = None,
    clip_x0: bool = True,
    clip_range: float = 1.0,
) -> jnp.ndarray:
    """Samples x0 by (generalised) DDIM with the ``known_mask`` entries held at ``x_known``.

    Args:
      denoise_fn: ``denoise_fn(x_t, t) -> eps``; x_t float32 of x_known's shape (B, ...),
        t int32 (B,) (all entries equal: the current training timestep); eps must have
        x_t's full shape (its values at known entries are ignored).
      schedule: a ``diffplan.schedule.Schedule`` (e.g. ``cosine_schedule(1000)``).
      key: a PRNG key (raw uint32 (2,) or typed); the same key gives the same output.
      x_known: float32 (B, ...), the values of the known entries (others are ignored).
      known_mask: bool (or 0/1) array that broadcasts to x_known's shape, e.g. (1, 1, 1, C + G)
        for "condition channels known"; True marks entries held fixed. They are set at
        initialisation and after every step, so they equal x_known bit-exactly in the output.
      num_steps: static int in [1, schedule.num_train_steps], the number of sampling steps;
        visited timesteps are ``timestep_sequence(T, num_steps)`` (trailing spacing).
      eta: >= 0 (may be a traced scalar): 0 is deterministic DDIM, 1 DDPM-like. The
        direction coefficient sqrt(1 - ab_prev - sigma^2) is clamped at 0 (matters for eta > 1).
      x_init: optional float32 array of x_known's shape, a previous plan to resume from
        (warm start). Requires ``start_step``.
      start_step: static int in [0, num_steps): with x_init, the number of the num_steps steps
        that are skipped. x starts as ``sqrt(ab) * x_init + sqrt(1 - ab) * noise`` with ab at
        the timestep of step ``start_step`` and ``num_steps - start_step`` denoiser calls are
        made (see ``denoiser_calls``). start_step=0 re-noises to the noisiest timestep.
      clip_x0: static bool; clip the predicted x0 to [-clip_range, clip_range] (and re-derive
        eps from the clipped x0 for the direction term, as diffusers' DDIM does with
        ``use_clipped_model_output=True``).
      clip_range: > 0 (may be traced), the clipping bound.

    Returns:
      float32 array of x_known's shape: the sample x0.

    Raises:
      ValueError: on bad arguments (num_steps out of range, start_step without x_init or the
        reverse, shapes that do not match, negative eta, non-positive clip_range, a
        denoise_fn output of the wrong shape).
    """
    if not isinstance(schedule, Schedule):
        raise ValueError(f"schedule must be a diffplan.schedule.Schedule, got {type(schedule)}")
    if not isinstance(clip_x0, (bool, np.bool_)):
        raise ValueError(f"clip_x0 must be a Python bool (static), got {clip_x0!r}")
    T = schedule.num_train_steps
    timesteps = timestep_sequence(T, num_steps)  # validates num_steps in [1, T]
    n = int(timesteps.shape[0])
    if (x_init is None) != (start_step is None):
        raise ValueError(
            "x_init and start_step must be given together (warm start) or both omitted; got "
            f"x_init={'None' if x_init is None else 'array'}, start_step={start_step!r}"
        )
    s0 = _check_start_step(n, start_step)
    _check_nonneg_scalar(eta, "eta")
    _check_nonneg_scalar(clip_range, "clip_range", strictly_positive=True)

    x_known = jnp.asarray(x_known, dtype=jnp.float32)
    shape = x_known.shape
    if x_known.ndim < 1:
        raise ValueError("x_known must have a leading batch axis (ndim >= 1), got a scalar")
    known_mask = jnp.asarray(known_mask)
    try:
        bshape = np.broadcast_shapes(known_mask.shape, shape)
    except ValueError:
        bshape = None
    if bshape != shape:
        raise ValueError(
            f"known_mask of shape {known_mask.shape} does not broadcast to x_known's {shape}"
        )
    mask = jnp.broadcast_to(known_mask.astype(bool), shape)
    ab_all = jnp.asarray(schedule.alphas_cumprod, dtype=jnp.float32)
    if ab_all.shape != (T,):
        raise ValueError(
            f"schedule.alphas_cumprod has shape {ab_all.shape}, expected ({T},) "
            "(num_train_steps)"
        )
    if x_init is not None:
        x_init = jnp.asarray(x_init, dtype=jnp.float32)
        if x_init.shape != shape:
            raise ValueError(f"x_init has shape {x_init.shape}, expected x_known's {shape}")

    # Static step tables: the timesteps still to visit and the cumulative alphas around them.
    t_run = timesteps[s0:]  # (m,) with m = n - s0
    m = int(t_run.shape[0])
    ab_t = ab_all[jnp.asarray(t_run)]  # (m,)
    ab_prev = jnp.concatenate([ab_t[1:], jnp.ones((1,), jnp.float32)])  # (m,), 1 after last

    key_init, key_steps = jax.random.split(key)
    z0 = jax.random.normal(key_init, shape, jnp.float32)
    if x_init is None:
        x = z0
    else:
        a0 = ab_t[0]
        x = jnp.sqrt(a0) * x_init + jnp.sqrt(1.0 - a0) * z0
    x = jnp.where(mask, x_known, x)

    add_noise = not (_is_concrete(eta) and float(np.asarray(eta)) == 0.0)
    eta_f = jnp.asarray(eta, jnp.float32)
    clip_f = jnp.asarray(clip_range, jnp.float32)
    batch = shape[0]

    def step(x, inputs):
        t, a_t, a_prev, k = inputs
        eps = denoise_fn(x, jnp.full((batch,), t, dtype=jnp.int32))
        if jnp.shape(eps) != shape:
            raise ValueError(f"denoise_fn returned shape {jnp.shape(eps)}, expected {shape}")
        eps = jnp.asarray(eps).astype(jnp.float32)
        sqrt_a = jnp.sqrt(a_t)
        sqrt_1ma = jnp.sqrt(1.0 - a_t)
        x0 = (x - sqrt_1ma * eps) / sqrt_a
        if clip_x0:
            x0 = jnp.clip(x0, -clip_f, clip_f)
            eps = (x - sqrt_a * x0) / sqrt_1ma
        sigma = eta_f * jnp.sqrt((1.0 - a_prev) / (1.0 - a_t)) * jnp.sqrt(1.0 - a_t / a_prev)
        dir_coef = jnp.sqrt(jnp.maximum(1.0 - a_prev - sigma**2, 0.0))
        x_prev = jnp.sqrt(a_prev) * x0 + dir_coef * eps
        if add_noise:
            x_prev = x_prev + sigma * jax.random.normal(k, shape, jnp.float32)
        return jnp.where(mask, x_known, x_prev), None

    step_keys = jax.random.split(key_steps, m)
    x, _ = jax.lax.scan(step, x, (jnp.asarray(t_run), ab_t, ab_prev, step_keys), length=m)
    return x
