"""The success checkers on hand-placed states: on, beside, tilted, held; and the tower check."""
from __future__ import annotations

import numpy as np

from envs.kuka import metrics

H = 0.03  # half height


def _state(*blocks):
    """pos (4, 3) from up to four (x, y, z) centres; the rest far away on the floor."""
    pos = np.array([[1.5, 1.5, H], [-1.5, 1.5, H], [1.5, -1.5, H], [-1.5, -1.5, H]])
    for i, b in enumerate(blocks):
        pos[i] = b
    return pos, np.zeros(4, bool)


def test_on():
    pos, held = _state((0.6, 0, H), (0.6 + 0.09, 0.0, 3 * H + 0.01))  # 9 cm off, 1 cm high
    on = np.asarray(metrics.on_matrix(pos, held))
    assert on[1, 0] and not on[0, 1] and on.sum() == 1
    assert np.asarray(metrics.diffuser_on_matrix(pos, held))[1, 0]
    np.testing.assert_array_equal(np.asarray(metrics.satisfied(on, [[1, 0], [0, 1], [-1, -1]])),
                                  [True, False, False])


def test_beside_is_not_on():
    # Beside on the floor: neither check.
    pos, held = _state((0.6, 0, H), (0.6, 0.21, H))
    assert not np.asarray(metrics.on_matrix(pos, held)).any()
    assert not np.asarray(metrics.diffuser_on_matrix(pos, held)).any()
    # Half off the lower block (15 cm): not on strictly, on by Diffuser's looser check.
    pos, held = _state((0.6, 0, H), (0.75, 0, 3 * H))
    assert not np.asarray(metrics.on_matrix(pos, held))[1, 0]
    assert np.asarray(metrics.diffuser_on_matrix(pos, held))[1, 0]


def test_tilted_block_leaning_on_another_is_not_on():
    # A block leaning at 30 degrees with its lower edge on the other's top has its centre
    # 0.1 sin 30 + 0.03 cos 30 = 0.076 m above that top (a flat one: 0.03).
    angle = np.radians(30)
    lift = 0.1 * np.sin(angle) + H * np.cos(angle)
    pos, held = _state((0.6, 0, H), (0.6 + 0.1 * np.cos(angle), 0, 2 * H + lift))
    assert not np.asarray(metrics.on_matrix(pos, held))[1, 0]
    assert np.asarray(metrics.diffuser_on_matrix(pos, held))[1, 0]
    # Slightly tilted (2 degrees): still on.
    angle = np.radians(2)
    lift = 0.1 * np.sin(angle) + H * np.cos(angle)
    pos, held = _state((0.6, 0, H), (0.6, 0, 2 * H + lift))
    assert np.asarray(metrics.on_matrix(pos, held))[1, 0]


def test_held_blocks_are_on_nothing():
    pos, held = _state((0.6, 0, H), (0.6, 0, 3 * H))
    for h in ([False, True, False, False], [True, False, False, False]):
        assert not np.asarray(metrics.on_matrix(pos, np.array(h))).any()
        assert not np.asarray(metrics.diffuser_on_matrix(pos, np.array(h))).any()


def test_too_high_or_sunk_is_not_on():
    for dz in (0.02, -0.02):
        pos, held = _state((0.6, 0, H), (0.6, 0, 3 * H + dz))
        assert not np.asarray(metrics.on_matrix(pos, held))[1, 0]


def test_single_tower():
    tower = [(0.6, 0, H + 2 * H * k) for k in range(4)]
    pos, held = _state(*tower)
    assert bool(metrics.single_tower(pos, held))
    assert np.asarray(metrics.on_floor(pos, held)).tolist() == [True, False, False, False]
    two = [(0.6, 0, H), (0.6, 0, 3 * H), (-0.6, 0, H), (-0.6, 0, 3 * H)]
    assert not bool(metrics.single_tower(*_state(*two)))
    assert not bool(metrics.single_tower(pos, np.array([False, False, False, True])))


def test_per_phrasing_counts_each_constraint_under_its_sentence():
    """Hand-written instructions: each instructed constraint is counted under the phrasing of
    its own sentence (the tower sentence is not a relation), absent rows nowhere."""
    from envs.kuka import grammar

    text = ["Build a tower of all four blocks. Put the red block below the green block.",
            "Place the green block on the red block. Put the red block below the blue block. "
            "Place the blue block on the yellow block."]
    tokens = np.stack([grammar.encode(t) for t in text])
    constraints = np.array([[[1, 0], [-1, -1], [-1, -1]], [[1, 0], [2, 0], [2, 3]]])
    strict = np.array([[False, False, False], [True, True, False]])
    rows = metrics.per_phrasing_metrics(tokens, constraints, strict)
    assert [(r["template"], r["constraints"], r["SR"]) for r in rows] == [(1, 2, 50.0),
                                                                          (2, 2, 50.0)]
    assert rows[1]["phrasing"] == grammar.RELATION_TEMPLATES[2]
    with np.testing.assert_raises(ValueError):  # a sentence per constraint, or no breakdown
        metrics.per_phrasing_metrics(tokens[:1], constraints[1:], strict[:1])
