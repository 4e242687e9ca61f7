"""The grid-world benchmark end to end on a tiny configuration (its numbers are not checked:
speed lives in the benchmark's output, never in tests), and that it times what it says."""
import json
import os

import numpy as np
import pytest

from experiments.bench import gridworld as bench_gridworld

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_bench_gridworld_tiny_run_writes_every_row(tmp_path):
    out = tmp_path / "bench.json"
    code = bench_gridworld.main(["--settings", "p_mo2g", "--episodes", "8", "--batch-sizes", "2,4",
                                 "--work", "200", "--repeats", "1", "--json", str(out)])
    assert code == 0
    data = json.loads(out.read_text())
    kinds = [(r["kind"], r["batch"]) for r in data["rows"]]
    assert kinds == [("generation", 8), ("env", 2), ("env", 4), ("env (step only)", 4),
                     ("env (+features)", 4)]
    for row in data["rows"]:
        assert row["per_second"] > 0 and row["best_per_second"] >= row["per_second"] * 0.999
    # Targets apply to the target batch (4096) and the P-MO2G generation row only.
    assert data["rows"][0]["target"] == bench_gridworld.TARGET_EPISODES_PER_S
    assert all(r["target"] is None for r in data["rows"][1:])


def test_env_runner_checksum_is_the_xor_of_every_observation():
    """The timed loop reads every observation (so XLA cannot drop observe): its checksum equals
    the XOR-fold of the observations computed step by step here; "features" also folds the
    expanded feature channels."""
    import jax

    from envs.gridworld import env, episode
    from envs.gridworld.config import make_config

    config = make_config("p_mo2g")
    eps = episode.generate_batch(jax.random.PRNGKey(3), config, 4)
    state = jax.vmap(lambda e: env.reset(e, config))(eps)
    actions = np.random.default_rng(0).integers(0, 4, (5, 4)).astype(np.int32)
    expected = {"observe": None, "features": None}
    s = state
    for a in actions:
        s = jax.vmap(lambda st, ac: env.step(st, ac, config))(s, a)
        o = jax.vmap(lambda st: env.observe(st, config))(s)
        for measure, leaves in (("observe", [o.cells, o.visited, o.agent]),
                                ("features", [o.cells, o.features])):
            leaves = [np.asarray(x) for x in leaves]
            acc = expected[measure]
            expected[measure] = leaves if acc is None else [x ^ y for x, y in zip(acc, leaves)]
    for measure, acc in expected.items():
        checksum = sum(int(x.astype(np.int64).sum()) for x in acc)
        got = int(bench_gridworld._env_runner(config, measure)(state, actions)[1])
        assert got == checksum, measure


def test_bench_planner_tiny_run(tmp_path):
    """bench_planner end to end on 2 episodes (numbers not checked; the eager reference must
    play the same game: its episodes end)."""
    from experiments.bench import planner as bench_planner

    out = tmp_path / "planner.json"
    assert bench_planner.main(["--batch-sizes", "2", "--num-steps", "2", "--eager-full", "2",
                               "--eager-forward", "jit", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert [(r["method"], r["batch"]) for r in data["rows"]] == [
        ("jitted", 2), ("bound", 2), ("eager-jit", 2)]
    assert all(r["episodes_per_second"] > 0 for r in data["rows"])
    jitted, bound, eager = data["rows"]
    assert eager["speedup"] == pytest.approx(
        jitted["episodes_per_second"] / eager["episodes_per_second"])
    assert jitted["of_bound"] == pytest.approx(
        jitted["episodes_per_second"] / bound["episodes_per_second"])


def test_eager_variants_run_the_same_moves_and_calls():
    """The op-by-op eager loop (no jax.jit) and the compiled-forward one do the same work:
    one move of 2 episodes, 2 denoising steps each."""
    from diffplan import load_denoiser
    from experiments.bench import eager as bench_eager
    from experiments.gridworld.eval import eval_episodes
    from experiments.gridworld.spec import SPECS

    den = load_denoiser(os.path.join(REPO, "checkpoints", "compile_gridworld"))
    config = SPECS["p_mo2g"].grid_config()
    episodes = eval_episodes(config, 2, 3000)
    works = [bench_eager.eager_rollout(den, config, episodes, 2, 1, 0, forward)[1:3]
             for forward in ("jit", "op")]
    assert works[0] == works[1] == (2, 4)
    with pytest.raises(ValueError, match="forward must be one of"):
        bench_eager.eager_rollout(den, config, episodes, 2, 1, 0, "torch")


def test_bench_release_says_how_to_get_torch_when_absent(monkeypatch, capsys):
    """Without torch/diffusers (CI installs neither) the benchmark says how to get them, in one
    line, and exits 2."""
    import sys

    from experiments.bench import release as bench_release

    monkeypatch.setitem(sys.modules, "torch", None)
    assert bench_release.main([]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and '.[anchors]' in err[0]


def test_release_configuration_is_the_published_one():
    from experiments.bench import release as bench_release

    cfg = bench_release.RELEASE_CONFIG
    assert cfg["in_channels"] == 514 and cfg["block_out_channels"] == (256, 512, 1024)
    assert cfg["cross_attention_dim"] == 1024 and cfg["out_channels"] == 2
