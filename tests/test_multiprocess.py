"""Two local CPU processes (127.0.0.1, one device each) through JAX's real multi-controller path
(``jax.distributed``, gloo collectives), against one process (issue 55):

- the grid-world CLI writes the JSON rows (timings aside) and trajectories, byte for byte, of a
  one-process run;
- a sweep killed with ``kill -9`` (process 0, the coordinator) after its first configuration and
  run again resumes from that configuration's kept row and ends with the one-process rows and
  trajectories;
- data-parallel training of the toy denoiser, one process killed with ``kill -9`` mid-run and
  the run started again, resumes from its last checkpoint and logs the one-process loss curve
  (200 steps, same global batch) within 1e-5 relative.

Each (second) 2-process run goes on while this process computes the one-process reference. Every
child runs in its own session with a timeout and is killed at teardown, so a failure leaves no
process behind. Tiny models (an untrained tiny grid denoiser, the toy denoiser), few episodes,
and the grid programs shared by the CLI and the sweep (and by the persistent compilation cache).
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HERE = os.path.join(REPO, "tests")
TIMEOUT = 600
"""Seconds a 2-process run may take before it is killed and the test fails."""
TIMINGS = ("seconds", "wall_seconds", "compile_seconds", "devices")
"""Row fields that measure the run, not its result."""
GRID = ["--episodes", "32", "--batch-size", "16", "--num-steps", "2", "--no-progress"]
"""32 episodes: 16 per device with two processes (diffplan.planner.MIN_SUB_BATCH)."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Launcher:
    """Starts N processes of one command, each with --coordinator/--num-processes/--process-id,
    in sessions of their own; kills whatever is left at teardown."""

    def __init__(self, tmp_path):
        self.tmp_path = tmp_path
        self.procs: list[subprocess.Popen] = []
        self.env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONUNBUFFERED="1",
                        PYTHONPATH=os.pathsep.join([REPO, HERE]),
                        XLA_FLAGS="--xla_force_host_platform_device_count=1")
        if jax.config.jax_compilation_cache_dir:
            self.env["DIFFPLAN_JAX_CACHE"] = jax.config.jax_compilation_cache_dir

    def start(self, argv: list[str], name: str, n: int = 2) -> list[subprocess.Popen]:
        port, group = _free_port(), []
        for i in range(n):
            log = open(self.tmp_path / f"{name}.{i}.log", "w")
            group.append(subprocess.Popen(
                [sys.executable, *argv, "--coordinator", f"127.0.0.1:{port}",
                 "--num-processes", str(n), "--process-id", str(i)],
                cwd=REPO, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True))
            log.close()
        self.procs += group
        return group

    def log(self, name: str, i: int) -> str:
        return (self.tmp_path / f"{name}.{i}.log").read_text()

    def wait(self, group, name: str, timeout: float = TIMEOUT) -> None:
        deadline = time.monotonic() + timeout
        for p in group:
            try:
                p.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                self.kill(group)
                pytest.fail(f"{name} took over {timeout} s:\n" + self._tails(group, name))
        if any(p.returncode for p in group):
            pytest.fail(f"{name} failed {[p.returncode for p in group]}:\n"
                        + self._tails(group, name))

    def _tails(self, group, name):
        return "\n".join(f"--- process {i}\n" + self.log(name, i)[-3000:]
                         for i in range(len(group)))

    @staticmethod
    def kill(group) -> None:
        for p in group:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
        for p in group:
            p.wait()


@pytest.fixture
def launcher(tmp_path):
    launch = Launcher(tmp_path)
    yield launch
    Launcher.kill(launch.procs)


def _wait_for(condition, group, what: str, timeout: float = TIMEOUT) -> None:
    """Polls condition() until it holds; fails if a process ends first or on timeout."""
    deadline = time.monotonic() + timeout
    while not condition():
        if any(p.poll() is not None for p in group):
            pytest.fail(f"the run ended before {what}")
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} after {timeout} s")
        time.sleep(0.05)


@pytest.fixture(scope="module")
def untrained(tmp_path_factory) -> str:
    """An untrained tiny grid denoiser saved as a checkpoint (what --train writes, without the
    training: its rollouts are as good a test of equality and compile in seconds)."""
    from diffplan import checkpoint as ckpt
    from diffplan.denoiser import Denoiser
    from diffplan.train import checkpoint_metadata, init_train_state
    from experiments.gridworld.spec import SPECS

    spec = SPECS["p_mo2g"]
    out = str(tmp_path_factory.mktemp("multiprocess") / "tiny")
    model_config, recipe = spec.model_config("tiny"), spec.recipe()
    config = spec.train_config(0, 2, 100, "diffusion")
    model = Denoiser(model_config)
    metadata = checkpoint_metadata(model, model_config, config, recipe.init_batch(),
                                   {**recipe.metadata(), "model_size": "tiny"})
    state = init_train_state(model, config, recipe.init_batch())
    ckpt.save_checkpoint(out, 2, state.ema_params, metadata)
    return out


def _rows(path) -> list[str]:
    """Each row as JSON text without its timing fields."""
    with open(path) as f:
        rows = json.load(f)["rows"]
    return [json.dumps({k: v for k, v in r.items() if k not in TIMINGS}) for r in rows]


def _assert_same_arrays(a_path, b_path) -> None:
    a, b = np.load(a_path), np.load(b_path)
    assert a.files == b.files
    for key in a.files:
        assert (a[key].dtype, a[key].shape) == (b[key].dtype, b[key].shape), key
        assert a[key].tobytes() == b[key].tobytes(), f"{b_path}: {key} differs"


def test_two_processes_evaluate_like_one(untrained, tmp_path, launcher):
    from experiments.gridworld.cli import main

    args = ["--checkpoint", untrained, *GRID, "--modes", "on_the_fly", "--no-reference-agents"]
    two = tmp_path / "two"
    group = launcher.start(["-m", "experiments.compile_p_mo2g", *args, "--json",
                            str(two / "e.json"), "--trajectories", str(two / "e.npz")], "eval")
    main("p_mo2g", [*args, "--json", str(tmp_path / "e.json"),
                    "--trajectories", str(tmp_path / "e.npz")])
    launcher.wait(group, "eval")
    assert _rows(two / "e.json") == _rows(tmp_path / "e.json")
    _assert_same_arrays(tmp_path / "e.npz", two / "e.npz")
    assert "SR" in launcher.log("eval", 0) and "SR" not in launcher.log("eval", 1)
    assert sorted(os.listdir(two)) == ["e.json", "e.npz"]


def test_a_sweep_that_loses_a_process_resumes(untrained, tmp_path, launcher):
    from experiments.sweeping.cli import main

    args = ["--checkpoint", untrained, *GRID, "--modes", "on_the_fly,one_shot"]
    two = tmp_path / "two"
    out = ["--json", str(two / "s.json"), "--trajectories", str(two / "traj")]
    group = launcher.start(["-m", "experiments.sweep", *args, *out], "sweep")
    kept = two / "s.json.parts" / "config_000.json"
    _wait_for(kept.exists, group, "the first configuration's row")
    os.kill(group[0].pid, signal.SIGKILL)  # the coordinator, mid-way through configuration 2
    group[1].wait(60)  # JAX's runtime ends the other process once process 0 is gone
    first = json.loads(kept.read_text())["row"]
    group = launcher.start(["-m", "experiments.sweep", *args, *out], "again")
    main([*args, "--json", str(tmp_path / "s.json"), "--trajectories", str(tmp_path / "traj")])
    launcher.wait(group, "again")
    assert "resuming: 1 of 2 configurations already finished" in launcher.log("again", 0)
    result = json.loads((two / "s.json").read_text())
    assert result["rows"][0] == first  # kept, not run again
    assert _rows(two / "s.json") == _rows(tmp_path / "s.json")
    for name in ("config_000.npz", "config_001.npz"):
        _assert_same_arrays(tmp_path / "traj" / name, two / "traj" / name)
    assert not (two / "s.json.parts").exists()


def test_data_parallel_training_survives_a_kill_and_matches_one_process(tmp_path, launcher):
    import multiprocess_worker as worker
    from diffplan import checkpoint as ckpt

    two = tmp_path / "two"
    argv = [os.path.join(HERE, "multiprocess_worker.py"), str(two)]
    group = launcher.start(argv, "train")
    _wait_for(lambda: any(s >= 100 for s in ckpt.all_steps(str(two))), group,
              "the checkpoint of step 100")
    os.kill(group[1].pid, signal.SIGKILL)
    # Process 0's next all-reduce fails; JAX's runtime would end it after its heartbeat
    # timeout (100 s): a launcher (srun, this test) ends it at once.
    Launcher.kill(group)
    resumed = max(ckpt.all_steps(str(two)))
    group = launcher.start(argv, "again")
    worker.run(str(tmp_path / "one"))
    launcher.wait(group, "again")
    assert f"resume: {resumed}" in launcher.log("again", 0) and resumed >= 100
    curves = []
    for run in ("one", "two"):
        with open(tmp_path / run / "metrics.jsonl") as f:
            curves.append([json.loads(line) for line in f])
    one, two_ = curves
    assert [r["step"] for r in one] == [r["step"] for r in two_] == list(range(1, 201))
    np.testing.assert_allclose([r["loss"] for r in two_], [r["loss"] for r in one], rtol=1e-5)
    assert ckpt.latest_step(str(two)) == 200
