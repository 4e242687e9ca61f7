"""Training never sees an evaluation episode (docs/DESIGN.md, "Seeds and evaluation hygiene"),
checked through the real training path: the episodes ``diffplan.train.train`` generates are
captured as it runs, they equal what ``envs.gridworld.training.training_episodes`` recomputes,
and that recomputation over the shipped model's whole run is compared with the evaluation
episodes of the validation and evaluation seeds."""
from __future__ import annotations

import collections
import types

import jax
import numpy as np
import pytest

from envs.gridworld import training
from envs.gridworld.episode import fingerprints

MIXTURE = (("p_mo2g", 2), ("mo1g", 1), ("1o1g", 1), ("p_mo2g_far", 2))
"""The paper's settings and p_mo2g_far (not in the shipped TRAINING_MIXTURE, but a mixture
may name it: its recomputed episodes must be the ones training generates too)."""
STEPS, BATCH, SEED = 3, 12, 5


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """setting -> Counter of the fingerprints of every episode a 3-step training generated."""
    from diffplan.denoiser import Denoiser, DenoiserConfig
    from diffplan.train import TrainConfig, train
    from envs.gridworld import grammar
    from envs.gridworld.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS

    seen = collections.defaultdict(collections.Counter)
    real_generate = training.generate

    def spy(key, config):
        episode = real_generate(key, config)

        def record(grid, agent, target, reference, tokens):
            n = int(np.size(agent)) // 2
            rows = types.SimpleNamespace(**{k: np.asarray(v).reshape(n, -1) for k, v in dict(
                grid=grid, agent=agent, target=target, reference=reference,
                tokens=tokens).items()})
            seen[config.setting].update(fingerprints(rows))

        jax.debug.callback(record, episode.grid, episode.agent, episode.target,
                           episode.reference, episode.tokens)
        return episode

    mp = pytest.MonkeyPatch()
    mp.setattr(training, "generate", spy)
    try:
        config = DenoiserConfig(vocab_size=len(grammar.VOCAB), max_tokens=grammar.MAX_TOKENS,
                                num_cond_channels=NUM_COND_CHANNELS,
                                num_gen_channels=NUM_GEN_CHANNELS, embed_dim=8, widths=(8,),
                                num_res_blocks=1, attn_levels=(), cross_attn_levels=(0,),
                                text_dim=8, text_layers=1, text_heads=2, groups=4, head_dim=4)
        recipe = training.Recipe(mixture=MIXTURE)
        train(Denoiser(config), config,
              TrainConfig(seed=SEED, steps=STEPS, batch_size=BATCH, warmup_steps=1,
                          num_gen_channels=NUM_GEN_CHANNELS, checkpoint_every=STEPS,
                          log_every=1),
              recipe.batch_fn(), str(tmp_path_factory.mktemp("disjoint")),
              init_batch=recipe.init_batch(), progress=False,
              tensorboard=False)
    finally:
        mp.undo()
    return seen


@pytest.mark.parametrize("setting", [name for name, _ in MIXTURE])
def test_recomputed_training_episodes_are_the_ones_training_generated(captured, setting):
    recomputed = training.training_episodes(setting, seed=SEED, steps=STEPS,
                                            batch_size=BATCH, mixture=MIXTURE, chunk=STEPS)
    count = dict(MIXTURE)[setting] * BATCH // sum(c for _, c in MIXTURE)
    assert sum(captured[setting].values()) == STEPS * count
    assert collections.Counter(fingerprints(recomputed)) == captured[setting]


def test_another_seed_or_step_count_gives_other_episodes(captured):
    """The comparison above can fail: a shifted seed recomputes other episodes."""
    other = training.training_episodes("p_mo2g", seed=SEED + 1, steps=STEPS, batch_size=BATCH,
                                       mixture=MIXTURE, chunk=STEPS)
    assert not set(fingerprints(other)) & set(captured["p_mo2g"])


def test_1o1g_episodes_seen_in_training_are_counted_and_left_out(tmp_path):
    """1O1G has 979,200 possible episodes and the shipped run drew 80,000: the CLI counts the
    evaluation episodes equal to a training episode and leaves them out of its rows and its
    trajectories (measured 86 of the 1000 episodes of seed 2001)."""
    import json
    import os

    from experiments.gridworld import cli as gridworld_cli, eval as ge
    from experiments.harness.core import CHECKPOINT_ROOT

    checkpoint = os.path.join(CHECKPOINT_ROOT, "compile_gridworld")
    episodes = ge.eval_episodes(training.make_config("1o1g"), 300, 2001)
    overlap = ge.training_overlap(checkpoint, "1o1g", episodes)
    seen = set(fingerprints(training.training_episodes(
        "1o1g", seed=0, steps=8000, batch_size=64, language="mixed"), instruction=False))
    assert overlap.tolist() == [f in seen for f in fingerprints(episodes, instruction=False)]
    assert 10 <= overlap.sum() <= 45  # ~8% of 300
    out = tmp_path / "r.json"
    traj = tmp_path / "t.npz"
    gridworld_cli.main("1o1g", ["--episodes", "300", "--seed", "2001", "--modes", "one_shot",
                                "--json", str(out), "--trajectories", str(traj),
                                "--no-progress", "--no-reference-agents"])
    result = json.loads(out.read_text())
    assert result["excluded_training_episodes"] == {"2001": int(overlap.sum())}
    kept = np.load(traj)
    assert len(kept["steps"]) == 300 - overlap.sum()
    rows = types.SimpleNamespace(**{k: kept[k] for k in ("grid", "agent", "target",
                                                          "reference")},
                                 tokens=np.asarray(episodes.tokens)[~overlap])
    assert not set(fingerprints(rows)) & seen


SHIPPED_RUNS = (("compile_gridworld", "mo1g"), ("compile_gridworld", "p_mo2g"),
                ("compile_gridworld_far", "p_mo2g_far"))
"""(shipped checkpoint, setting) whose evaluation rows count every episode: their whole training
runs are recomputed below (1O1G, whose world space is small, is the counted-and-left-out case
above)."""


@pytest.mark.parametrize("checkpoint,setting", SHIPPED_RUNS)
def test_no_validation_or_evaluation_world_is_a_training_world(checkpoint, setting):
    """Every episode of the shipped run, every step of it (its seed, steps, batch size,
    mixture and phrasing from the checkpoint's metadata), compared by world (grid, agent,
    target, reference; any wording) with the 1000 episodes of the validation seed and each
    evaluation seed: none is equal. The 1O1G test above is the control that this comparison
    finds an overlap where there is one."""
    import os

    from diffplan.checkpoint import read_metadata
    from experiments.gridworld import eval as ge
    from experiments.harness.core import CHECKPOINT_ROOT

    meta = read_metadata(os.path.join(CHECKPOINT_ROOT, checkpoint))
    mixture = tuple((name, int(count)) for name, count in meta["extra"]["mixture"])
    steps, batch = int(meta["step"]), int(meta["train_config"]["batch_size"])
    episodes = training.training_episodes(
        setting, seed=int(meta["train_config"]["seed"]), steps=steps, batch_size=batch,
        mixture=mixture, language=meta["extra"].get("language", "canonical"), chunk=2000)
    per_step = dict(mixture)[setting] * batch // sum(c for _, c in mixture)
    assert len(episodes.tokens) == steps * per_step  # the whole run, every step
    seen = set(fingerprints(episodes, instruction=False))
    assert len(seen) > 0.99 * steps * per_step  # distinct worlds: the digests discriminate
    for seed in (1000, 2001, 2002, 2003):
        evaluation = ge.eval_episodes(training.make_config(setting), 1000, seed)
        assert not set(fingerprints(evaluation, instruction=False)) & seen, seed
