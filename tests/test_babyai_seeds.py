"""The BabyAI seed streams (envs/babyai/seeds.py): evaluation episodes, training layouts and
generate(key) reset minigrid with seeds from disjoint ranges, checked from the functions
themselves; a planted overlap is caught. The training layouts the cache holds
(envs.babyai.training) are checked against the evaluation seeds too."""
from __future__ import annotations

import numpy as np
import pytest

from envs.babyai import seeds

EVAL_SEEDS = (1000, 2001, 2002, 2003)


def test_the_streams_are_disjoint_by_construction():
    ranges = seeds.check_disjoint()
    assert ranges == {"evaluation": (0, 2 ** 31 - 1), "training": (2 ** 31, 2 ** 32 - 1),
                      "key": (2 ** 32, 2 ** 33 - 1)}


def test_the_seeds_the_evaluation_and_training_use_never_coincide():
    evaluation = {seeds.evaluation_seed(s, i) for s in EVAL_SEEDS for i in range(10_000)}
    training = {seeds.training_seed(j) for j in range(100_000)}
    assert len(evaluation) == 40_000 and len(training) == 100_000
    assert not evaluation & training


def test_control_a_planted_overlap_is_caught():
    planted = dict(seeds.STREAMS, training=(lambda j: 2 ** 30 + j, (2 ** 31,)))
    with pytest.raises(ValueError, match="overlap"):
        seeds.check_disjoint(planted)
    # an evaluation seed that reaches past its range is caught too
    wide = dict(seeds.STREAMS, evaluation=(lambda s, i: s * 2 ** 21 + i, (2 ** 11, 2 ** 20)))
    with pytest.raises(ValueError, match="'evaluation'.*'training'|'training'.*'evaluation'"):
        seeds.check_disjoint(wide)


@pytest.mark.parametrize("call, args, needle", [
    (seeds.evaluation_seed, (2 ** 11, 0), "seed must be in"),
    (seeds.evaluation_seed, (1000, 2 ** 20), "episode index must be in"),
    (seeds.evaluation_seed, (-1, 0), "seed must be in"),
    (seeds.training_seed, (2 ** 31,), "training layout index"),
    (seeds.key_seed, (2 ** 32,), "key bits"),
])
def test_out_of_range_arguments_are_refused_in_one_line(call, args, needle):
    with pytest.raises(ValueError, match=needle) as info:
        call(*args)
    assert "\n" not in str(info.value)


def test_numpy_integers_are_accepted():
    assert seeds.evaluation_seed(np.int64(3), np.int32(5)) == 3 * 2 ** 20 + 5
