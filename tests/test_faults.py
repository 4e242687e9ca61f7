"""Fault injection: training killed with SIGKILL at a random point resumes to the same weights
(bit for bit) as an uninterrupted run; corrupted or truncated checkpoints are reported and
training falls back to the previous good one; a full disk while checkpointing loses nothing
already saved; NaNs in the loss stop training with the last checkpoint intact."""
import glob
import os
import random
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan import checkpoint as ckpt
from diffplan.train import NonFiniteLossError, train
from toy_denoiser import TinyConfig, TinyDenoiser, toy_batch_fn

HERE = os.path.dirname(os.path.abspath(__file__))
WORKER = os.path.join(HERE, "fault_worker.py")
STEPS = 24


def _env():
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    cache = jax.config.jax_compilation_cache_dir
    if cache:
        env["DIFFPLAN_JAX_CACHE"] = cache
    return env


def _run(*args, timeout=300):
    return subprocess.run([sys.executable, WORKER, *map(str, args)], capture_output=True,
                          text=True, env=_env(), timeout=timeout)


def _load_npz(path):
    with np.load(path) as z:
        return [z[k] for k in sorted(z.files, key=lambda k: int(k.split("_")[1]))]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The reference: STEPS steps in one process."""
    d = tmp_path_factory.mktemp("full")
    res = _run(d / "run", STEPS, "--dump", d / "final.npz")
    assert res.returncode == 0, res.stderr[-2000:]
    return d / "run", _load_npz(d / "final.npz")


def test_sigkill_at_a_random_point_resumes_bit_exactly(uninterrupted, tmp_path):
    _, reference = uninterrupted
    out = tmp_path / "killed"
    kill_after = random.Random(os.getpid()).randint(6, STEPS - 4)  # a step, not a checkpoint
    proc = subprocess.Popen([sys.executable, WORKER, str(out), str(STEPS)],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            env=_env())
    deadline = time.time() + 300
    for line in proc.stdout:
        if line.strip() == f"step {kill_after}" or time.time() > deadline:
            proc.send_signal(signal.SIGKILL)
            break
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, "the worker finished before it was killed"
    saved = ckpt.all_steps(out)
    assert saved and saved[-1] < STEPS
    res = _run(out, STEPS, "--dump", tmp_path / "resumed.npz")
    assert res.returncode == 0, res.stderr[-2000:]
    resumed = _load_npz(tmp_path / "resumed.npz")
    assert len(resumed) == len(reference)
    for a, b in zip(resumed, reference):
        np.testing.assert_array_equal(a, b)  # bit-exact: same data order and optimizer state


def _largest_file(step_dir):
    files = [f for f in glob.glob(os.path.join(step_dir, "**", "*"), recursive=True)
             if os.path.isfile(f) and "/d/" in f]
    return max(files, key=os.path.getsize)


@pytest.mark.parametrize("damage", ["flip", "truncate", "delete"])
def test_damaged_checkpoint_is_reported_and_training_falls_back(uninterrupted, tmp_path,
                                                                damage):
    import shutil

    run_dir, reference = uninterrupted
    work = tmp_path / "run"
    shutil.copytree(run_dir, work)
    steps = ckpt.all_steps(work)
    assert steps == [STEPS - 4, STEPS]
    victim = _largest_file(work / str(STEPS))
    data = open(victim, "rb").read()
    if damage == "flip":
        b = bytearray(data)
        b[len(b) // 2] ^= 0x40
        open(victim, "wb").write(bytes(b))
    elif damage == "truncate":
        open(victim, "wb").write(data[: len(data) // 3])
    else:
        os.remove(victim)
    # Loading says what is wrong instead of returning wrong values.
    with pytest.raises(ckpt.CorruptCheckpointError, match="corrupted"):
        ckpt.load_params_for_eval(str(work))
    # The previous checkpoint is intact.
    ckpt.load_params_for_eval(str(work), step=STEPS - 4)
    # Training resumes from it (with a warning), redoes the last steps and ends where an
    # uninterrupted run ends.
    res = _run(work, STEPS, "--dump", tmp_path / "again.npz")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "resumed from step" in res.stderr and "corrupted" in res.stderr
    for a, b in zip(_load_npz(tmp_path / "again.npz"), reference):
        np.testing.assert_array_equal(a, b)
    assert ckpt.all_steps(work) == [STEPS - 4, STEPS]
    assert glob.glob(str(work / f"corrupt-{STEPS}-*"))


def test_full_disk_while_checkpointing_keeps_what_was_saved(tmp_path):
    out = tmp_path / "full_disk"
    res = _run(out, STEPS, "--limit-after", 5)
    assert res.returncode == 3, (res.returncode, res.stderr[-2000:])
    message = [l for l in res.stderr.splitlines() if l.startswith("CheckpointWriteError")]
    assert message and "could not write checkpoint step 8" in message[0]
    assert "the last good checkpoint is step 4" in message[0]
    # Nothing half-written is left that could pass for a checkpoint; step 4 loads.
    assert ckpt.all_steps(out) == [4]
    assert not [n for n in os.listdir(out) if n.startswith("8")]
    params, meta = ckpt.load_params_for_eval(str(out))
    assert meta["step"] == 4


def test_nan_in_the_loss_stops_training_and_keeps_the_last_checkpoint(tmp_path):
    """A batch with NaNs at step 7: a clear error naming the last good checkpoint (4), which
    still loads with finite values; a rerun with clean data resumes from it."""
    from fault_worker import config

    cfg = config(12)

    def nan_after_six(key, batch_size):
        b = toy_batch_fn(key, batch_size)
        return b._replace(x0=jnp.where(key_is_late(key), jnp.nan, b.x0))

    from diffplan.train import step_key
    late_keys = jnp.stack([jax.random.key_data(jax.random.split(step_key(cfg.seed, s))[0])
                           for s in range(6, 12)])

    def key_is_late(key):
        return jnp.any(jnp.all(late_keys == jax.random.key_data(key), axis=-1))

    out = str(tmp_path / "nan")
    with pytest.raises(NonFiniteLossError, match="last good checkpoint is step 4") as info:
        train(TinyDenoiser(TinyConfig()), TinyConfig(), cfg, nan_after_six, out,
              progress=False, tensorboard=False)
    assert info.value.step == 7
    assert ckpt.all_steps(out) == [4]
    params, _ = ckpt.load_params_for_eval(out)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(params))
    result = train(TinyDenoiser(TinyConfig()), TinyConfig(), cfg, toy_batch_fn, out,
                   progress=False, tensorboard=False)
    assert int(result.state.step) == 12
