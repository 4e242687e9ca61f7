"""A grid-world denoiser on pretrained text features end to end, tiny and untrained: --train
--text pretrained trains and checkpoints it (its batches' sentence ids assembled from the
training sentence table inside the step), the CLI loads and evaluates it in the natural
language too, try_instruction plans a user's own sentence with it and draws the figure; a
token-id checkpoint is refused the natural language, and try_instruction refuses what it
cannot do, each in one line. (The numbers of an untrained model mean nothing: only that
everything runs is checked.)"""
from __future__ import annotations

import os

import numpy as np
import pytest

from envs.gridworld import grammar
from envs.gridworld.sentences import FEATURE_TOKENS


def run_exit(capsys, fn, *args) -> str:
    """The one-line error (stderr) of a CLI call that exits with code 2."""
    with pytest.raises(SystemExit) as e:
        fn(*args)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    return err


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from experiments.gridworld.cli import main

    out = tmp_path_factory.mktemp("features")
    train_dir = str(out / "run")
    result = main("p_mo2g", ["--train", "--text", "pretrained", "--model-size", "tiny",
                             "--train-steps", "2", "--train-dir", train_dir, "--episodes", "2",
                             "--batch-size", "2", "--modes", "one_shot", "--language",
                             "natural", "--no-reference-agents", "--no-progress",
                             "--json", str(out / "result.json")])
    return train_dir, result, out


def test_train_checkpoint_and_evaluate_in_the_natural_language(trained):
    from diffplan.checkpoint import read_metadata

    train_dir, result, out = trained
    assert [row["language"] for row in result["rows"]] == ["natural"]
    assert result["rows"][0]["method"] == "one-shot, natural"
    assert os.path.isfile(out / "result.json")
    meta = read_metadata(train_dir)
    assert meta["step"] == 2
    assert meta["input_shapes"]["tokens"] == [1, FEATURE_TOKENS, 384]
    assert meta["model_config"]["context_dim"] == 384
    assert meta["model_config"]["vocab_size"] == len(grammar.CELL_TOKENS)
    extra = meta["extra"]
    assert extra["text"] == "pretrained" and extra["cell_tokens"] == list(grammar.CELL_TOKENS)
    assert extra["text_encoder"]["max_tokens"] == FEATURE_TOKENS
    assert extra["text_encoder"]["directory"] is None  # the shipped encoder
    assert "vocabulary" not in extra
    # Its cells are embedded by their names' features, written before the first step and
    # unchanged by training (no gradient, no weight decay): the checkpoint carries them.
    assert meta["model_config"]["cell_context"] is True
    assert meta["model_config"]["cell_lookup"] is True
    from diffplan.checkpoint import load_params_for_eval
    from envs.gridworld.sentences import cell_features

    params, _ = load_params_for_eval(train_dir)
    np.testing.assert_array_equal(np.asarray(params["frozen_cell_features"]),
                                  cell_features())


def test_try_instruction_plans_a_users_sentence(trained, tmp_path, capsys):
    from experiments.gridworld.try_instruction import main

    train_dir, _, _ = trained
    figure = str(tmp_path / "out.png")
    result = main(["First go to the apple, then find the pear north of it.", "--setting",
                   "p_mo2g", "--seed", "3", "--checkpoint", train_dir, "--figure", figure,
                   "--json", str(tmp_path / "out.json")])
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(("success", "failure")) and "denoiser calls" in out[0]
    assert os.path.getsize(figure) > 0
    assert set(result) >= {"success", "ordered", "moves", "denoiser_calls"}
    assert result["moves"] >= 0 and result["denoiser_calls"] >= 1


def test_one_line_refusals(trained, capsys):
    from experiments.gridworld.cli import main as grid_main
    from experiments.gridworld.try_instruction import main

    train_dir, _, _ = trained
    err = run_exit(capsys, grid_main, "p_mo2g", ["--language", "natural", "--episodes", "2",
                                                  "--no-progress", "--no-reference-agents"])
    assert "--language natural needs a denoiser on pretrained text features" in err
    err = run_exit(capsys, main, ["Put red on blue.", "--world", "kuka"])
    assert "experiments.try_instruction --world kuka" in err  # the Kuka world's own CLI
    err = run_exit(capsys, main, ["   ", "--checkpoint", train_dir])
    assert "empty" in err
    err = run_exit(capsys, main, ["apple " * 60, "--checkpoint", train_dir])
    assert f"over the limit of {FEATURE_TOKENS}" in err
    err = run_exit(capsys, main, ["Go to the apple.", "--checkpoint", "compile_gridworld"])
    assert "reads token ids" in err
    missing = os.path.join(str(train_dir), "nowhere")
    err = run_exit(capsys, main, ["Go to the apple.", "--checkpoint", missing])
    assert "--text pretrained" in err


def test_features_of_evaluation_episodes_are_their_rendered_texts(trained):
    """What the planner reads of an evaluation episode is the encoder's features of the text
    its phrasing renders (any language; here the held-out one)."""
    from envs.gridworld.config import make_config
    from envs.gridworld.sentences import episode_texts, instruction_encoder, with_features
    from experiments.gridworld.eval import eval_episodes

    episodes = eval_episodes(make_config("p_mo2g", language="unseen"), 6, 1000)
    filled = with_features(episodes, "p_mo2g", instruction_encoder())
    texts = episode_texts(episodes, "p_mo2g")
    assert texts == [grammar.decode(t) for t in np.asarray(episodes.tokens)]
    np.testing.assert_array_equal(filled.features, instruction_encoder().encode(texts))


def test_all_never_includes_the_sealed_natural_set():
    """--language all (e.g. on the validation seed) must not show the sealed set: it is
    measured once, by name."""
    from experiments.gridworld.text import languages_of

    for features in (False, True):
        assert "natural" not in languages_of("all", features)
        assert languages_of("all", features) == ("canonical", "paraphrased", "unseen")
    assert languages_of("natural", True) == ("natural",)


def test_a_training_table_longer_than_L_is_refused_in_one_line():
    """The grid world's training sentences in an encoder of L = 16 (the longest training
    instruction is longer): refused, naming the length and L."""
    from envs.gridworld.sentences import (instruction_encoder, longest_instruction,
                                          training_index, training_table)

    short = instruction_encoder(None, 16)
    with pytest.raises(ValueError) as e:
        training_table(short)
    index = training_index()
    longest = longest_instruction(index, short.table(index.sentences).length)
    assert longest > 16
    assert str(e.value) == (f"an instruction is {longest} wordpieces long, over the grid "
                            "world's L = 16")


def test_the_features_recipe_trains_5000_steps_by_default():
    """--text pretrained trains 5000 steps unless told (the token recipe 8000, the far
    denoiser's 10000 either way), and --help says so."""
    from experiments.gridworld.flags import build_parser
    from experiments.gridworld.spec import SPECS

    assert SPECS["p_mo2g"].default_train_steps("pretrained") == 5000
    assert SPECS["p_mo2g"].default_train_steps("tokens") == 8000
    assert SPECS["p_mo2g_far"].default_train_steps("pretrained") == 10000
    assert "default 8000; 5000 with --text pretrained" in " ".join(
        build_parser(SPECS["mo1g"]).format_help().split())


def test_mo1g_names_control_renames_the_goal_in_the_text(trained):
    """--control names in MO1G (no reference): a row on the episodes with a distractor in view,
    the goal's name in the rendered sentence replaced (what a features denoiser reads), with
    the share of them in which the agent stood on the named object before the true target."""
    from experiments.gridworld.cli import main

    train_dir, _, _ = trained
    result = main("mo1g", ["--checkpoint", train_dir, "--episodes", "4", "--batch-size", "4",
                           "--modes", "one_shot", "--control", "names", "--seed", "3",
                           "--no-reference-agents", "--no-progress"])
    rows = {row["method"]: row for row in result["rows"]}
    control = rows["one-shot, goal named as a visible distractor (control)"]
    assert control["control"] == "names" and 1 <= control["control_episodes"] <= 4
    share = control["named_first_percent"] * control["control_episodes"] / 100.0
    assert abs(share - round(share)) < 1e-6 and "one-shot" in rows  # a count of episodes
