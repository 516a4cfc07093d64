"""The label-shift check tells an off-by-one in a class list (every class moved) from a weakly trained detector's
confusion (one class called another), which can make one roll of the labels score far better too."""

from __future__ import annotations

import numpy as np
import pytest

from harness.scoring import agreement as A

NC = 7  # RGBT-Tiny's classes: ship, car, cyclist, pedestrian, bus, drone, plane
SHIP, CAR, BUS, DRONE = 0, 1, 4, 5


def _scene(seed: int = 0, images: int = 40):
    """Objects of every class on ``images`` frames: 6 to 10 each, boxes 6-20 px, apart from each other."""
    rng = np.random.default_rng(seed)
    gt = {}
    for i in range(images):
        n = int(rng.integers(6, 11))
        xs = rng.permutation(np.arange(0, 600, 40))[:n]
        boxes = np.stack([xs, np.full(n, 100.0), xs + rng.integers(6, 20, n), np.full(n, 100.0) + 12], axis=1)
        gt[i] = (boxes.astype(np.float64), rng.integers(0, NC, n))
    return gt, (lambda i: gt[i]), list(gt)


def _preds(gt, label_of, rng):
    """One prediction on each object, its label ``label_of(object label, rng)``, plus a few boxes on nothing."""
    out = []
    for i, (boxes, labels) in gt.items():
        for b, lab in zip(boxes, labels):
            out.append((i, [float(v) for v in b], float(rng.uniform(0.05, 0.9)), label_of(int(lab), rng)))
        for _ in range(5):
            x = float(rng.uniform(0, 600))
            out.append((i, [x, 300.0, x + 10, 310.0], float(rng.uniform(0.05, 0.5)), int(rng.integers(0, NC))))
    return out


def test_labels_rolled_for_every_class_are_an_off_by_one():
    gt, targets, images = _scene()
    rng = np.random.default_rng(1)
    preds = _preds(gt, lambda lab, r: (lab - 1) % NC, rng)  # the class list read one too low
    found = A.label_findings(preds, targets, images, NC)
    assert len(found) == 1 and "rolled by +1" in found[0].message


def test_a_weak_detectors_confusion_that_one_roll_happens_to_fix_is_not_an_off_by_one():
    # as a CMA-Det trained 12 epochs on tiny targets did: most cars (and buses, drones) called "ship", the rest of
    # the labels mostly wrong, so rolling by +1 (ship -> car) scores far better than the labels as given
    gt, targets, images = _scene()

    def confused(lab: int, r) -> int:
        if lab in (CAR, BUS, DRONE):
            return SHIP if r.random() < 0.8 else int(r.integers(0, NC))
        return int(r.choice([k for k in range(NC) if k != lab]))  # never right, never the roll's label either

    preds = _preds(gt, confused, np.random.default_rng(2))
    given = A.ap50(preds, targets, images)
    rolled = A.ap50([(i, b, s, (lab + 1) % NC) for i, b, s, lab in preds], targets, images)
    assert A.found(given, rolled, A.count_objects(targets, images))  # AP50 alone would call it a roll
    moved, counted = A.consistent_classes(A.agnostic_matches(preds, targets, images), lambda lab: (lab + 1) % NC)
    assert counted == NC and moved <= 2
    assert A.label_findings(preds, targets, images, NC) == []


@pytest.mark.parametrize("shift", [1, -1])
def test_labels_shifted_by_one_are_still_found(shift):
    gt, targets, images = _scene(seed=3)
    preds = _preds(gt, lambda lab, r: lab - shift, np.random.default_rng(4))  # 0-based read as 1-based or back
    preds = [p for p in preds if 0 <= p[3] < NC]
    found = A.label_findings(preds, targets, images, NC)
    assert len(found) == 1 and f"shift of {shift:+d}" in found[0].message
