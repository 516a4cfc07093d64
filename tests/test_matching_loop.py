"""COCO's greedy matching is one loop (``harness.evaluation.pairs.greedy_rounds``) that both evaluation paths run:
the rules of ``COCOeval.evaluateImg`` on a hand-made set of candidate entries, and both callers going through it."""

from __future__ import annotations

import numpy as np

from harness.evaluation import bulk, pairs
from harness.evaluation.pairs import greedy_rounds


def test_the_loop_follows_cocoevals_rules_rank_by_rank():
    # one pair; GT columns 0 and 1 are plain, column 2 is crowd (not preferred, and may be taken again)
    #            rank: 0    0    0    1    1    2    2    3
    row = np.array([0, 0, 0, 1, 1, 2, 2, 3])
    col = np.array([0, 1, 2, 0, 1, 1, 2, 2])
    value = np.array([0.6, 0.6, 0.9, 0.5, 0.8, 0.9, 0.7, 0.7])
    crowd = col == 2
    chosen = greedy_rounds(row, np.zeros(8, np.int64), ~crowd, crowd, col, 3, col, value)
    # rank 0: a plain GT before the better crowd one, and of the tied plain ones the later; rank 1: GT 1 is taken,
    # so GT 0; rank 2: both plain ones are taken, so the crowd GT; rank 3: the crowd GT again
    assert chosen.tolist() == [1, 3, 6, 7]


def test_groups_are_matched_apart_and_a_taken_key_is_per_group():
    # two groups over the same GT: taken in group 0 does not take it in group 1 (its own taken key)
    row = np.array([0, 0, 1, 1])
    group = np.array([0, 1, 0, 1])
    key = np.array([0, 1, 0, 1])  # GT 0 in group 0 and in group 1, keyed apart
    chosen = greedy_rounds(row, group, np.ones(4, bool), np.zeros(4, bool), key, 2, np.zeros(4, np.int64), np.ones(4))
    assert chosen.tolist() == [0, 1]  # rank 1 finds its GT taken in both groups
    assert greedy_rounds(row[:0], group[:0], row[:0] > 0, row[:0] > 0, key[:0], 2, row[:0], row[:0] * 1.0).size == 0


def test_both_evaluation_paths_run_the_one_loop(monkeypatch):
    calls: list[str] = []

    def spy(*args):
        calls.append("called")
        return greedy_rounds(*args)

    monkeypatch.setattr(pairs, "greedy_rounds", spy)
    monkeypatch.setattr(bulk, "greedy_rounds", spy)
    layout = pairs.PairLayout(
        img_ids=np.array([1]),
        cat_ids=np.array([1]),
        det_order=np.array([0, 1]),
        det_keys=np.array([0]),
        det_start=np.array([0]),
        det_count=np.array([2]),
        gt_order=np.array([0]),
        gt_keys=np.array([0]),
        gt_start=np.array([0]),
        gt_count=np.array([1]),
        keys=np.array([0]),
        rows=np.array([2]),
        cols=np.array([1]),
        det=np.array([0, 1]),
        gt=np.array([0, 0]),
        pair=np.array([0, 0]),
        row=np.array([0, 1]),
        col=np.array([0, 0]),
        gt_box=np.array([[0.0, 0.0, 4.0, 4.0]]),
        gt_crowd=np.array([False]),
        gt_id=np.array([1]),
        evaluated=np.array([True, True]),
    )
    values = np.array([0.9, 0.95])
    d, g = layout.greedy_match_indices(values, threshold=0.5)
    assert d.tolist() == [0] and g.tolist() == [0]  # the first-ranked detection takes the one GT
    m = bulk.match_all(layout, values, [0.5, 0.75], np.array([[False]]))
    assert m.at(0, 0)[0].tolist() == [0] and m.at(1, 0)[0].tolist() == [0]
    assert calls == ["called", "called"]
