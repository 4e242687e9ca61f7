"""Tests for diffplan.schedule: the cosine (squaredcos_cap_v2) schedule and timestep spacing."""

import math
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

try:
    import diffplan.schedule  # noqa: F401
except ImportError:  # repo not installed: run from a checkout
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from diffplan.schedule import Schedule, cosine_schedule, timestep_sequence


def diffusers_squaredcos_cap_v2_betas(T, max_beta=0.999):
    """A literal transcription of diffusers' betas_for_alpha_bar(alpha_transform_type="cosine")
    followed by torch.tensor(betas, dtype=torch.float32)."""

    def alpha_bar_fn(t):
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = []
    for i in range(T):
        t1 = i / T
        t2 = (i + 1) / T
        betas.append(min(1 - alpha_bar_fn(t2) / alpha_bar_fn(t1), max_beta))
    return np.asarray(betas, dtype=np.float32)


def numpy_cosine_alphas_cumprod(T, max_beta=0.999):
    """Vectorised float64 version, for alphas_cumprod."""
    f = lambda t: np.cos((t + 0.008) / 1.008 * np.pi / 2) ** 2
    i = np.arange(T, dtype=np.float64)
    betas = np.minimum(1 - f((i + 1) / T) / f(i / T), max_beta)
    return np.cumprod(1 - betas)


@pytest.mark.parametrize("T,max_beta", [(1000, 0.999), (100, 0.999), (50, 0.3), (1, 0.999)])
def test_matches_numpy_squaredcos_cap_v2(T, max_beta):
    s = cosine_schedule(T, max_beta=max_beta)
    ref_betas = diffusers_squaredcos_cap_v2_betas(T, max_beta)
    np.testing.assert_array_equal(np.asarray(s.betas), ref_betas)
    np.testing.assert_array_equal(np.asarray(s.alphas), np.float32(1) - ref_betas)
    # diffusers: torch.cumprod over float32 alphas; compare against a float64 cumprod.
    np.testing.assert_allclose(
        np.asarray(s.alphas_cumprod, np.float64), numpy_cosine_alphas_cumprod(T, max_beta), rtol=1e-4
    )
    for a in (s.betas, s.alphas, s.alphas_cumprod):
        assert a.dtype == jnp.float32 and a.shape == (T,)
    assert s.num_train_steps == T and isinstance(s.num_train_steps, int)


def test_known_properties():
    s = cosine_schedule(1000)
    betas, ab = np.asarray(s.betas), np.asarray(s.alphas_cumprod)
    assert np.all(betas > 0) and np.all(betas <= np.float32(0.999))
    assert betas[-1] == np.float32(0.999)  # alpha_bar(1) ~ 0: the cap is active at the end
    assert np.all(np.diff(betas) > 0)  # the cosine schedule's betas increase monotonically
    assert np.all(np.diff(ab) < 0)  # strictly decreasing
    assert 0 < ab[-1] < 1e-6 and 0.9999 < ab[0] < 1
    # Midpoint of the cosine schedule: alpha_bar(0.5) / alpha_bar(0) ~ 0.4937.
    expected_mid = math.cos(0.508 / 1.008 * math.pi / 2) ** 2 / math.cos(0.008 / 1.008 * math.pi / 2) ** 2
    np.testing.assert_allclose(ab[499], expected_mid, rtol=1e-4)


def test_max_beta_caps():
    s = cosine_schedule(20, max_beta=0.2)
    betas = np.asarray(s.betas)
    assert betas.max() == np.float32(0.2)
    assert np.all(betas <= np.float32(0.2))
    assert np.sum(betas == np.float32(0.2)) >= 1 and np.sum(betas < np.float32(0.2)) >= 1


def test_schedule_is_pytree_with_static_num_train_steps():
    s = cosine_schedule(64)
    leaves = jax.tree_util.tree_leaves(s)
    assert len(leaves) == 3  # num_train_steps is not a leaf

    @jax.jit
    def f(sched):
        # num_train_steps stays a Python int under jit.
        assert isinstance(sched.num_train_steps, int)
        return sched.alphas_cumprod[sched.num_train_steps - 1] * 2.0

    np.testing.assert_allclose(f(s), 2.0 * np.asarray(s.alphas_cumprod)[-1], rtol=1e-6)
    s2 = jax.tree_util.tree_map(lambda a: a * 1.0, s)
    assert isinstance(s2, Schedule) and s2.num_train_steps == 64


@pytest.mark.parametrize("T", [0, -3, 2.5, True, "10", None])
def test_cosine_schedule_bad_T(T):
    with pytest.raises(ValueError):
        cosine_schedule(T)


@pytest.mark.parametrize("max_beta", [0.0, 1.0, 1.5, -0.1, float("nan"), "x"])
def test_cosine_schedule_bad_max_beta(max_beta):
    with pytest.raises(ValueError):
        cosine_schedule(10, max_beta=max_beta)


@pytest.mark.parametrize("T,n", [(1000, 1), (1000, 3), (1000, 7), (1000, 50), (1000, 1000), (10, 10), (1, 1), (97, 13)])
def test_timestep_sequence_properties(T, n):
    ts = timestep_sequence(T, n)
    assert ts.dtype == np.int32 and ts.shape == (n,)
    assert ts[0] == T - 1  # starts from the noisiest timestep
    assert ts[-1] >= 0
    assert np.all(np.diff(ts) < 0)  # strictly decreasing, so all distinct
    gaps = -np.diff(ts)
    if n > 1:
        assert set(gaps.tolist()) <= {T // n, -(-T // n)}  # evenly spaced
    assert ts[-1] == T // n - 1  # the last step's gap to x0 is as large as the others


def test_timestep_sequence_all_steps_and_diffusers_trailing():
    np.testing.assert_array_equal(timestep_sequence(20, 20), np.arange(19, -1, -1))
    for T, n in [(1000, 50), (1000, 10), (1000, 1), (100, 20), (64, 8)]:
        # diffusers DDIMScheduler.set_timesteps with timestep_spacing="trailing" (n divides T).
        ref = np.round(np.arange(T, 0, -T / n)).astype(np.int64) - 1
        np.testing.assert_array_equal(timestep_sequence(T, n), ref)


@pytest.mark.parametrize("T,n", [(10, 0), (10, 11), (10, -1), (0, 1), (10, 2.0), (10, None)])
def test_timestep_sequence_bad_args(T, n):
    with pytest.raises(ValueError):
        timestep_sequence(T, n)
