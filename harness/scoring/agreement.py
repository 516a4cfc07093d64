"""One agreement check for every prediction set: a detector plugin's (``harness run``), a file's (``harness score``).

A prediction set read in the wrong convention scores near zero as an ordinary weak detector would, without a word.
Whatever made it, the set is checked here in the harness's own form (per prediction: the sample, the box ``x1, y1,
x2, y2`` in the frame the ground truth is in, the score, the 0-based label) before anything is scored:

* ``score_scale``: scores outside 0..1 (logits, percentages): the operating point, the confidence threshold and the
  precision-recall curve all read scores as probabilities;
* ``duplicates``: more than ``SHARE`` of the predictions repeat another one exactly (the same image, label, box and
  score): a set written twice, which halves the precision;
* ``label_shift``: the labels agree with the ground truth far better read shifted by one or rolled (``(label + 1) mod
  classes``, as an off-by-one in a class table makes them);
* ``box_format``: the boxes agree far better read as ``x, y, w, h``, as ``cx, cy, w, h`` or with ``y`` first;
* ``image_shift``: the predictions agree far better moved to the neighbouring image in image-id order (ids off by one).

"Far better" is ``shift_found`` of ``harness.scoring.plausibility``: recall at IoU 0.50 (``agreement``) of at least
``SHIFT_MIN_AGREEMENT`` read the other way and at least ``SHIFT_FACTOR`` times the reading as given. An untrained or
weak detector agrees little under every reading and raises nothing; a misreading shows as one reading far above the
others. Each finding says what was seen with the recall of both readings; the caller prefixes who made the set and
adds what to do. ``harness score`` refuses the file (exit status 2) unless ``--allow-implausible``, which labels the
stored result; ``harness run`` stops naming the detector (exit status 2) unless ``eval.allow_degenerate=true``,
which stores the result labelled with the same finding.
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from harness.scoring.plausibility import Finding, Pred, agreement, pct, shift_found, too_many

#: How far outside 0..1 a score may lie before it counts (float rounding of a product of probabilities).
SCORE_TOL = 1e-6
#: The checks of ``check``, in the order they are made (``only`` picks some).
CHECKS = ("score_scale", "duplicates", "label_shift", "box_format", "image_shift")

Targets = Callable[[int], tuple[np.ndarray, np.ndarray]]


def _seen(given: float | None, other: float | None, as_given: str, as_other: str) -> str:
    return f"recall at IoU 0.50 {given or 0:.0%} {as_given}, {other or 0:.0%} {as_other}"


def score_findings(scores: Sequence[float]) -> list[Finding]:
    """``score_scale`` when any score lies outside 0..1 (the finite ones; non-finite scores are malformed)."""
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    s = s[np.isfinite(s)]
    if not len(s) or (s.min() >= -SCORE_TOL and s.max() <= 1.0 + SCORE_TOL):
        return []
    below, above = int((s < -SCORE_TOL).sum()), int((s > 1 + SCORE_TOL).sum())
    if below:
        guess = "logits (scores before the sigmoid or softmax)?"
    elif s.max() <= 100.0:
        guess = "percentages?"
    else:
        guess = "not probabilities?"
    parts = [f"{below} below 0" if below else "", f"{above} above 1" if above else ""]
    return [
        Finding(
            "score_scale",
            f"scores {s.min():.4g}..{s.max():.4g} where probabilities 0..1 are expected "
            f"({', '.join(p for p in parts if p)} of {len(s)}): {guess}",
        )
    ]


def duplicate_findings(preds: Sequence[Pred]) -> list[Finding]:
    """``duplicates`` when more than ``SHARE`` of the predictions repeat another exactly (image, label, box, score)."""
    keys = Counter(
        (idx, label, tuple(round(float(v), 3) for v in box), round(float(score), 6)) for idx, box, score, label in preds
    )
    extra = sum(c - 1 for c in keys.values() if c > 1)
    n = len(preds)
    if not too_many(extra, n):
        return []
    most = max(keys.values())
    return [
        Finding(
            "duplicates",
            f"predictions of which {extra} of {n} ({pct(extra, n)}) repeat another one exactly (the same image, "
            f"label, box and score; up to {most} times): every detection listed "
            f"{'twice' if most == 2 else 'more than once'}?",
        )
    ]


def label_readings(num_classes: int) -> list[tuple[str, Callable[[int], int | None]]]:
    """The other readings of 0-based labels: (how they are read, the label a given one is read as), the shift or
    roll named as the correction (``shift of -1``: the given labels are one too high)."""
    nc = num_classes

    def shifted(d: int) -> Callable[[int], int | None]:
        return lambda lab: lab + d if 0 <= lab + d < nc else None

    def rolled(d: int) -> Callable[[int], int | None]:
        return lambda lab: (lab + d) % nc

    out: list[tuple[str, Callable[[int], int | None]]] = [(f"after a shift of {d:+d}", shifted(d)) for d in (1, -1)]
    if nc > 2:  # with two classes a roll by +1 is a roll by -1; with one there is nothing to roll
        out += [(f"rolled by {d:+d} ((label {'+' if d > 0 else '-'} 1) mod {nc})", rolled(d)) for d in (1, -1)]
    elif nc == 2:
        out.append(("rolled ((label + 1) mod 2)", rolled(1)))
    return out


def label_findings(preds: Sequence[Pred], targets: Targets, images: Sequence[int], num_classes: int) -> list[Finding]:
    """``label_shift`` when the labels agree with the ground truth far better shifted or rolled (module docstring)."""
    given = agreement(preds, targets, images)
    best: tuple[str, float] | None = None
    for what, read in label_readings(num_classes):
        alt = agreement([(i, b, s, None if lab is None else read(lab)) for i, b, s, lab in preds], targets, images)
        if shift_found(given, alt) and (best is None or (alt or 0.0) > best[1]):
            best = (what, alt or 0.0)
    if best is None:
        return []
    return [
        Finding(
            "label_shift",
            f"labels that agree with the ground truth only {best[0]} "
            f"({_seen(given, best[1], 'as given', best[0].split(' (')[0])}): an off-by-one in the class list?",
        )
    ]


#: The other box conventions: (name, ``x1, y1, x2, y2`` as given -> the box that convention means).
BOX_READINGS: tuple[tuple[str, Callable[[np.ndarray], np.ndarray]], ...] = (
    ("x, y, w, h", lambda b: np.stack([b[:, 0], b[:, 1], b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]], axis=1)),
    (
        "cx, cy, w, h",
        lambda b: np.stack(
            [b[:, 0] - b[:, 2] / 2, b[:, 1] - b[:, 3] / 2, b[:, 0] + b[:, 2] / 2, b[:, 1] + b[:, 3] / 2], axis=1
        ),
    ),
    ("y1, x1, y2, x2 (y first)", lambda b: b[:, [1, 0, 3, 2]]),
)


def box_findings(
    preds: Sequence[Pred], targets: Targets, images: Sequence[int], readings: Sequence[str] | None = None
) -> list[Finding]:
    """``box_format`` when the boxes agree far better in another convention (``BOX_READINGS``; ``readings``: some)."""
    if not preds:
        return []
    boxes = np.asarray([b for _, b, _, _ in preds], dtype=np.float64).reshape(-1, 4)
    given = agreement(preds, targets, images)
    best: tuple[str, float] | None = None
    for what, read in BOX_READINGS:
        if readings is not None and what not in readings:
            continue
        with np.errstate(invalid="ignore", over="ignore"):
            other = read(boxes)
        alt = agreement([(i, o, s, lab) for (i, _, s, lab), o in zip(preds, other.tolist())], targets, images)
        if shift_found(given, alt) and (best is None or (alt or 0.0) > best[1]):
            best = (what, alt or 0.0)
    if best is None:
        return []
    return [
        Finding(
            "box_format",
            f"boxes that agree with the ground truth only read as {best[0]} "
            f"({_seen(given, best[1], 'as x1, y1, x2, y2', f'as {best[0]}')})",
        )
    ]


def image_findings(preds: Sequence[Pred], targets: Targets, images: Sequence[int]) -> list[Finding]:
    """``image_shift`` when the predictions agree far better moved to the neighbouring image of ``images`` (in the
    order given: image-id order)."""
    order = list(images)
    pos = {idx: k for k, idx in enumerate(order)}
    given = agreement(preds, targets, order)
    for d in (1, -1):
        moved = [
            (order[pos[i] + d], b, s, lab)
            for i, b, s, lab in preds
            if i in pos and 0 <= pos[i] + d < len(order)  # type: ignore[index]
        ]
        alt = agreement(moved, targets, order)
        if shift_found(given, alt):
            return [
                Finding(
                    "image_shift",
                    f"predictions that agree with the ground truth only moved to the "
                    f"{'next' if d == 1 else 'previous'} image in image-id order "
                    f"({_seen(given, alt, 'as given', 'moved')}): image ids off by one?",
                )
            ]
    return []


def check(
    preds: Sequence[Pred],
    targets: Targets,
    images: Sequence[int],
    num_classes: int,
    only: Sequence[str] = CHECKS,
) -> list[Finding]:
    """The findings of every check in ``only`` (``CHECKS``) on ``preds`` against the ground truth of ``images`` (in
    image-id order), with labels in 0..``num_classes``-1. A set with a score or duplicate finding is not read further
    (its agreement would say nothing new)."""
    out: list[Finding] = []
    if "score_scale" in only:
        out += score_findings([s for _, _, s, _ in preds])
    if "duplicates" in only:
        out += duplicate_findings(preds)
    if out:
        return out
    if "label_shift" in only:
        out += label_findings(preds, targets, images, num_classes)
    if "box_format" in only and not out:
        out += box_findings(preds, targets, images)
    if "image_shift" in only and not out:
        out += image_findings(preds, targets, images)
    return out


def coco_targets(gt: Mapping[str, Any]) -> tuple[Targets, list[int]]:
    """The ground truth of a COCO dict (``harness.cache`` ``coco``): ``targets(image_id) -> (boxes xyxy, 0-based
    labels)`` and the image ids in order."""
    boxes: dict[int, list[list[float]]] = {}
    labels: dict[int, list[int]] = {}
    for a in gt.get("annotations") or []:
        i = int(a["image_id"])
        x, y, w, h = (float(v) for v in a["bbox"])
        boxes.setdefault(i, []).append([x, y, x + w, y + h])
        labels.setdefault(i, []).append(int(a["category_id"]) - 1)
    ids = sorted(int(im["id"]) for im in gt.get("images") or [])

    def targets(i: int) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(boxes.get(i, []), dtype=np.float64).reshape(-1, 4), np.asarray(labels.get(i, []), np.int64)

    return targets, ids


def coco_preds(dets: Sequence[Mapping[str, Any]]) -> list[Pred]:
    """COCO results (``bbox`` ``x, y, w, h``, ``category_id = label + 1``) in the harness's form."""
    out: list[Pred] = []
    for d in dets:
        x, y, w, h = (float(v) for v in d["bbox"])
        out.append((int(d["image_id"]), [x, y, x + w, y + h], float(d["score"]), int(d["category_id"]) - 1))
    return out


def check_run(
    detector: str,
    dets: Sequence[Mapping[str, Any]],
    gt: Mapping[str, Any],
    num_classes: int,
    allow: bool = False,
) -> list[str]:
    """``harness run``: the agreement check on a detector plugin's held-out predictions (COCO results in the thermal
    frame) against the fold's ground truth ``gt``, before they are scored or stored. A finding stops the run with a
    ``PluginError`` naming the detector, unless ``allow`` (``eval.allow_degenerate``): then the findings come back as
    labels for the stored result (none when the set is plausible). Image ids are the harness's own here, so the
    image shift is not looked for."""
    from harness.errors import PluginError

    targets, ids = coco_targets(gt)
    found = check(coco_preds(dets), targets, ids, num_classes, only=CHECKS[:4])
    if not found:
        return []
    fixes = {
        "score_scale": "eval-mode 'scores' must be probabilities in 0..1",
        "duplicates": "return each detection once",
        "label_shift": f"eval-mode 'labels' must be 0-based indices into the dataset's {num_classes} categories",
        "box_format": "eval-mode 'boxes' must be x1, y1, x2, y2 in input pixels",
    }
    lines = [f"detector {detector!r} returned {f.message}; {fixes[f.kind]}" for f in found]
    if allow:
        return [f"implausible predictions stored as returned (eval.allow_degenerate): {x}" for x in lines]
    raise PluginError(
        "\n".join(lines) + "\nNothing was stored: fix the detector, or set eval.allow_degenerate=true to store the "
        "run labelled."
    )
