"""Tests of diffplan.sharding: data parallelism over all devices.

The multi-device checks run this file as a subprocess with
XLA_FLAGS=--xla_force_host_platform_device_count=2 (the flag must be set before JAX starts):
the train step, the train loop, a batched forward and batched in-painting sampling on a
2-device "data" mesh must match the same computations on one device within 1e-5.
"""
import dataclasses
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import sharding as shd

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
from toy_denoiser import C, G, H, L, W, TinyConfig, TinyDenoiser, toy_batch_fn


# ------------------------------------------------------------------------------- in-process

def test_mesh_over_all_devices_and_batch_checks():
    mesh = shd.data_mesh()
    assert mesh.axis_names == ("data",) and mesh.size == jax.device_count()
    tree = {"a": jnp.zeros((4, 3)), "b": jnp.zeros((4,), jnp.int32)}
    assert shd.batch_size_of(tree) == 4
    with pytest.raises(ValueError, match="different leading"):
        shd.batch_size_of({"a": jnp.zeros((4, 3)), "b": jnp.zeros((5,))})
    with pytest.raises(ValueError, match="scalar"):
        shd.shard_batch({"a": jnp.zeros(())}, mesh)
    placed = shd.shard_batch(tree, mesh)
    assert placed["a"].sharding.is_equivalent_to(shd.batch_sharding(mesh), 2)
    rep = shd.replicate({"w": jnp.ones((2, 2))}, mesh)
    assert rep["w"].sharding.is_fully_replicated


def test_data_parallel_jit_matches_jit_on_this_process():
    mesh = shd.data_mesh()
    n = mesh.size
    f = shd.data_parallel_jit(lambda w, x: jnp.tanh(x @ w), mesh, batched_argnums=(1,))
    w = jnp.arange(6.0).reshape(3, 2) / 6
    x = jnp.linspace(-1, 1, 12 * n).reshape(4 * n, 3)
    np.testing.assert_allclose(f(w, x), jnp.tanh(x @ w), atol=1e-6)


# ------------------------------------------------------------------------------- 2 devices

def _child() -> dict:
    """Runs under 2 host devices; returns max abs differences and placement facts."""
    from diffplan.schedule import cosine_schedule
    from diffplan.train import TrainConfig, init_train_state, make_train_step, step_key, train
    from diffplan import sample

    assert jax.device_count() == 2, jax.devices()
    mesh2, mesh1 = shd.data_mesh(), shd.data_mesh(jax.devices()[:1])
    model = TinyDenoiser(TinyConfig())
    cfg = TrainConfig(seed=1, steps=20, batch_size=8, lr=1e-2, warmup_steps=1,
                      checkpoint_every=100, log_every=100)
    make_batch = jax.jit(toy_batch_fn, static_argnums=1)
    shapes = jax.eval_shape(lambda: toy_batch_fn(jax.random.PRNGKey(0), 1))
    state0 = init_train_state(model, cfg, shapes)
    out = {"devices": jax.device_count()}

    def maxdiff(a, b):
        return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y))))
                   for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))

    # 1. The public train step: 3 steps with the loop's batches and keys, on 1 and 2 devices.
    runs = {}
    for name, mesh in (("one", mesh1), ("two", mesh2)):
        step = make_train_step(model, cfg, mesh=mesh)
        s, losses = state0, []
        for i in range(3):
            batch_key, loss_key = jax.random.split(step_key(cfg.seed, i))
            s, m = step(s, make_batch(batch_key, cfg.batch_size), loss_key)
            losses.append(float(m["loss"]))
        runs[name] = (s, losses)
    out["step_param_diff"] = maxdiff(runs["one"][0].params, runs["two"][0].params)
    out["step_ema_diff"] = maxdiff(runs["one"][0].ema_params, runs["two"][0].ema_params)
    out["step_loss_diff"] = float(np.max(np.abs(np.subtract(runs["one"][1], runs["two"][1]))))
    out["step_params_devices"] = len(runs["two"][0].params["Conv_0"]["kernel"].sharding.device_set)
    out["step_changed_params"] = maxdiff(runs["two"][0].params, state0.params)

    # 2. The train loop on 2 devices equals the 1-device train step fed the same batches.
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        res = train(model, TinyConfig(), cfg, toy_batch_fn, d, progress=False, mesh=mesh2)
        # Reloading the final checkpoint onto the 2-device mesh (a finished run just loads).
        again = train(model, TinyConfig(), cfg, toy_batch_fn, d, progress=False, mesh=mesh2)
    out["reload_diff"] = max(maxdiff(res.state.params, again.state.params),
                             maxdiff(res.state.opt_state, again.state.opt_state))
    out["reload_devices"] = len(again.state.params["Conv_0"]["kernel"].sharding.device_set)
    step1 = make_train_step(model, cfg, mesh=mesh1)
    s = state0
    for i in range(20):
        batch_key, loss_key = jax.random.split(step_key(cfg.seed, i))
        s, _ = step1(s, make_batch(batch_key, cfg.batch_size), loss_key)
    out["loop_param_diff"] = maxdiff(res.state.params, s.params)
    out["loop_ema_diff"] = maxdiff(res.state.ema_params, s.ema_params)

    # 3. A batched forward and batched in-painting sampling, split over the data axis.
    params = runs["two"][0].params
    batch = make_batch(jax.random.PRNGKey(5), 8)
    t = jnp.arange(8, dtype=jnp.int32) * 10
    schedule = cosine_schedule(100)
    known = jnp.zeros(batch.x0.shape, bool).at[..., :C].set(True)

    def fwd(p, x, t, tok):
        return model.apply({"params": p}, x, t, tok)

    def plan(p, key, x_known, tok):
        def denoise_fn(x_t, tt):
            eps = model.apply({"params": p}, x_t, tt, tok)
            return jnp.concatenate([jnp.zeros(x_t.shape[:-1] + (C,)), eps], -1)
        return sample(denoise_fn, schedule, key, x_known, known, num_steps=4, eta=1.0)

    ys, plans = {}, {}
    for name, mesh in (("one", mesh1), ("two", mesh2)):
        ys[name] = shd.data_parallel_jit(fwd, mesh, batched_argnums=(1, 2, 3))(
            params, batch.x0, t, batch.tokens)
        plans[name] = shd.data_parallel_jit(plan, mesh, batched_argnums=(2, 3))(
            params, jax.random.PRNGKey(9), batch.x0, batch.tokens)
    out["forward_diff"] = maxdiff(ys["one"], ys["two"])
    out["forward_out_devices"] = len(ys["two"].sharding.device_set)
    out["sample_diff"] = maxdiff(plans["one"], plans["two"])
    out["sample_out_devices"] = len(plans["two"].sharding.device_set)
    out["sample_known_kept"] = bool(jnp.all(plans["two"][..., :C] == batch.x0[..., :C]))
    out["sample_spread"] = float(jnp.std(plans["two"][..., C:]))

    # 4. Batches that do not split evenly are refused with a clear message.
    errors = []
    try:
        shd.shard_batch({"x0": jnp.zeros((3, H, W, C + G)), "tokens": jnp.zeros((3, L))}, mesh2)
    except ValueError as e:
        errors.append(str(e))
    try:
        train(model, TinyConfig(), dataclasses.replace(cfg, batch_size=3), toy_batch_fn,
              tempfile.mkdtemp(), progress=False, mesh=mesh2)
    except ValueError as e:
        errors.append(str(e))
    out["errors"] = errors
    return out


@pytest.fixture(scope="module")
def two_device_results():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu", PYTHONPATH=REPO)
    cache_dir = jax.config.jax_compilation_cache_dir  # share the session's persistent cache
    if cache_dir:
        env.update(JAX_COMPILATION_CACHE_DIR=cache_dir,
                   JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.5",
                   JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    res = subprocess.run([sys.executable, os.path.abspath(__file__)], capture_output=True,
                         text=True, env=env, cwd=REPO, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_sharded_train_step_matches_single_device(two_device_results):
    r = two_device_results
    print({k: v for k, v in r.items() if k != "errors"})
    assert r["devices"] == 2 and r["step_params_devices"] == 2
    assert r["step_changed_params"] > 1e-3  # the steps did something
    assert r["step_param_diff"] < 1e-5 and r["step_ema_diff"] < 1e-5
    assert r["step_loss_diff"] < 1e-5


def test_sharded_train_loop_matches_single_device_steps(two_device_results):
    r = two_device_results
    assert r["loop_param_diff"] < 1e-5 and r["loop_ema_diff"] < 1e-5
    assert r["reload_diff"] == 0.0 and r["reload_devices"] == 2


def test_sharded_forward_and_sampling_match_single_device(two_device_results):
    r = two_device_results
    assert r["forward_out_devices"] == 2 and r["sample_out_devices"] == 2
    assert r["forward_diff"] < 1e-5
    assert r["sample_diff"] < 1e-5
    assert r["sample_known_kept"] and r["sample_spread"] > 0.1


def test_indivisible_batch_is_refused(two_device_results):
    errors = two_device_results["errors"]
    assert len(errors) == 2
    for e in errors:
        assert "batch size 3 is not divisible by the number of devices 2" in e


if __name__ == "__main__":
    print(json.dumps(_child()))
