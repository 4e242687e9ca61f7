"""Property-based tests (hypothesis) of the instruction tokenizer and of the experiment CLIs'
argument handling: any input either works or is refused with a clear one-line error."""
import string

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from envs.gridworld import grammar
from experiments.gridworld import flags as gridworld_flags, spec as gridworld_spec
from experiments.harness import core as harness

WORDS = [w for w in grammar.VOCAB if w not in grammar.SPECIAL_TOKENS]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from(WORDS), min_size=1, max_size=grammar.MAX_TOKENS))
def test_encode_decode_round_trip(words):
    ids = grammar.encode(" ".join(words))
    assert ids.shape == (grammar.MAX_TOKENS,) and ids.dtype == np.int32
    assert np.count_nonzero(ids) == len(words)
    np.testing.assert_array_equal(grammar.encode(grammar.decode(ids)), ids)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from(WORDS), max_size=5),
       st.text(alphabet=string.ascii_lowercase, min_size=1, max_size=12))
def test_unknown_words_are_named(words, stranger):
    if stranger in grammar.WORD_TO_ID:
        return
    with pytest.raises(ValueError, match="outside the vocabulary") as info:
        grammar.encode(" ".join(words + [stranger]))
    assert stranger in str(info.value)


@settings(max_examples=50, deadline=None)
@given(st.text(alphabet=" \t\n", max_size=5))
def test_empty_instructions_are_refused(blank):
    with pytest.raises(ValueError, match="empty"):
        grammar.encode(blank)


def test_too_long_and_special_tokens_are_refused():
    with pytest.raises(ValueError, match="more than max_tokens"):
        grammar.encode(" ".join(["apple"] * (grammar.MAX_TOKENS + 1)))
    with pytest.raises(ValueError, match="outside the vocabulary"):
        grammar.encode("go to the <pad>")


FLAG_VALUES = {
    "--episodes": st.integers(-3, 5).map(str) | st.just("x"),
    "--seed": st.integers(-2, 3).map(str) | st.just("1.5"),
    "--seeds": st.sampled_from(["1,2", "1,1", "a", "", "3"]),
    "--batch-size": st.integers(-1, 3).map(str),
    "--num-steps": st.integers(-1, 200).map(str),
    "--warm-num-steps": st.integers(-1, 5).map(str),
    "--warm-start-step": st.integers(-1, 5).map(str),
    "--modes": st.sampled_from(["on_the_fly", "two_shot", "", "one_shot,warm_start", ","]),
    "--noise": st.sampled_from(["fresh", "episode", "pink"]),
    "--train-steps": st.integers(-1, 5).map(str),
    "--num-figures": st.integers(-1, 3).map(str),
    "--checkpoint-every": st.integers(-1, 3).map(str),
    "--model-size": st.sampled_from(["tiny", "huge"]),
    "--json": st.sampled_from(["/", "out.json", ""]),
    "--trajectories": st.sampled_from(["t.npz", "t", "/"]),
}
SWITCHES = ["--train", "--no-progress", "--no-reference-agents"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(st.sampled_from(sorted(FLAG_VALUES)), st.none(), max_size=5)
       .flatmap(lambda d: st.fixed_dictionaries({k: FLAG_VALUES[k] for k in d})),
       st.lists(st.sampled_from(SWITCHES), unique=True))
def test_cli_arguments_are_accepted_or_refused_in_one_line(flags, switches):
    """Parsing and checking never raises anything but argparse's SystemExit(2) (one usage
    line and one error line on stderr); nothing is evaluated here."""
    import contextlib
    import io

    spec = gridworld_spec.SPECS["p_mo2g"]
    parser = gridworld_flags.build_parser(spec)
    argv = [x for k, v in flags.items() for x in (k, v)] + switches
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            args = parser.parse_args(argv)
            gridworld_flags.check_args(parser, args, spec)
            harness.parse_seeds(parser, args)
        except SystemExit as e:
            assert e.code == 2
            lines = err.getvalue().strip().splitlines()
            assert lines[-1].startswith(f"{parser.prog}: error:"), lines
            assert "Traceback" not in err.getvalue()
