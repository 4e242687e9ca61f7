"""Tests for diffplan.sampler.sample (DESIGN contract 3).

Most tests use an exact noise predictor for Gaussian data: if x0 ~ N(mu, s^2) elementwise then
x_t ~ N(sqrt(ab) mu, ab s^2 + 1 - ab) and E[eps | x_t] = sqrt(1-ab) (x_t - sqrt(ab) mu) / (ab s^2 + 1 - ab).
With it every sampler step is an affine map of x_t plus Gaussian noise, so the exact mean and
std of the sampler's output (including its finite-step discretisation error) follow from a
short float64 recursion (``predicted_moments``), which the samples must match within sampling
error. With few steps DDIM / DDPM under-disperse (e.g. 50 steps: std 0.484 / 0.468 for s=0.5),
and with num_steps = T they converge to s.
"""

import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

try:
    import diffplan.sampler  # noqa: F401
except ImportError:  # repo not installed: run from a checkout
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from diffplan.sampler import denoiser_calls, sample
from diffplan.schedule import cosine_schedule, timestep_sequence

T = 1000
MU, S = 0.3, 0.5
N, D = 4096, 4  # Gaussian-moment tests: 16384 scalar samples


@pytest.fixture(scope="session")
def schedule():
    return cosine_schedule(T)


def gaussian_eps_fn(schedule, mu=MU, s=S):
    ab = schedule.alphas_cumprod

    def eps_fn(x, t):
        assert t.dtype == jnp.int32 and t.shape == x.shape[:1]
        a = ab[t].reshape((-1,) + (1,) * (x.ndim - 1))
        return jnp.sqrt(1 - a) * (x - jnp.sqrt(a) * mu) / (a * s * s + 1 - a)

    return eps_fn


def predicted_moments(schedule, num_steps, eta, start_step=0, x_init_value=None, mu=MU, s=S):
    """Exact mean and std of the sampler output for Gaussian data and the exact eps (float64)."""
    ab = np.asarray(schedule.alphas_cumprod, np.float64)
    ts = timestep_sequence(schedule.num_train_steps, num_steps)[start_step:]
    a_t = ab[ts]
    a_p = np.append(a_t[1:], 1.0)
    if x_init_value is None:
        m, v = 0.0, 1.0
    else:
        m, v = np.sqrt(a_t[0]) * x_init_value, 1.0 - a_t[0]
    for a, ap in zip(a_t, a_p):
        vt, mt = a * s * s + 1 - a, np.sqrt(a) * mu
        sig = eta * np.sqrt((1 - ap) / (1 - a)) * np.sqrt(1 - a / ap)
        d = np.sqrt(max(1 - ap - sig**2, 0.0))
        # x0_hat = mu + (x - mt) sqrt(a) s^2 / vt,  eps = sqrt(1 - a) (x - mt) / vt
        gain = (np.sqrt(ap) * np.sqrt(a) * s * s + d * np.sqrt(1 - a)) / vt
        m, v = np.sqrt(ap) * mu + gain * (m - mt), gain**2 * v + sig**2
    return m, np.sqrt(v)


def assert_moments(out, mean, std, n_sigma=5.0, atol=2e-4):
    """Sample mean / std within n_sigma standard errors (plus a float32 round-off floor)."""
    out = np.asarray(out, np.float64).ravel()
    n = out.size
    se_mean, se_std = std / np.sqrt(n), std / np.sqrt(2 * n)
    assert abs(out.mean() - mean) < n_sigma * se_mean + atol, (out.mean(), mean, se_mean)
    assert abs(out.std() - std) < n_sigma * se_std + atol, (out.std(), std, se_std)


def make_gauss_sampler(schedule, num_steps, n=N, d=D):
    """A jitted key, eta -> samples (n, d); eta is traced, so one compile serves eta 0 and 1."""
    eps_fn = gaussian_eps_fn(schedule)
    x_known = jnp.zeros((n, d), jnp.float32)
    mask = jnp.zeros((1, d), bool)
    return jax.jit(
        lambda key, eta: sample(
            eps_fn, schedule, key, x_known, mask, num_steps=num_steps, eta=eta, clip_x0=False
        )
    )


@pytest.fixture(scope="session")
def gauss50(schedule):
    return make_gauss_sampler(schedule, 50)


# ---------------------------------------------------------------- Gaussian moments


@pytest.mark.parametrize("eta,max_rel_bias", [(0.0, 0.04), (1.0, 0.08)])
def test_gaussian_moments_50_steps(schedule, gauss50, eta, max_rel_bias):
    out = np.asarray(gauss50(jax.random.PRNGKey(0), eta))
    assert out.shape == (N, D) and out.dtype == np.float32
    mean, std = predicted_moments(schedule, 50, eta)
    assert abs(mean - MU) < 1e-4 and abs(std - S) < max_rel_bias * S  # discretisation error only
    assert_moments(out, mean, std)
    assert abs(out.mean() - MU) < 0.02 and abs(out.std() - S) < max_rel_bias * S + 0.01


def test_gaussian_moments_converge_with_all_steps(schedule):
    f = make_gauss_sampler(schedule, T, n=1024, d=4)
    for eta, key in [(0.0, 1), (1.0, 2)]:
        out = np.asarray(f(jax.random.PRNGKey(key), eta))
        mean, std = predicted_moments(schedule, T, eta)
        assert abs(std - S) < 0.005 * S
        assert_moments(out, mean, std)
        assert abs(out.mean() - MU) < 0.03 and abs(out.std() - S) < 0.02


@pytest.mark.parametrize("num_steps", [1, 5])
def test_ddim_few_steps(schedule, num_steps):
    eps_fn = gaussian_eps_fn(schedule)
    f = jax.jit(
        lambda key: sample(
            eps_fn, schedule, key, jnp.zeros((N, D)), jnp.zeros((), bool),
            num_steps=num_steps, eta=0.0, clip_x0=False,
        )
    )
    out = np.asarray(f(jax.random.PRNGKey(3)))
    mean, std = predicted_moments(schedule, num_steps, 0.0)
    assert_moments(out, mean, std)
    assert abs(out.mean() - MU) < 0.02
    if num_steps == 1:  # one step from pure noise: the posterior mean E[x0 | x_T] ~ mu
        assert out.std() < 1e-3
    else:
        assert 0.3 < out.std() < 0.4  # 5-step DDIM under-disperses: predicted 0.362


def test_traced_eta_zero_matches_static_eta_zero(schedule, gauss50):
    eps_fn = gaussian_eps_fn(schedule)
    static = jax.jit(
        lambda key: sample(
            eps_fn, schedule, key, jnp.zeros((N, D)), jnp.zeros((1, D), bool),
            num_steps=50, eta=0.0, clip_x0=False,
        )
    )
    key = jax.random.PRNGKey(4)
    np.testing.assert_allclose(gauss50(key, 0.0), static(key), rtol=1e-5, atol=1e-6)


def test_determinism(gauss50):
    k1, k2 = jax.random.PRNGKey(5), jax.random.PRNGKey(6)
    a, b, c = gauss50(k1, 1.0), gauss50(k1, 1.0), gauss50(k2, 1.0)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    np.testing.assert_array_equal(gauss50(k1, 0.0), gauss50(k1, 0.0))


# ---------------------------------------------------------------- in-painting, transforms

SMALL = (3, 6, 6, 5)  # (B, H, W, C + G): 3 condition channels, 2 generated


def small_inputs(seed=0):
    rng = np.random.default_rng(seed)
    x_known = rng.uniform(-1, 1, SMALL).astype(np.float32)
    x_known[..., 0] = rng.integers(0, 12, SMALL[:3])  # token ids: far outside the clip range
    x_known[..., 1] = rng.integers(0, 2, SMALL[:3])
    x_known[..., 2] = np.float32(np.pi)  # not representable exactly by arithmetic round trips
    mask = np.zeros((1, 1, 1, 5), bool)
    mask[..., :3] = True
    return jnp.asarray(x_known), jnp.asarray(mask)


def nonlinear_eps_fn(x, t):
    # An arbitrary smooth "model" that depends on all channels and on t.
    tf = t.astype(jnp.float32).reshape((-1, 1, 1, 1)) / T
    return jnp.tanh(0.7 * x + 0.3 * jnp.roll(x, 1, axis=-1)) + 0.2 * tf - 0.1


@pytest.fixture(scope="session")
def small_sampler(schedule):
    """jitted (key, x_known, eta) -> x0 on SMALL with the condition channels held fixed."""
    _, mask = small_inputs()

    def f(key, x_known, eta):
        return sample(nonlinear_eps_fn, schedule, key, x_known, mask, num_steps=8, eta=eta)

    return jax.jit(f)


def test_known_entries_bit_exact(small_sampler):
    x_known, _ = small_inputs()
    for eta in (0.0, 1.0):
        out = np.asarray(small_sampler(jax.random.PRNGKey(7), x_known, eta))
        assert out.shape == SMALL and out.dtype == np.float32
        np.testing.assert_array_equal(out[..., :3], np.asarray(x_known)[..., :3])
        gen = out[..., 3:]
        assert np.all(np.isfinite(gen)) and np.all(np.abs(gen) <= 1.0)  # clip_x0 default on
        assert not np.allclose(gen, np.asarray(x_known)[..., 3:])


def test_known_entries_bit_exact_elementwise_mask_and_warm_start(schedule):
    x_known, _ = small_inputs(1)
    rng = np.random.default_rng(1)
    mask = jnp.asarray(rng.random(SMALL) < 0.4)
    x_init = jnp.asarray(rng.uniform(-1, 1, SMALL).astype(np.float32))
    f = jax.jit(
        lambda key: sample(
            nonlinear_eps_fn, schedule, key, x_known, mask, num_steps=6, eta=1.0,
            x_init=x_init, start_step=2,
        )
    )
    out = np.asarray(f(jax.random.PRNGKey(8)))
    m = np.asarray(mask)
    np.testing.assert_array_equal(out[m], np.asarray(x_known)[m])
    assert not np.allclose(out[~m], np.asarray(x_known)[~m])


def test_vmap_over_keys_and_inputs(small_sampler):
    keys = jax.random.split(jax.random.PRNGKey(9), 4)
    xs = jnp.stack([small_inputs(0)[0]] * 2 + [small_inputs(s)[0] for s in (1, 2)])
    batched = np.asarray(jax.vmap(small_sampler, in_axes=(0, 0, None))(keys, xs, 1.0))
    single = np.stack([np.asarray(small_sampler(k, x, 1.0)) for k, x in zip(keys, xs)])
    np.testing.assert_allclose(batched, single, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(batched[..., :3], np.asarray(xs)[..., :3])
    assert not np.allclose(single[0], single[1])  # same inputs, different keys: different plans


def test_inside_user_lax_scan(schedule, small_sampler):
    x_known, mask = small_inputs()
    keys = jax.random.split(jax.random.PRNGKey(10), 3)

    @jax.jit
    def rollout(keys, x_known):
        def body(carry, key):
            x0 = sample(nonlinear_eps_fn, schedule, key, carry, mask, num_steps=8, eta=1.0)
            # Feed the plan back as the next step's known tensor (a re-planning loop).
            return x0, x0

        return jax.lax.scan(body, x_known, keys)

    final, plans = rollout(keys, x_known)
    x = x_known
    for i, k in enumerate(keys):
        x = small_sampler(k, x, 1.0)
        np.testing.assert_allclose(plans[i], x, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(final)[..., :3], np.asarray(x_known)[..., :3])


# ---------------------------------------------------------------- the update rule itself


def numpy_ddim_step(x, eps, a_t, a_prev, clip, clip_range=1.0):
    """diffusers DDIMScheduler.step (epsilon prediction, eta=0, use_clipped_model_output=True)."""
    x, eps = x.astype(np.float64), eps.astype(np.float64)
    x0 = (x - np.sqrt(1 - a_t) * eps) / np.sqrt(a_t)
    if clip:
        x0 = np.clip(x0, -clip_range, clip_range)
        eps = (x - np.sqrt(a_t) * x0) / np.sqrt(1 - a_t)
    return np.sqrt(a_prev) * x0 + np.sqrt(1 - a_prev) * eps


def run_recorded(schedule, num_steps, clip_x0, x_init=None, start_step=None, clip_range=1.0):
    """Runs a jitted sample and records every denoiser call (x_t, t) at run time, in order."""
    calls = []

    def record(x, t):
        calls.append((np.asarray(x), np.asarray(t)))

    def eps_fn(x, t):
        jax.debug.callback(record, x, t, ordered=True)
        return nonlinear_eps_fn(x, t)

    x_known, mask = small_inputs(2)
    f = jax.jit(
        lambda key: sample(
            eps_fn, schedule, key, x_known, mask, num_steps=num_steps, eta=0.0,
            x_init=x_init, start_step=start_step, clip_x0=clip_x0, clip_range=clip_range,
        )
    )
    out = np.asarray(f(jax.random.PRNGKey(11)))
    jax.effects_barrier()
    return out, calls, np.asarray(x_known), np.asarray(mask)


@pytest.mark.parametrize("clip_x0,clip_range", [(True, 0.5), (False, 1.0)])
def test_matches_numpy_ddim_reference(schedule, clip_x0, clip_range):
    num_steps = 7
    out, calls, x_known, mask = run_recorded(schedule, num_steps, clip_x0, clip_range=clip_range)
    ts = timestep_sequence(T, num_steps)
    assert len(calls) == num_steps == denoiser_calls(num_steps)
    ab = np.asarray(schedule.alphas_cumprod, np.float64)
    mask_b = np.broadcast_to(mask, x_known.shape)
    xs = [c[0] for c in calls] + [out]
    for k, (x, t) in enumerate(calls):
        assert t.dtype == np.int32 and t.shape == (x.shape[0],) and np.all(t == ts[k])
        np.testing.assert_array_equal(x[mask_b], x_known[mask_b])
        eps = np.asarray(nonlinear_eps_fn(jnp.asarray(x), jnp.asarray(t)), np.float64)
        a_prev = ab[ts[k + 1]] if k + 1 < num_steps else 1.0
        ref = numpy_ddim_step(x, eps, ab[ts[k]], a_prev, clip_x0, clip_range)
        np.testing.assert_allclose(xs[k + 1][~mask_b], ref[~mask_b], rtol=2e-4, atol=2e-4)
    gen = out[..., 3:]
    if clip_x0:  # the last step returns the clipped x0 itself
        assert np.all(np.abs(gen) <= clip_range) and np.max(np.abs(gen)) == np.float32(clip_range)
    else:
        assert np.max(np.abs(gen)) > 1.0  # this "model" predicts x0 outside [-1, 1]


# ---------------------------------------------------------------- warm start


def test_warm_start_scan_length_and_trace_count(schedule):
    eps_fn = gaussian_eps_fn(schedule)
    x_known = jnp.zeros((2, 3))
    mask = jnp.zeros((1, 3), bool)
    x_init = jnp.full((2, 3), MU)
    num_steps = 10
    for start_step in [None, 0, 1, 5, 9]:
        traces = []

        def counting_eps_fn(x, t):
            traces.append(1)
            return eps_fn(x, t)

        kw = {} if start_step is None else dict(x_init=x_init, start_step=start_step)
        jaxpr = jax.make_jaxpr(
            lambda key: sample(counting_eps_fn, schedule, key, x_known, mask, num_steps=num_steps, **kw)
        )(jax.random.PRNGKey(0))
        scans = [e for e in jaxpr.jaxpr.eqns if e.primitive.name == "scan"]
        assert len(scans) == 1
        expected = num_steps - (start_step or 0)
        assert scans[0].params["length"] == expected == denoiser_calls(num_steps, start_step)
        assert len(traces) == 1  # the denoiser is traced once: no Python loop over steps


def test_warm_start_runtime_calls_and_timesteps(schedule):
    x_init = jnp.asarray(np.random.default_rng(3).uniform(-1, 1, SMALL).astype(np.float32))
    num_steps, start_step = 7, 4
    out, calls, x_known, mask = run_recorded(
        schedule, num_steps, True, x_init=x_init, start_step=start_step
    )
    assert len(calls) == num_steps - start_step == denoiser_calls(num_steps, start_step)
    ts = timestep_sequence(T, num_steps)
    assert [int(c[1][0]) for c in calls] == ts[start_step:].tolist()
    # The first x_t is x_init re-noised to ts[start_step] (plus the known entries).
    a = float(schedule.alphas_cumprod[ts[start_step]])
    m = np.broadcast_to(mask, x_known.shape)
    z = (calls[0][0][~m] - np.sqrt(a) * np.asarray(x_init)[~m]) / np.sqrt(1 - a)
    assert abs(z.mean()) < 0.3 and 0.7 < z.std() < 1.3  # ~ N(0, 1) noise (216 draws)
    np.testing.assert_array_equal(calls[0][0][m], x_known[m])


def test_warm_start_from_data_mean_stays_close(schedule):
    eps_fn = gaussian_eps_fn(schedule)
    num_steps = 20
    x_known = jnp.zeros((1024, 4))
    mask = jnp.zeros((1, 4), bool)
    x_init = jnp.full((1024, 4), MU)
    stds = {}
    for start_step in (10, 18):
        out = np.asarray(
            jax.jit(
                lambda key: sample(
                    eps_fn, schedule, key, x_known, mask, num_steps=num_steps, eta=0.0,
                    x_init=x_init, start_step=start_step, clip_x0=False,
                )
            )(jax.random.PRNGKey(12))
        )
        mean, std = predicted_moments(schedule, num_steps, 0.0, start_step, x_init_value=MU)
        assert_moments(out, mean, std)
        stds[start_step] = out.std()
    # Skipping 18 of 20 steps re-noises only to t=99 (noise std 0.17): the plan stays near
    # x_init (predicted spread 0.16 around it, against s = 0.5 for a fresh sample).
    assert stds[18] < 0.35 * S and np.max(np.abs(out - MU)) < 1.0
    assert stds[18] < stds[10] < S


# ---------------------------------------------------------------- argument checking


def test_bad_arguments_raise(schedule):
    eps_fn = gaussian_eps_fn(schedule)
    key = jax.random.PRNGKey(0)
    xk = jnp.zeros((4, 5))
    mask = jnp.zeros((1, 5), bool)
    good = dict(num_steps=5)
    bad_calls = [
        lambda: sample(eps_fn, schedule, key, xk, mask, num_steps=0),
        lambda: sample(eps_fn, schedule, key, xk, mask, num_steps=T + 1),
        lambda: sample(eps_fn, schedule, key, xk, mask, num_steps=2.5),
        lambda: sample(eps_fn, schedule, key, xk, mask, num_steps=5, x_init=xk),
        lambda: sample(eps_fn, schedule, key, xk, mask, num_steps=5, start_step=1),
        lambda: sample(eps_fn, schedule, key, xk, mask, num_steps=5, x_init=xk, start_step=5),
        lambda: sample(eps_fn, schedule, key, xk, mask, num_steps=5, x_init=xk, start_step=-1),
        lambda: sample(eps_fn, schedule, key, xk, mask, num_steps=5, x_init=xk[:2], start_step=1),
        lambda: sample(eps_fn, schedule, key, xk, jnp.zeros((1, 3), bool), **good),
        lambda: sample(eps_fn, schedule, key, xk, jnp.zeros((2, 4, 5), bool), **good),
        lambda: sample(eps_fn, schedule, key, jnp.zeros(()), jnp.zeros((), bool), **good),
        lambda: sample(eps_fn, schedule, key, xk, mask, eta=-1.0, **good),
        lambda: sample(eps_fn, schedule, key, xk, mask, clip_range=0.0, **good),
        lambda: sample(eps_fn, schedule, key, xk, mask, clip_x0=jnp.array(True), **good),
        lambda: sample(lambda x, t: x[:, :2], schedule, key, xk, mask, **good),
        lambda: sample(eps_fn, {"alphas_cumprod": schedule.alphas_cumprod}, key, xk, mask, **good),
        lambda: denoiser_calls(0),
        lambda: denoiser_calls(5, 5),
        lambda: denoiser_calls(5, -1),
    ]
    for i, call in enumerate(bad_calls):
        with pytest.raises(ValueError):
            jax.eval_shape(call)  # trace only: every check fires before anything compiles
            pytest.fail(f"bad call {i} did not raise")
    assert denoiser_calls(5) == 5 and denoiser_calls(5, 0) == 5 and denoiser_calls(5, 3) == 2
