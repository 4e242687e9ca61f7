"""envs.gridworld.metrics against hand-computed cases."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from envs.gridworld import metrics


def _path_mask(cells, size=4):
    m = np.zeros((size, size), bool)
    for r, c in cells:
        m[r, c] = True
    return m


def test_executed_cells_respects_steps():
    pos = np.array([[[0, 0], [0, 1], [0, 2], [3, 3]]])  # the 4th entry is beyond steps
    mask = metrics.executed_cells(pos, np.array([2]), 4)
    np.testing.assert_array_equal(mask[0], _path_mask([(0, 0), (0, 1), (0, 2)]))


def test_two_episodes_by_hand():
    # Episode 0: expert (0,0)->(0,1)->(0,2); agent walks it exactly and succeeds.
    # Episode 1: expert (0,0)->(1,0)->(2,0); agent goes (0,0)->(0,1) and stops: fails.
    positions = np.array([
        [[0, 0], [0, 1], [0, 2], [0, 2]],
        [[0, 0], [0, 1], [0, 1], [0, 1]],
    ])
    steps = np.array([2, 3])
    target = np.array([[0, 2], [2, 0]])
    expert = np.stack([_path_mask([(0, 0), (0, 1), (0, 2)]), _path_mask([(0, 0), (1, 0), (2, 0)])])
    out = metrics.trajectory_metrics(positions, steps, target, expert)
    assert out["SR"] == pytest.approx(50.0)
    # GD: 0 and |(0,1)-(2,0)| = sqrt(5).
    assert out["GD"] == pytest.approx(np.sqrt(5) / 2)
    # Executed cells: 3 + 2 = 5; true positives: 3 + 1 = 4; expert cells: 6.
    assert out["path_precision"] == pytest.approx(80.0)
    assert out["path_recall"] == pytest.approx(400 / 6)
    p, r = 80.0, 400 / 6
    assert out["path_f1"] == pytest.approx(2 * p * r / (p + r))
    assert out["mean_steps"] == pytest.approx(2.5)
    assert "SR_ordered" not in out


def test_sr_ordered_needs_the_reference_first():
    positions = np.array([
        [[0, 0], [1, 0], [1, 1], [1, 1]],  # via reference (1,0) to target (1,1)
        [[0, 0], [0, 1], [1, 1], [1, 1]],  # straight to the target, reference skipped
    ])
    steps = np.array([2, 2])
    target = np.array([[1, 1], [1, 1]])
    reference = np.array([[1, 0], [1, 0]])
    expert = np.stack([_path_mask([(0, 0), (1, 0), (1, 1)])] * 2)
    out = metrics.trajectory_metrics(positions, steps, target, expert, reference)
    assert out["SR"] == pytest.approx(100.0)
    assert out["SR_ordered"] == pytest.approx(50.0)


def test_reference_after_the_end_does_not_count():
    positions = np.array([[[0, 0], [0, 1], [1, 1], [1, 0]]])  # (1,0) visited after the end
    out = metrics.trajectory_metrics(positions, np.array([2]), np.array([[1, 1]]),
                                     _path_mask([(0, 0), (1, 0), (1, 1)])[None],
                                     np.array([[1, 0]]))
    assert out["SR_ordered"] == 0.0


def test_plan_metrics_threshold_at_zero():
    plan = np.full((1, 4, 4), -1.0)
    plan[0, 0, 0] = plan[0, 0, 1] = 0.5
    plan[0, 3, 3] = 0.1
    expert = _path_mask([(0, 0), (0, 1), (0, 2)])[None]
    out = metrics.plan_metrics(plan, expert)
    assert out["plan_precision"] == pytest.approx(200 / 3)
    assert out["plan_recall"] == pytest.approx(200 / 3)


def test_empty_predictions_give_zero_not_nan():
    p, r, f = metrics.precision_recall_f1(np.zeros((1, 4, 4), bool), np.ones((1, 4, 4), bool))
    assert (p, r, f) == (0.0, 0.0, 0.0)


# ------------------------------------------------------------------ SPL

def _spl_oracle(success, p, l):
    total = 0.0
    for s, pi, li in zip(success, p, l):
        if s:
            total += 1.0 if li == 0 else li / max(pi, li)
    return total / len(success)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.integers(0, 100), st.integers(0, 100)),
                min_size=1, max_size=30))
def test_spl_against_a_plain_loop(cases):
    from diffplan.metrics import spl

    success, p, l = map(list, zip(*cases))
    value = spl(success, p, l)
    assert value == pytest.approx(_spl_oracle(success, p, l))
    assert 0.0 <= value <= np.mean(success) + 1e-12


def test_spl_of_the_expert_is_its_success_rate():
    """An agent that walks the expert's path scores SPL = SR / 100; one twice as long, half."""
    from envs.gridworld.metrics import trajectory_metrics

    positions = np.zeros((2, 5, 2), np.int32)
    positions[:, 1:, 1] = np.arange(1, 5)  # four moves east
    steps = np.array([4, 4])
    target = np.array([[0, 4], [0, 4]])
    expert = np.zeros((2, 8, 8), bool)
    m = trajectory_metrics(positions, steps, target, expert, expert_length=np.array([4, 2]))
    assert m["SR"] == 100.0 and m["SPL"] == pytest.approx((1.0 + 0.5) / 2)


def test_per_phrasing_splits_by_template():
    """Three episodes, templates 8, 3, 8: the ordered success of each phrasing on its own
    episodes; a row that mixes phrasings prints one line per template."""
    from types import SimpleNamespace

    from envs.gridworld import grammar
    from experiments.harness.tables import format_phrasings

    positions = np.array([
        [[0, 0], [1, 0], [1, 1], [1, 1]],  # via the reference: ordered success
        [[0, 0], [0, 1], [1, 1], [1, 1]],  # reference skipped: success, not ordered
        [[0, 0], [0, 1], [0, 2], [0, 3]],  # never reaches the target
    ])
    episodes = SimpleNamespace(template=np.array([8, 3, 8]),
                               target=np.array([[1, 1]] * 3), reference=np.array([[1, 0]] * 3),
                               expert_path=np.stack([_path_mask([(0, 0), (1, 0), (1, 1)])] * 3))
    rows = metrics.per_phrasing_metrics(positions, np.array([2, 2, 3]), episodes, True)
    assert [(r["template"], r["episodes"]) for r in rows] == [(3, 1), (8, 2)]
    assert [(r["SR"], r["SR_ordered"]) for r in rows] == [(100.0, 0.0), (50.0, 50.0)]
    assert rows[1]["phrasing"] == grammar.phrasings(True)[8]
    goal_only = metrics.per_phrasing_metrics(positions, np.array([2, 2, 3]), episodes, False)
    assert "SR_ordered" not in goal_only[0]
    assert goal_only[0]["phrasing"] == grammar.phrasings(False)[3]
    text = format_phrasings([{"method": "on-the-fly, unseen", "per_phrasing": rows},
                             {"method": "on-the-fly"}])
    assert text.splitlines()[1:] == ["  on-the-fly, unseen: #3 100.0/0.0 (1) #8 50.0/50.0 (2)"]
    assert format_phrasings([{"method": "on-the-fly"}]) == ""
