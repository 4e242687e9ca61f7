"""Tests of diffplan.train: the loss, the optimiser schedule, the loop, resume and NaN handling.

A tiny stand-in denoiser (a conv net with the Denoiser call signature) on a toy task keeps the
tests fast; one test also runs the real ``diffplan.denoiser.Denoiser``.
"""
import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import checkpoint as ckpt
from diffplan.schedule import cosine_schedule
from diffplan.train import (Batch, ConfigMismatchError, NonFiniteLossError, TrainConfig,
                            diffusion_loss, init_train_state, lr_schedule, make_train_step,
                            step_key, train)

from toy_denoiser import C, G, H, L, W, TinyConfig, TinyDenoiser, toy_batch_fn

make_batch = jax.jit(toy_batch_fn, static_argnums=1)  # for batches drawn outside the loop


def small_cfg(**kw):
    base = dict(seed=3, steps=12, batch_size=4, lr=3e-3, warmup_steps=2, weight_decay=1e-2,
                grad_clip=1.0, ema_decay=0.99, num_train_timesteps=100, num_gen_channels=G,
                checkpoint_every=4, log_every=1)
    base.update(kw)
    return TrainConfig(**base)


def read_metrics(out_dir):
    with open(os.path.join(out_dir, "metrics.jsonl")) as f:
        return [json.loads(line) for line in f if line.strip()]


def leaves_close(a, b, atol=1e-6):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    return all(np.allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=0) for x, y in zip(la, lb))


# ------------------------------------------------------------------------------- config

def test_train_config_roundtrip_and_validation():
    cfg = small_cfg()
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert TrainConfig().lr == 2e-4 and TrainConfig().num_train_timesteps == 100
    with pytest.raises(ValueError, match="warmup_steps"):
        small_cfg(warmup_steps=12)
    with pytest.raises(ValueError, match="batch_size"):
        small_cfg(batch_size=0)
    with pytest.raises(ValueError, match="unknown TrainConfig fields"):
        TrainConfig.from_dict({"lr": 1e-3, "bogus": 1})
    with pytest.raises(ValueError, match="ema_decay"):
        small_cfg(ema_decay=1.0)


def test_lr_schedule_warms_up_then_decays():
    cfg = TrainConfig(steps=100, warmup_steps=10, lr=1e-3)
    lr = np.array([float(lr_schedule(cfg)(i)) for i in range(101)])
    assert lr[0] == 0.0
    assert np.all(np.diff(lr[:11]) > 0), "linear warm-up"
    np.testing.assert_allclose(lr[5], 5e-4, rtol=1e-5)
    np.testing.assert_allclose(lr[10], 1e-3, rtol=1e-6)
    assert np.all(np.diff(lr[10:]) < 0), "cosine decay"
    np.testing.assert_allclose(lr[55], 5e-4, rtol=1e-4)  # half-way through the decay
    assert lr[100] < 1e-9


# ------------------------------------------------------------------------------- loss

def test_loss_noises_only_generated_channels_and_respects_mask():
    batch = make_batch(jax.random.PRNGKey(0), 4)
    ab = cosine_schedule(100).alphas_cumprod
    key = jax.random.PRNGKey(1)
    goal_masked = batch.loss_mask.at[..., 1].set(0.0)

    def oracle(variables, x_t, t, tokens):
        # Recovers eps exactly iff x_t follows the forward process on the generated channels;
        # adds the change of the condition channels (zero iff they are clean).
        a = ab[t][:, None, None, None]
        eps = (x_t[..., C:] - jnp.sqrt(a) * batch.x0[..., C:]) / jnp.sqrt(1 - a)
        return eps + jnp.sum(x_t[..., :C] - batch.x0[..., :C], -1, keepdims=True)

    def zero(variables, x_t, t, tokens):
        return jnp.zeros(x_t.shape[:-1] + (G,))

    def junk_goal(variables, x_t, t, tokens):  # garbage where the mask is 0
        return zero(variables, x_t, t, tokens).at[..., 1].set(1e3)

    @jax.jit
    def losses(b):
        exact, aux = diffusion_loss({}, oracle, b, key, ab, G)
        full, _ = diffusion_loss({}, zero, b, key, ab, G)
        masked, _ = diffusion_loss({}, junk_goal, b._replace(loss_mask=goal_masked), key, ab, G)
        eps = jax.random.normal(jax.random.split(key)[1], b.x0.shape[:-1] + (G,))
        return exact, aux["t"], full, masked, jnp.mean(eps[..., 0] ** 2)

    exact, t, full, masked, path_only = losses(batch)
    assert float(exact) < 1e-8
    assert t.shape == (4,) and int(t.min()) >= 0 and int(t.max()) < 100
    assert 0.7 < float(full) < 1.3  # E[eps^2] = 1
    # Masking the goal channel: what is predicted there is ignored and the loss is normalised
    # by the mask sum (the path channel's mean squared noise).
    np.testing.assert_allclose(float(masked), float(path_only), rtol=1e-5)
    with pytest.raises(ValueError, match="loss_mask"):
        diffusion_loss({}, zero, batch._replace(loss_mask=goal_masked[..., :1]), key, ab, G)


# One configuration shared by the loop tests: the jitted loop step is compiled once (jit
# caches are keyed by model, config, batch_fn and mesh) and reused by the resumed runs.
LOOP_CFG = small_cfg(steps=60, batch_size=8, warmup_steps=5, checkpoint_every=20, log_every=1,
                     val_every=30, val_batches=2)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A 60-step run of the tiny model on the toy task (shared by several tests)."""
    out = str(tmp_path_factory.mktemp("trained"))
    result = train(TinyDenoiser(TinyConfig()), TinyConfig(), LOOP_CFG, toy_batch_fn, out,
                   progress=False, extra_metadata={"task": "toy"})
    return out, LOOP_CFG, result


def test_training_lowers_the_loss(trained):
    out, cfg, result = trained
    recs = read_metrics(out)
    assert [r["step"] for r in recs] == list(range(1, 61))
    for r in recs:
        assert set(r) >= {"step", "loss", "lr", "grad_norm", "steps_per_sec", "wall_time"}
        assert np.isfinite(r["loss"]) and r["steps_per_sec"] > 0
    first = np.mean([r["loss"] for r in recs[:10]])
    last = np.mean([r["loss"] for r in recs[-10:]])
    print(f"toy loss: first 10 steps {first:.4f} -> last 10 steps {last:.4f}")
    assert last < 0.8 * first, (first, last)
    assert result.final_loss == recs[-1]["loss"]
    # Validation (EMA params, fixed batches) at steps 30 and 60 only.
    assert [r["step"] for r in recs if "val_loss" in r] == [30, 60]
    assert all(np.isfinite(r["val_loss"]) for r in recs if "val_loss" in r)
    assert int(result.state.step) == 60
    assert ckpt.all_steps(out) == [40, 60]  # latest 2 kept
    # The EMA moved away from the initial params but differs from the raw params.
    init = init_train_state(TinyDenoiser(TinyConfig()), cfg, make_batch(jax.random.PRNGKey(0), 1))
    assert not leaves_close(result.state.ema_params, init.params, atol=1e-4)
    assert not leaves_close(result.state.ema_params, result.state.params, atol=1e-7)
    meta = ckpt.read_metadata(out)
    assert meta["train_config"] == cfg.to_dict() and meta["extra"] == {"task": "toy"}
    assert meta["model_config"] == TinyConfig().to_dict()
    assert meta["input_shapes"] == {"x": [1, H, W, C + G], "tokens": [1, L]}
    assert meta["kind"] == "train" and meta["step"] == 60


def test_finished_run_is_not_retrained_and_config_mismatch_raises(trained):
    out, cfg, result = trained
    kw = dict(progress=False, extra_metadata={"task": "toy"})
    again = train(TinyDenoiser(TinyConfig()), TinyConfig(), cfg, toy_batch_fn, out, **kw)
    assert int(again.state.step) == 60 and leaves_close(again.state.params, result.state.params, 0)
    with pytest.raises(ConfigMismatchError,
                       match=r"model_config\.features: stored 8, requested 16"):
        train(TinyDenoiser(TinyConfig(features=16)), TinyConfig(features=16), cfg, toy_batch_fn,
              out, **kw)
    with pytest.raises(ValueError, match=r"train_config\.lr: stored 0\.003, requested 0\.001"):
        train(TinyDenoiser(TinyConfig()), TinyConfig(), dataclasses.replace(cfg, lr=1e-3),
              toy_batch_fn, out, **kw)
    with pytest.raises(ValueError, match=r"extra\.task"):
        train(TinyDenoiser(TinyConfig()), TinyConfig(), cfg, toy_batch_fn, out, progress=False,
              extra_metadata={"task": "other"})
    # Logging-only fields may change.
    train(TinyDenoiser(TinyConfig()), TinyConfig(), dataclasses.replace(cfg, log_every=7),
          toy_batch_fn, out, **kw)
    assert ckpt.all_steps(out) == [40, 60]


class _Crash(Exception):
    pass


def test_resume_after_crash_matches_uninterrupted_run(trained, tmp_path):
    full_dir, cfg, full = trained  # 60 steps in one go; checkpoints every 20, log every step
    crash_dir = str(tmp_path / "crash")

    def crash_at_27(step, record):
        if step == 27:
            raise _Crash()

    with pytest.raises(_Crash):
        train(TinyDenoiser(TinyConfig()), TinyConfig(), cfg, toy_batch_fn, crash_dir,
              progress=False, extra_metadata={"task": "toy"}, callback=crash_at_27)
    assert ckpt.all_steps(crash_dir) == [20]
    assert [r["step"] for r in read_metrics(crash_dir)] == list(range(1, 28))

    # "Fresh process": new model / config objects rebuilt from JSON, a fresh call.
    cfg2 = TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    mc2 = TinyConfig.from_dict(json.loads(json.dumps(TinyConfig().to_dict())))
    resumed = train(TinyDenoiser(mc2), mc2, cfg2, toy_batch_fn, crash_dir, progress=False,
                    extra_metadata={"task": "toy"})

    assert int(resumed.state.step) == 60
    assert leaves_close(full.state.params, resumed.state.params, 1e-6)
    assert leaves_close(full.state.ema_params, resumed.state.ema_params, 1e-6)
    assert leaves_close(full.state.opt_state, resumed.state.opt_state, 1e-6)
    # Same data and noise order: the per-step losses agree, including the replayed steps
    # 21-27, and the resumed log holds each step once.
    a, b = read_metrics(full_dir), read_metrics(crash_dir)
    assert [r["step"] for r in b] == list(range(1, 61))
    np.testing.assert_allclose([r["loss"] for r in a], [r["loss"] for r in b], rtol=1e-6)
    assert ckpt.all_steps(crash_dir) == [40, 60]


def test_step_keys_depend_only_on_seed_and_step():
    k = np.asarray(jax.random.key_data(step_key(3, 5)))
    assert np.array_equal(k, np.asarray(jax.random.key_data(step_key(3, 5))))
    assert not np.array_equal(k, np.asarray(jax.random.key_data(step_key(3, 6))))
    assert not np.array_equal(k, np.asarray(jax.random.key_data(step_key(4, 5))))


def test_nan_loss_raises_and_keeps_last_checkpoint(tmp_path):
    # Same optimisation settings as LOOP_CFG (so the compiled step is reused), another seed.
    cfg = dataclasses.replace(LOOP_CFG, seed=11, log_every=4, checkpoint_every=4, val_every=0)
    bad_step = 10  # 0-based index: the 11th step; checkpoint 12 must not be written
    bad_key = jax.random.key_data(jax.random.split(step_key(cfg.seed, bad_step))[0])

    def nan_batch_fn(key, batch_size):
        b = toy_batch_fn(key, batch_size)
        hit = jnp.all(jax.random.key_data(key) == bad_key)
        return b._replace(x0=jnp.where(hit, jnp.nan, b.x0))

    out = str(tmp_path / "nan")
    with pytest.raises(NonFiniteLossError, match="non-finite loss") as info:
        train(TinyDenoiser(TinyConfig()), TinyConfig(), cfg, nan_batch_fn, out, progress=False)
    assert info.value.step == bad_step + 1
    assert info.value.last_checkpoint_step == 8
    assert "step 8" in str(info.value)
    assert ckpt.all_steps(out) == [4, 8]
    params, meta = ckpt.load_params_for_eval(out, TinyConfig(), model=TinyDenoiser(TinyConfig()))
    assert meta["step"] == 8
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(params))
    assert all(np.isfinite(r["loss"]) for r in read_metrics(out))


def test_public_train_step_is_pure_and_learns():
    cfg = LOOP_CFG  # the step compiled for the loop tests is reused
    model = TinyDenoiser(TinyConfig())
    batch = make_batch(jax.random.PRNGKey(0), 8)
    state0 = init_train_state(model, cfg, batch)
    step = make_train_step(model, cfg)
    key = jax.random.PRNGKey(7)
    s1, m1 = step(state0, batch, key)
    s1b, m1b = step(state0, batch, key)
    assert float(m1["loss"]) == float(m1b["loss"]) and int(s1.step) == 1
    assert leaves_close(s1.params, s1b.params, 0)
    assert float(m1["lr"]) == 0.0  # first step of the warm-up
    s = s1
    for i in range(10):
        s, m = step(s, batch, key)  # same batch and noise: the loss must go down
    assert float(m["loss"]) < float(m1["loss"])
    assert np.isfinite(float(m["grad_norm"]))


def test_x0_prediction_targets_the_clean_generated_channels():
    """With prediction="x0" the loss is the masked MSE to x0's generated channels: a model that
    returns exactly those channels has zero loss, one returning the noise does not."""
    import jax.numpy as jnp
    from diffplan.schedule import cosine_schedule
    from diffplan.train import Batch, TrainConfig, diffusion_loss

    x0 = jax.random.uniform(jax.random.PRNGKey(0), (4, 8, 8, 5), minval=-1, maxval=1)
    batch = Batch(x0=x0, tokens=jnp.ones((4, 3), jnp.int32), loss_mask=jnp.ones((4, 8, 8, 2)))
    ab = cosine_schedule(100).alphas_cumprod

    def oracle(variables, x_t, t, tokens):
        return x0[..., 3:]

    loss, _ = diffusion_loss(None, oracle, batch, jax.random.PRNGKey(1), ab, 2, "x0")
    assert float(loss) == 0.0
    loss_eps, _ = diffusion_loss(None, oracle, batch, jax.random.PRNGKey(1), ab, 2, "eps")
    assert float(loss_eps) > 0.1
    with pytest.raises(ValueError, match="prediction"):
        TrainConfig(prediction="v")


def test_draw_timesteps_uniform_is_the_papers_draw_and_power_skews_to_noisy():
    from diffplan.losses import draw_timesteps

    key = jax.random.PRNGKey(7)
    np.testing.assert_array_equal(  # power 1: exactly the uniform draw it replaced
        np.asarray(draw_timesteps(key, 64, 10)),
        np.asarray(jax.random.randint(key, (64,), 0, 10, dtype=jnp.int32)))
    n, T = 200_000, 10
    for power in (0.5, 2.0, 3.0):
        t = np.asarray(draw_timesteps(key, n, T, power))
        assert t.dtype == np.int32 and t.min() >= 0 and t.max() <= T - 1
        # P(t < k) = (k / T) ** power, checked against the closed form (4 sigma)
        for k in (2, 5, 8):
            p = (k / T) ** power
            assert abs(np.mean(t < k) - p) < 4 * np.sqrt(p * (1 - p) / n)


def test_timestep_power_config_and_loss():
    cfg = small_cfg(timestep_power=3.0)
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert "timestep_power" not in small_cfg().to_dict()  # old checkpoints compare equal
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="timestep_power"):
            small_cfg(timestep_power=bad)
    x0 = jax.random.uniform(jax.random.PRNGKey(0), (64, 4, 4, 3), minval=-1, maxval=1)
    batch = Batch(x0=x0, tokens=jnp.ones((64, 3), jnp.int32), loss_mask=jnp.ones((64, 4, 4, 2)))
    ab = cosine_schedule(10).alphas_cumprod
    _, aux = diffusion_loss(None, lambda v, x, t, k: x[..., 1:], batch, jax.random.PRNGKey(1),
                            ab, 2, "x0", timestep_power=4.0)
    assert np.mean(np.asarray(aux["t"]) >= 8) > 0.4  # uniform: 0.2


# ------------------------------------------------------------------------------- the one loop

def _quadratic_run():
    """A state of one vector pulled towards a random target each step (fast to compile)."""
    from diffplan.train import TrainState

    def init_fn():
        w = jnp.ones(3, jnp.float32)
        return TrainState(params={"w": w}, ema_params={"w": w}, opt_state=(),
                          step=jnp.zeros((), jnp.int32))

    def step_fn(state, key, data):
        target = jax.random.normal(key, (3,)) * data
        w = state.params["w"] - 0.1 * (state.params["w"] - target)
        loss = jnp.mean((w - target) ** 2)
        return (TrainState(params={"w": w}, ema_params={"w": 0.5 * w}, opt_state=(),
                           step=state.step + 1), {"loss": loss, "w0": w[0]})

    return init_fn, step_fn


def test_fit_runs_any_state_logs_checkpoints_and_resumes_bit_exactly(tmp_path):
    import shutil

    from diffplan.train import fit, mean_metrics, run_metadata

    init_fn, step_fn = _quadratic_run()
    meta = run_metadata(None, {"size": 3}, {"lr": 0.1, "log_every": 2}, {"w": [3]},
                        {"run": "quadratic"})
    assert meta["model_config_class"] is None and meta["model_class"] == "builtins:NoneType"
    kw = dict(steps=10, seed=4, metadata=meta, data=jnp.float32(1.0), checkpoint_every=4,
              log_every=2, progress=False)
    out = str(tmp_path / "fit")
    kw.update(validate=lambda s: {"val": float(s.params["w"].sum())}, validate_every=5)
    calls = []
    res = fit(step_fn, init_fn, out_dir=out, callback=lambda s, r: calls.append(s), **kw)
    recs = read_metrics(out)
    assert [r["step"] for r in recs] == [2, 4, 5, 6, 8, 10] and calls == [2, 4, 5, 6, 8, 10]
    assert [r["step"] for r in recs if "val" in r] == [5, 10]
    assert set(recs[0]) == {"step", "loss", "w0", "steps_per_sec", "wall_time"}
    assert res.last_record == recs[-1] and int(res.state.step) == 10 and res.wall_time > 0
    assert ckpt.all_steps(out) == [8, 10]
    with open(os.path.join(out, "config.json")) as f:
        assert json.load(f) == meta
    params, stored = ckpt.load_params_for_eval(out)  # the state's ema_params
    np.testing.assert_array_equal(params["w"], 0.5 * np.asarray(res.state.params["w"]))
    assert stored["last_loss"] == recs[-1]["loss"]
    # Keys are step_key(seed, i): the same run by hand gives the same state.
    state = init_fn()
    for i in range(10):
        state, _ = jax.jit(step_fn)(state, step_key(4, i), jnp.float32(1.0))
    np.testing.assert_array_equal(state.params["w"], res.state.params["w"])
    # Resuming from step 8 replays steps 9-10 exactly; a finished run returns at once.
    cut = str(tmp_path / "cut")
    shutil.copytree(out, cut)
    shutil.rmtree(os.path.join(cut, "10"))
    again = fit(step_fn, init_fn, out_dir=cut, **kw)
    np.testing.assert_array_equal(again.state.params["w"], res.state.params["w"])
    strip = lambda rs: [{k: v for k, v in r.items() if k not in ("wall_time", "steps_per_sec")}
                        for r in rs]
    assert strip(read_metrics(cut)) == strip(recs)
    done = fit(step_fn, init_fn, out_dir=cut, **kw)
    assert done.last_record is None and int(done.state.step) == 10
    with pytest.raises(ConfigMismatchError, match=r"train_config\.lr"):
        fit(step_fn, init_fn, out_dir=cut, **dict(kw, metadata=dict(meta, train_config={
            "lr": 0.2, "log_every": 2})))
    assert mean_metrics([{"a": np.float32(1), "b": np.float32(2)},
                         {"a": np.float32(2), "b": np.float32(4)}]) == {"a": 1.5, "b": 3.0}


def test_fit_stops_at_the_first_non_finite_metric_before_any_checkpoint(tmp_path):
    """A NaN loss at step 6 (of 12; checkpoints every 4, no log before the end) is found at
    the next check point (step 8), before checkpoint 8 is written."""
    from diffplan.train import fit, run_metadata

    init_fn, step_fn = _quadratic_run()

    def nan_at_6(state, key, nan):
        new, metrics = step_fn(state, key, jnp.float32(1.0))
        return new, dict(metrics, loss=jnp.where(state.step == 5, nan, metrics["loss"]))

    out = str(tmp_path / "nan")
    with pytest.raises(NonFiniteLossError, match=r"non-finite loss or metrics \(loss\) at step 6 "
                                                r"\(detected at step 8.*last good checkpoint "
                                                r"is step 4") as info:
        fit(nan_at_6, init_fn, steps=12, seed=0, out_dir=out,
            metadata=run_metadata(None, {}, {}, {"w": [3]}), data=jnp.float32(jnp.nan),
            checkpoint_every=4, log_every=100, progress=False)
    assert info.value.step == 6 and info.value.last_checkpoint_step == 4
    assert ckpt.all_steps(out) == [4] and not os.path.exists(os.path.join(out, "metrics.jsonl"))


def test_run_metadata_refuses_what_json_cannot_hold():
    from diffplan.train import run_metadata

    model = TinyDenoiser(TinyConfig())
    meta = run_metadata(model, TinyConfig(), {"lr": 1}, {"x": [1, 2]}, {"k": (1, 2)})
    assert meta["model_class"].endswith("toy_denoiser:TinyDenoiser")
    assert meta["model_config_class"].endswith("toy_denoiser:TinyConfig")
    assert meta["extra"] == {"k": [1, 2]} and meta["model_config"] == TinyConfig().to_dict()
    with pytest.raises(ValueError, match="JSON-serialisable"):
        run_metadata(model, TinyConfig(), {}, {}, {"bad": object()})
