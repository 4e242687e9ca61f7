"""A Kuka denoiser on pretrained text features (envs.kuka.sentences, the features recipe, the
CLIs' --text pretrained and --language natural): the table path equal to the text path bit for
bit on Kuka sentences, L measured over every phrasing set and filling (the sealed natural set
counted only), training sentence ids drawn from the training phrasings only (a planted
development, held-out or natural sentence refused), the one-line refusals, and a tiny end to
end run (--train --text pretrained of 2 steps of the tiny model, evaluated on the natural set:
the numbers of an untrained model mean nothing, only that everything runs is checked)."""
from __future__ import annotations

import json

import jax
import numpy as np
import pytest

import kuka_fixtures as kf
from diffplan import language
from diffplan.instruction import (InstructionEncoder, assemble_batch, instruction_lengths,
                                  split_sentences)
from envs.kuka import grammar, natural, sentences
from envs.kuka.sentences import FEATURE_TOKENS

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)

LANGUAGES = grammar.EVALUATION_LANGUAGES
PAIRS = ((1, 0), (3, 2))
"""Two fillings of every relation phrasing in the table-path test (green on red, yellow on
blue)."""


def one_line(excinfo) -> str:
    message = str(excinfo.value)
    assert "\n" not in message, message
    return message


def run_exit(capsys, fn, *args) -> str:
    """The last line on stderr of a CLI call that exits with code 2, checked to be one line
    (argparse prints its usage before it)."""
    with pytest.raises(SystemExit) as e:
        fn(*args)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def encoder(tmp_path_factory):
    from diffplan.pretrained_text import load_text_encoder

    return InstructionEncoder(load_text_encoder(), FEATURE_TOKENS,
                              cache_dir=str(tmp_path_factory.mktemp("text-features")))


def _episodes(column: str, language_name: str):
    """kf.BATCH episodes of a column in a language (the suite's compiled generator)."""
    return kf.episodes(column, 3, language_name)


# ------------------------------------------------------------------ the text and table paths

def ending(kind: str) -> list[int]:
    """The phrasings of a kind (the grammar's and the natural set's) that end their sentence:
    those a sentence table may hold."""
    return [k for k, p in enumerate(sentences._phrasings(kind))
            if p.endswith(sentences.SENTENCE_ENDS)]


def test_table_path_equals_text_path_on_kuka_sentences(encoder):
    """Every phrasing that ends its sentence (the grammar's, and the natural set's, some of
    two sentences) in two fillings: instructions assembled from the table equal the encoded
    text bit for bit. One that does not (natural lower case) is refused by the table."""
    every = {kind: ending(kind) for kind in sentences.KINDS}
    assert len(every["relation"]) == len(grammar.relation_phrasings()) - 5
    index = sentences.sentence_index(every, PAIRS)
    assert index.towers.shape[-1] == 2  # "See the {bottom} block? Put the {top} block on ..."
    table = encoder.table(index.sentences)
    rng = np.random.default_rng(0)
    phrasings, constraints, towers, texts = [], [], [], []
    for i in range(96):
        p = np.array([rng.choice(every["tower"])] + list(rng.choice(every["relation"], 3)),
                     np.int32)
        n = 1 + i % 3
        c = np.full((3, 2), -1, np.int32)
        c[:n] = [PAIRS[j % 2] for j in range(n)]
        tower = n == 1 and i % 2 == 0
        phrasings.append(p)
        constraints.append(c)
        towers.append(tower)
        texts.append(grammar.render(c, tower, [int(k) for k in p[1:n + 1]], int(p[0])))
    ids = jax.jit(jax.vmap(index.ids))(np.stack(phrasings), np.stack(constraints),
                                       np.array(towers))
    got = np.asarray(jax.jit(assemble_batch)(table, ids))
    want = encoder.encode(texts)
    assert got.shape == want.shape == (96, FEATURE_TOKENS, encoder.dim)
    np.testing.assert_array_equal(got, want)
    # Each id list is the text's sentences, in order.
    for row, text in zip(np.asarray(ids), texts):
        assert [index.sentences[r] for r in row if r >= 0] == split_sentences(text)
    lower_case = len(grammar.RELATION_TEMPLATES) + 5 * 5  # "put the {top} block on the ..."
    with pytest.raises(ValueError) as e:
        sentences.sentence_index({"relation": [0, lower_case]})
    assert "does not end its sentence" in one_line(e)


def test_evaluation_features_are_the_rendered_texts(encoder):
    """What the planner reads of an evaluation episode is the encoder's features of the text
    its phrasings render; in every grammar language that text is the tokens' own, and a
    natural-language episode's tokens are its canonical phrasing's."""
    for name in LANGUAGES:
        episodes = _episodes("stacking_single", name)
        texts = sentences.episode_texts(episodes)
        filled = sentences.with_features(episodes, encoder)
        assert filled.features.dtype == np.float32
        np.testing.assert_array_equal(filled.features, encoder.encode(texts))
        decoded = [grammar.decode(t) for t in np.asarray(episodes.tokens)]
        if name == language.NATURAL:
            assert not set(texts) & set(decoded)
            canonical = [grammar.render(c, True) for c in np.asarray(episodes.constraints)]
            assert decoded == canonical
        else:
            assert texts == decoded


def test_the_task_hands_the_planner_the_features_and_physics_carries_none(encoder):
    from envs.kuka.task import KukaTask

    episodes = sentences.with_features(_episodes("stacking_multi", "canonical"), encoder)
    one = jax.tree.map(lambda x: x[0], episodes)
    np.testing.assert_array_equal(KukaTask(text="features").tokens(one), one.features)
    np.testing.assert_array_equal(KukaTask().tokens(one), one.tokens)
    assert jax.eval_shape(KukaTask(text="features").reset, one).episode.features is None
    with pytest.raises(ValueError) as e:
        KukaTask(text="features").tokens(one.replace(features=None))
    assert "with_features" in one_line(e)
    with pytest.raises(ValueError) as e:
        KukaTask(text="words")
    assert "text must be one of" in one_line(e)


def test_the_longest_instruction_of_every_phrasing_set_fits_in_L(encoder):
    """L (FEATURE_TOKENS) was chosen on this count: the longest instruction (wordpieces, each
    sentence's [CLS] and [SEP]) of every phrasing set in every filling: the tower sentence and
    one relation, or three relations, each as long as its set's longest. Of the sealed natural
    set only the length of each rendered sentence is read."""
    longest = {}
    for name in LANGUAGES + (language.BROAD,):
        tower_pool, relation_pool = grammar.phrasing_pools(name)
        towers = max(encoder.length(grammar.tower_phrasings()[k]) for k in tower_pool)
        relations = max(encoder.length(grammar.render([pair], False, [int(k)]))
                        for k in relation_pool for pair in sentences.PAIRS)
        longest[name] = max(towers + relations, grammar.MAX_RELATIONS * relations)
    assert longest.pop(language.NATURAL) == 54
    assert max(longest.values()) == 45  # the grammar's phrasings
    assert FEATURE_TOKENS >= 54 + 16  # room for a person's own wording
    # The training table's own check counts the same way and refuses what does not fit.
    index = sentences.training_index()
    lengths = np.array([encoder.length(s) for s in index.sentences])
    assert sentences.longest_instruction(index, lengths) == longest[language.BROAD]
    assert instruction_lengths(lengths, index.towers).max() == 11
    short = InstructionEncoder(encoder.encoder, 40, cache_dir=encoder.cache_dir)
    with pytest.raises(ValueError) as e:
        sentences.training_table(short)
    assert "is 45 wordpieces long, over the Kuka world's L = 40" in one_line(e)


# ------------------------------------------------------------------ training

def test_training_draws_only_training_sentences():
    index = sentences.training_index()
    assert sentences.training_templates() == {"tower": (0, 1, 2, 3),
                                              "relation": tuple(range(8)) + grammar.EXTRA}
    assert len(index.sentences) == 4 + 15 * 12
    forbidden = sentences.never_trained_sentences()
    assert set(forbidden.values()) == {language.DEVELOPMENT, language.HELDOUT,
                                       language.NATURAL}
    assert not set(index.sentences) & set(forbidden)
    # Planted: a natural, a development and a held-out sentence or phrasing is refused.
    planted = grammar.render([(1, 0)], False, [len(grammar.RELATION_TEMPLATES)])
    assert planted == natural.relation_sentences()[0].format(top="green", bottom="red")
    with pytest.raises(ValueError) as e:
        sentences.check_training_sentences(list(index.sentences) + [planted])
    assert "natural phrasing's" in one_line(e)
    for kind, k in (("relation", 8), ("relation", 19), ("tower", 4),
                    ("relation", len(grammar.RELATION_TEMPLATES)),
                    ("tower", len(grammar.TOWER_TEMPLATES))):
        with pytest.raises(ValueError) as e:
            sentences.check_training_templates({kind: [0, k]})
        assert "not training phrasings" in one_line(e)
    # A phrasing the index does not hold maps to no sentence.
    rows = index.ids(np.array([4, 8, 19, len(grammar.RELATION_TEMPLATES)]),
                     np.array([[1, 0], [2, 1], [3, 2]]), True)
    assert np.all(np.asarray(rows) == -1)
    # Training refuses every never-trained language.
    from envs.kuka.training import Recipe

    for name in (language.NATURAL, language.HELDOUT, language.DEVELOPMENT):
        with pytest.raises(ValueError):
            Recipe(specs=(("stacking", False, name),), text="pretrained")


@pytest.mark.parametrize("name", ["canonical", "paraphrased", language.BROAD])
def test_training_sentence_ids_are_the_episodes_instructions(name):
    """The sentence ids a training example carries (envs.kuka.training.
    instruction_sentence_ids) are its instruction's sentences, none lost, in every column and
    training language."""
    from envs.kuka.training import instruction_sentence_ids

    index = sentences.training_index()
    ids_of = jax.jit(jax.vmap(instruction_sentence_ids))
    for column in ("stacking_single", "stacking_multi"):  # the tower sentence; 3 relations
        episodes = _episodes(column, name)
        for ids, tokens in zip(np.asarray(ids_of(episodes)), np.asarray(episodes.tokens)):
            assert " ".join(index.sentences[r] for r in ids if r >= 0) == grammar.decode(tokens)


def test_the_features_recipe_and_its_refusals():
    from envs.kuka.training import Recipe

    recipe = Recipe(text="pretrained")
    shapes = recipe.init_batch()
    assert shapes.tokens.shape == (recipe.batch_multiple, 4) and shapes.token_labels is None
    assert shapes.tokens.dtype == np.int32
    meta = recipe.metadata()
    assert meta["text"] == "pretrained" and meta["cell_tokens"] == list(grammar.CELL_TOKENS)
    assert meta["text_encoder"]["max_tokens"] == FEATURE_TOKENS and "vocabulary" not in meta
    assert Recipe().metadata()["vocabulary"] == list(grammar.VOCAB)  # token ids as before
    assert Recipe().sentences() is None
    with pytest.raises(ValueError) as e:
        Recipe(text="pretrained", role_loss_weight=0.5)
    assert "role_loss_weight" in one_line(e)
    with pytest.raises(ValueError) as e:
        Recipe(text="words")
    assert "text must be one of" in one_line(e)


# ------------------------------------------------------------------ the CLIs

def test_all_never_includes_the_sealed_natural_set():
    """--language all (e.g. on the validation seed) must not show the sealed set: it is
    measured once, by name."""
    from experiments.kuka.text import languages_of

    assert languages_of("all") == grammar.LANGUAGES
    assert language.NATURAL not in languages_of("all") + languages_of("both")
    assert languages_of("natural") == (language.NATURAL,)


@pytest.mark.parametrize("argv, message", [
    (["--language", "natural", "--policy", "expert"], "it needs --policy planner"),
    (["--language", "natural", "--baselines", "bc"], "--baselines reads token ids"),
    (["--language", "natural", "--reader", "."], "--reader reads token ids"),
    (["--text", "pretrained", "--policy", "expert"], "--text selects the planner's denoiser"),
])
def test_flags_refuse_what_cannot_read_natural_sentences(argv, message, capsys):
    from experiments.kuka.cli import main

    assert message in run_exit(capsys, main, "stacking", argv + ["--no-progress"])


def test_a_token_checkpoint_is_refused_the_natural_set(capsys, tmp_path):
    from experiments.kuka.cli import main

    err = run_exit(capsys, main, "stacking", ["--language", "natural", "--no-progress"])
    assert "--language natural needs a denoiser on pretrained text features" in err
    err = run_exit(capsys, main, "rearrangement", ["--text", "pretrained", "--checkpoint",
                                                   str(tmp_path / "none"), "--no-progress"])
    assert "kuka_rearrangement --train --text pretrained" in err


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """--train --text pretrained (2 steps, tiny), evaluated on the natural set (on-the-fly,
    settle 0: the features path only; the settling step is the token runs')."""
    from experiments.kuka.cli import main

    out = tmp_path_factory.mktemp("kuka_features")
    train_dir = out / "run"
    result = main("stacking", [
        "--train", "--text", "pretrained", "--model-size", "tiny", "--train-steps", "2",
        "--train-dir", str(train_dir), "--episodes", str(kf.BATCH), "--batch-size",
        str(kf.BATCH), "--language", "natural", "--modes", "on_the_fly", "--settle", "0",
        "--seed", "3", "--json", str(out / "r.json"), "--states", str(out / "s.npz"),
        "--no-progress"])
    return train_dir, result, out


def test_train_checkpoint_and_evaluate_in_the_natural_language(trained):
    from diffplan.checkpoint import read_metadata
    from diffplan.instruction import encoder_record
    from experiments.kuka import spec as ks

    train_dir, result, out = trained
    assert json.loads((out / "r.json").read_text()) == json.loads(json.dumps(result))
    main_row, *rows = result["rows"]
    assert main_row["method"] == "planner on-the-fly, natural"
    assert [(r["language"], r["column"]) for r in rows] == [("natural", "single"),
                                                           ("natural", "multi")]
    for row in rows:
        assert row["episodes"] == kf.BATCH and row["denoiser_calls_per_episode"] == \
            pytest.approx(10.0 * row["placements_per_episode"])
    meta = read_metadata(str(train_dir))
    shipped = sentences.instruction_encoder()  # the shipped encoder: its directory None
    assert {key: meta["extra"].get(key) for key in ("text", "cell_tokens", "text_encoder",
                                                    "vocabulary")} == {
        "text": "pretrained", "cell_tokens": list(grammar.CELL_TOKENS), "vocabulary": None,
        "text_encoder": encoder_record(shipped.encoder, FEATURE_TOKENS)}
    assert (meta["step"], meta["input_shapes"]["tokens"], meta["model_config"]["context_dim"],
            meta["model_config"]["vocab_size"]) == (2, [1, FEATURE_TOKENS, 384], 384, 5)
    denoiser = ks.load_checked(str(train_dir), ks.NUM_STEPS, "stacking")
    assert denoiser.model_config == ks.model_config("tiny", "pretrained")
    # The states file writes each episode's own (natural) text.
    with np.load(out / "s.npz") as states:
        written = [str(t) for t in states["instruction"]]
    from envs.kuka.config import TaskSpec
    from experiments.kuka.eval import generate_episodes

    expected = []
    for multi in (False, True):
        episodes = generate_episodes(TaskSpec("stacking", multi, "natural"), kf.BATCH, 3,
                                     kf.BATCH)
        expected += sentences.episode_texts(episodes)
    assert written == expected


def test_features_checkpoint_refusals(trained, capsys, tmp_path, monkeypatch):
    """The reader restates token ids: refused with a features checkpoint, in one line; so is a
    features checkpoint whose recorded encoder hashes differ from the encoder's files."""
    from diffplan import checkpoint
    from experiments.harness.text import checkpoint_encoder
    from experiments.kuka import spec as ks
    from experiments.kuka.cli import main

    train_dir, _, _ = trained
    err = run_exit(capsys, main, "stacking", ["--checkpoint", str(train_dir), "--reader",
                                              str(tmp_path), "--no-progress"])
    assert "--reader restates an instruction's token ids" in err
    denoiser = ks.load_checked(str(train_dir), ks.NUM_STEPS, "stacking")
    assert checkpoint_encoder(str(train_dir), denoiser).max_tokens == FEATURE_TOKENS
    meta = checkpoint.read_metadata(str(train_dir))
    record = meta["extra"]["text_encoder"]
    forged = dict(meta, extra=dict(meta["extra"], text_encoder=dict(
        record, sha256={name: "0" * 64 for name in record["sha256"]})))
    monkeypatch.setattr(checkpoint, "read_metadata", lambda *args, **kwargs: forged)
    err = run_exit(capsys, checkpoint_encoder, str(train_dir), denoiser)
    assert f"the checkpoint {train_dir}'s text encoder" in err
