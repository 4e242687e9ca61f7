"""The clustered 95% interval (intervals.clustered_interval): the constraints of one Kuka episode
are one cluster, not independent trials."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from experiments.harness import intervals


def _oracle(successes, trials):
    """Plain-Python restatement: Kish's effective size from the ratio's cluster-robust
    variance, then Wilson's interval."""
    pairs = [(s, t) for s, t in zip(successes, trials) if t > 0]
    total = sum(t for _, t in pairs)
    p = sum(s for s, _ in pairs) / total
    if p in (0.0, 1.0):
        n_eff = len(pairs)
    else:
        robust = sum((s - p * t) ** 2 for s, t in pairs) / total ** 2
        deff = max(1.0, robust / (p * (1 - p) / total))
        n_eff = total / min(deff, total)
    z = 1.959964
    centre = (p + z * z / (2 * n_eff)) / (1 + z * z / n_eff)
    half = z * ((p * (1 - p) / n_eff + z * z / (4 * n_eff ** 2)) ** 0.5) / (1 + z * z / n_eff)
    return [100 * max(0.0, centre - half), 100 * min(1.0, centre + half)]


clusters = st.lists(st.tuples(st.integers(0, 3), st.integers(1, 3)).map(
    lambda st_: (min(st_), st_[1])), min_size=1, max_size=40)


@settings(max_examples=60, deadline=None)
@given(clusters)
def test_clustered_interval_matches_oracle_and_contains_the_rate(pairs):
    s, t = map(np.array, zip(*pairs))
    lo, hi = intervals.clustered_interval(s, t)
    np.testing.assert_allclose([lo, hi], _oracle(s, t), atol=1e-9)
    rate = 100 * s.sum() / t.sum()
    assert lo - 1e-9 <= rate <= hi + 1e-9
    # Never narrower than counting every constraint as an independent trial.
    wlo, whi = intervals.wilson_interval(s.sum(), t.sum())
    assert lo <= wlo + 1e-9 and hi >= whi - 1e-9


@settings(max_examples=30, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=50))
def test_clusters_of_one_trial_give_wilsons_interval(outcomes):
    s = np.array(outcomes, int)
    np.testing.assert_allclose(intervals.clustered_interval(s, np.ones_like(s)),
                               intervals.wilson_interval(s.sum(), len(s)), atol=1e-9)


def test_perfect_episodes_count_once_each():
    # 70 episodes of 3 constraints, all held: the interval of 70 trials, not of 210.
    lo, hi = intervals.clustered_interval(np.full(70, 3), np.full(70, 3))
    assert [lo, hi] == pytest.approx(intervals.wilson_interval(70, 70))
    assert lo < intervals.wilson_interval(210, 210)[0]
    # Whole episodes failing together widen the interval beyond the independent one.
    s = np.array([3] * 60 + [0] * 10)
    assert intervals.clustered_interval(s, np.full(70, 3))[0] < intervals.wilson_interval(180, 210)[0]


@pytest.mark.parametrize("s, t", [([2], [1]), ([-1], [2]), ([1, 1], [2])])
def test_clustered_interval_refuses_impossible_counts(s, t):
    with pytest.raises(ValueError, match="successes"):
        intervals.clustered_interval(s, t)
