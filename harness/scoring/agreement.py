"""One agreement check for every prediction set: a detector plugin's (``harness run``), a file's (``harness score``).

A prediction set read in the wrong convention scores near zero as an ordinary weak detector would, without a word.
Whatever made it, the set is checked here in the harness's own form (per prediction: the sample, the box ``x1, y1,
x2, y2`` in the frame the ground truth is in, the score, the 0-based label) before anything is scored:

* ``score_scale``: scores outside 0..1 (logits, percentages): the operating point, the confidence threshold and the
  precision-recall curve all read scores as probabilities;
* ``duplicates``: more than ``SHARE`` of the predictions repeat another one exactly (the same image, label, box and
  score): a set written twice, which halves the precision;
* ``label_shift``: the labels agree with the ground truth far better read shifted by one or rolled (``(label + 1) mod
  classes``, as an off-by-one in a class table makes them), and the shift holds for most classes: an off-by-one moves
  every class, while a weakly trained detector's confusion (every car called a ship) helps one reading through some
  classes only (``consistent_classes``, ``CLASS_SHARE``);
* ``box_format``: the boxes agree far better read as ``x, y, w, h``, as ``cx, cy, w, h`` or with ``y`` first;
* ``image_shift``: the predictions agree far better moved to the neighbouring image in image-id order (ids off by one).

"Far better" (``found``): the AP50 of the other reading (``ap50``: average precision at IoU 0.50, all classes pooled,
each image's ``TOP_PER_IMAGE`` highest-scoring predictions) is at least ``MIN_GAIN`` above the reading as given and at
least ``FACTOR`` times it. AP, not recall: a hundred random boxes per image reach a fair recall under every reading,
but no precision, so an untrained or weak detector raises nothing under any reading, while a misread good one shows
as one reading far above the others. Each finding says what was seen with the AP50 of both readings; the caller
prefixes who made the set and adds what to do. ``harness score`` refuses the file (exit status 2) unless
``--allow-implausible``, which labels the stored result; ``harness run`` stops naming the detector (exit status 2)
unless ``eval.allow_degenerate=true``, which stores the result labelled with the same finding.
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np

from harness.scoring.plausibility import TOP_PER_IMAGE, Finding, Pred, _iou, pct

#: Another reading is a finding when its AP50 is at least ``MIN_GAIN`` above the reading as given and at least
#: ``FACTOR`` times it (module docstring).
MIN_GAIN = 0.05
FACTOR = 3.0
#: ... and the gain is worth at least this many objects (``MIN_OBJECTS / objects``): on a few images a few chance
#: matches are worth more than ``MIN_GAIN`` (a 1-epoch detector on two held-out images of 30 objects reached AP50
#: 0.167 read y-first against 0.005 as given: five objects' worth), while a misread detector that learned anything
#: gains tens of objects (labels rolled at mAP50 0.084 on a 300-object fold: about 25).
MIN_OBJECTS = 10
#: A label reading is an off-by-one only when, among the classes with at least ``CLASS_MATCHES`` predictions that
#: overlap an object (IoU 0.50, any label), at least ``CLASS_SHARE`` are read as the label of the objects they overlap
#: most often: a CMA-Det trained 12 epochs on 144 tiny-target pairs called most cars, buses and drones "ship", so that
#: rolled by +1 (ship -> car) its labels gave AP50 0.067 against 0.008 as given; another seed's roll moved 3 of its 6
#: classes that way.
CLASS_MATCHES = 3
CLASS_SHARE = 2 / 3
#: The share of predictions repeating another exactly above which a set counts as written more than once (one
#: written twice repeats half of it; a detector's own near-duplicates that survive its NMS stay far below).
DUPLICATE_SHARE = 0.4
#: How far outside 0..1 a score may lie before it counts (float rounding of a product of probabilities).
SCORE_TOL = 1e-6
#: The checks of ``check``, in the order they are made (``only`` picks some).
CHECKS = ("score_scale", "duplicates", "label_shift", "box_format", "image_shift")

Targets = Callable[[int], tuple[np.ndarray, np.ndarray]]


def _ranked(
    preds: Sequence[Pred], images: Sequence[int], top: int
) -> dict[int, list[tuple[float, Sequence[float], int]]]:
    """Per image of ``images``, its ``top`` highest-scoring labelled predictions as (score, box, label)."""
    wanted = set(images)
    by_image: dict[int, list[tuple[float, Sequence[float], int]]] = {}
    for idx, box, score, label in preds:
        if idx in wanted and label is not None:
            by_image.setdefault(idx, []).append((score, box, label))  # type: ignore[arg-type]
    return {idx: sorted(items, key=lambda t: -t[0])[:top] for idx, items in by_image.items()}


def _greedy(
    items: Sequence[tuple[float, Sequence[float], int]], gt_boxes: Any, gt_labels: Any, same_label: bool = True
) -> list[int]:
    """Per item (in order: highest score first), the object it matches at IoU 0.50, or -1: each to the unmatched
    object it overlaps most, of its own label unless ``same_label`` is False."""
    boxes = np.asarray([b for _, b, _ in items], dtype=np.float64).reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        iou = np.nan_to_num(_iou(boxes, np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 4)))
    ok = iou >= 0.5
    if same_label:
        ok &= np.asarray([lab for _, _, lab in items])[:, None] == np.asarray(gt_labels)[None, :]
    used = np.zeros(len(gt_boxes), dtype=bool)
    out = []
    for k in range(len(items)):
        free = ok[k] & ~used
        j = int(np.argmax(np.where(free, iou[k], -1.0))) if free.any() else -1
        if j >= 0:
            used[j] = True
        out.append(j)
    return out


def ap50(preds: Sequence[Pred], targets: Targets, images: Sequence[int], top: int = TOP_PER_IMAGE) -> float | None:
    """Average precision at IoU 0.50 of ``preds`` on ``images``, all classes pooled: each image's ``top``
    highest-scoring predictions matched greedily (highest score first) to unmatched objects of their label, the
    precision made monotone as COCO's is, summed at every true positive over the number of objects. ``None`` when
    the images hold no objects."""
    ranked = _ranked(preds, images, top)
    objects = 0
    scores: list[float] = []
    hits: list[bool] = []
    for idx in set(images):
        gt_boxes, gt_labels = targets(idx)
        objects += len(gt_boxes)
        items = ranked.get(idx, [])
        if not items:
            continue
        scores += [t[0] for t in items]
        if len(gt_boxes) == 0:
            hits += [False] * len(items)
            continue
        hits += [j >= 0 for j in _greedy(items, gt_boxes, gt_labels)]
    if not objects:
        return None
    if not hits:
        return 0.0
    order = np.argsort(-np.asarray(scores), kind="stable")
    tp = np.asarray(hits)[order]
    precision = np.cumsum(tp) / np.arange(1, len(tp) + 1)
    precision = np.maximum.accumulate(precision[::-1])[::-1]
    return float(precision[tp].sum() / objects)


def found(given: float | None, other: float | None, objects: int = 0) -> bool:
    """Whether the other reading agrees so much better (AP50) that the reading as given is a misreading, on images
    holding ``objects`` objects."""
    if other is None:
        return False
    g = given or 0.0
    return other - g >= max(MIN_GAIN, MIN_OBJECTS / objects if objects else 0.0) and other >= FACTOR * g


def count_objects(targets: Targets, images: Sequence[int]) -> int:
    return sum(len(targets(i)[0]) for i in set(images))


def _seen(given: float | None, other: float | None, as_given: str, as_other: str) -> str:
    return f"AP50 {given or 0:.3f} {as_given}, {other or 0:.3f} {as_other}"


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


def duplicate_key(pred: Pred) -> tuple[Any, ...]:
    """What makes two predictions (image, box, score, label) the same one written twice: image, label, the box to
    1e-3 px and the score to 1e-6."""
    idx, box, score, label = pred
    return (idx, label, tuple(round(float(v), 3) for v in box), round(float(score), 6))


def duplicate_findings(preds: Sequence[Pred]) -> list[Finding]:
    """``duplicates`` when more than ``SHARE`` of the predictions repeat another exactly (image, label, box, score)."""
    keys = Counter(
        duplicate_key(p)
        for p in preds
        if float(p[1][2]) > float(p[1][0]) and float(p[1][3]) > float(p[1][1])  # a detector's collapsed boxes are not
    )  # a set written twice: an untrained one returns many identical zero-size boxes at a frame's edge
    extra = sum(c - 1 for c in keys.values() if c > 1)
    n = len(preds)
    if not (n > 0 and extra > DUPLICATE_SHARE * n):
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


Candidate = tuple[float, Finding]


def label_findings(preds: Sequence[Pred], targets: Targets, images: Sequence[int], num_classes: int) -> list[Finding]:
    """``label_shift`` when the labels agree with the ground truth far better shifted or rolled (module docstring)."""
    return [f for _, f in _label_best(preds, targets, images, num_classes)]


def _best_reading(
    given: float | None, objects: int, alternatives: Iterable[tuple[str, float | None]]
) -> tuple[str, float] | None:
    """The other reading (how it is read, its AP50) that agrees best among those ``found`` far better than the reading
    as given; None when none is."""
    best: tuple[str, float] | None = None
    for what, alt in alternatives:
        if found(given, alt, objects) and (best is None or (alt or 0.0) > best[1]):
            best = (what, alt or 0.0)
    return best


def agnostic_matches(
    preds: Sequence[Pred], targets: Targets, images: Sequence[int], top: int = TOP_PER_IMAGE
) -> list[tuple[int, int]]:
    """(predicted label, object label) of each prediction that overlaps an object at IoU 0.50 whatever the labels:
    each image's ``top`` highest-scoring predictions matched greedily, highest score first, to unmatched objects."""
    pairs: list[tuple[int, int]] = []
    for idx, items in _ranked(preds, images, top).items():
        gt_boxes, gt_labels = targets(idx)
        if len(gt_boxes) == 0:
            continue
        for (_, _, lab), j in zip(items, _greedy(items, gt_boxes, gt_labels, same_label=False)):
            if j >= 0:
                pairs.append((int(lab), int(gt_labels[j])))
    return pairs


def consistent_classes(pairs: Sequence[tuple[int, int]], read: Callable[[int], int | None]) -> tuple[int, int]:
    """(classes the reading moves onto the object label they overlap most often, classes with at least
    ``CLASS_MATCHES`` overlapping predictions), from ``agnostic_matches``."""
    by_class: dict[int, Counter] = {}
    for lab, obj in pairs:
        by_class.setdefault(lab, Counter())[obj] += 1
    counted = [c for c in by_class.values() if sum(c.values()) >= CLASS_MATCHES]
    moved = 0
    for lab, c in by_class.items():
        if sum(c.values()) >= CLASS_MATCHES and read(lab) is not None and c[read(lab)] == max(c.values()):
            moved += 1
    return moved, len(counted)


def _label_best(preds: Sequence[Pred], targets: Targets, images: Sequence[int], num_classes: int) -> list[Candidate]:
    given, n_obj = ap50(preds, targets, images), count_objects(targets, images)
    readings = dict(label_readings(num_classes))
    best = _best_reading(
        given,
        n_obj,
        (
            (what, ap50([(i, b, s, None if lab is None else read(lab)) for i, b, s, lab in preds], targets, images))
            for what, read in readings.items()
        ),
    )
    if best is None:
        return []
    moved, counted = consistent_classes(agnostic_matches(preds, targets, images), readings[best[0]])
    if counted > 1 and moved < CLASS_SHARE * counted:  # a confusion of some classes, not an off-by-one
        return []
    return [
        (
            best[1],
            Finding(
                "label_shift",
                f"labels that agree with the ground truth only {best[0]} "
                f"({_seen(given, best[1], 'as given', best[0].split(' (')[0])}): an off-by-one in the class list?",
            ),
        )
    ]


#: The other box conventions: (name, (``x1, y1, x2, y2`` as given, per box the offset ``c``) -> the box that
#: convention means). ``c``: where the boxes were returned in a letterboxed input and mapped back as ``x, y``, a
#: ``y, x`` pair comes back shifted by ``c = (pad_top - pad_left) / ratio`` (0 for a square frame).
BOX_READINGS: tuple[tuple[str, Callable[[np.ndarray, np.ndarray], np.ndarray]], ...] = (
    ("x, y, w, h", lambda b, c: np.stack([b[:, 0], b[:, 1], b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]], axis=1)),
    (
        "cx, cy, w, h",
        lambda b, c: np.stack(
            [b[:, 0] - b[:, 2] / 2, b[:, 1] - b[:, 3] / 2, b[:, 0] + b[:, 2] / 2, b[:, 1] + b[:, 3] / 2], axis=1
        ),
    ),
    (
        "y1, x1, y2, x2 (y first)",
        lambda b, c: np.stack([b[:, 1] + c, b[:, 0] - c, b[:, 3] + c, b[:, 2] - c], axis=1),
    ),
)


def box_findings(
    preds: Sequence[Pred],
    targets: Targets,
    images: Sequence[int],
    readings: Sequence[str] | None = None,
    offsets: Sequence[float] | None = None,
) -> list[Finding]:
    """``box_format`` when the boxes agree far better in another convention (``BOX_READINGS``; ``readings``: some;
    ``offsets``: per prediction, the letterbox's ``c``, else 0)."""
    return [f for _, f in _box_best(preds, targets, images, readings, offsets)]


def _box_best(
    preds: Sequence[Pred],
    targets: Targets,
    images: Sequence[int],
    readings: Sequence[str] | None = None,
    offsets: Sequence[float] | None = None,
) -> list[Candidate]:
    if not preds:
        return []
    boxes = np.asarray([b for _, b, _, _ in preds], dtype=np.float64).reshape(-1, 4)
    given, n_obj = ap50(preds, targets, images), count_objects(targets, images)
    c = np.zeros(len(boxes)) if offsets is None else np.asarray(offsets, dtype=np.float64)

    def alternatives() -> Iterator[tuple[str, float | None]]:
        for what, read in BOX_READINGS:
            if readings is not None and what not in readings:
                continue
            with np.errstate(invalid="ignore", over="ignore"):
                other = read(boxes, c)
            yield what, ap50([(i, o, s, lab) for (i, _, s, lab), o in zip(preds, other.tolist())], targets, images)

    best = _best_reading(given, n_obj, alternatives())
    if best is None:
        return []
    return [
        (
            best[1],
            Finding(
                "box_format",
                f"boxes that agree with the ground truth only read as {best[0]} "
                f"({_seen(given, best[1], 'as x1, y1, x2, y2', f'as {best[0]}')})",
            ),
        )
    ]


def image_findings(preds: Sequence[Pred], targets: Targets, images: Sequence[int]) -> list[Finding]:
    """``image_shift`` when the predictions agree far better moved to the neighbouring image of ``images`` (in the
    order given: image-id order)."""
    return [f for _, f in _image_best(preds, targets, images)]


def _image_best(preds: Sequence[Pred], targets: Targets, images: Sequence[int]) -> list[Candidate]:
    order = list(images)
    pos = {idx: k for k, idx in enumerate(order)}
    given, n_obj = ap50(preds, targets, order), count_objects(targets, order)
    for d in (1, -1):
        moved = [
            (order[pos[i] + d], b, s, lab)
            for i, b, s, lab in preds
            if i in pos and 0 <= pos[i] + d < len(order)  # type: ignore[index]
        ]
        alt = ap50(moved, targets, order)
        if found(given, alt, n_obj):
            return [
                (
                    alt or 0.0,
                    Finding(
                        "image_shift",
                        f"predictions that agree with the ground truth only moved to the "
                        f"{'next' if d == 1 else 'previous'} image in image-id order "
                        f"({_seen(given, alt, 'as given', 'moved')}): image ids off by one?",
                    ),
                )
            ]
    return []


def check(
    preds: Sequence[Pred],
    targets: Targets,
    images: Sequence[int],
    num_classes: int,
    only: Sequence[str] = CHECKS,
    offsets: Sequence[float] | None = None,
) -> list[Finding]:
    """The findings of every check in ``only`` (``CHECKS``) on ``preds`` against the ground truth of ``images`` (in
    image-id order), with labels in 0..``num_classes``-1. A set with a score or duplicate finding is not read further
    (its agreement would say nothing new); of the other readings only the one that agrees best is a finding (one
    misreading makes the others agree a little by chance). ``offsets``: see ``box_findings``."""
    out: list[Finding] = []
    if "score_scale" in only:
        out += score_findings([s for _, _, s, _ in preds])
    if "duplicates" in only:
        out += duplicate_findings(preds)
    if out:
        return out
    candidates: list[Candidate] = []
    if "label_shift" in only:
        candidates += _label_best(preds, targets, images, num_classes)
    if "box_format" in only:
        candidates += _box_best(preds, targets, images, offsets=offsets)
    if "image_shift" in only:
        candidates += _image_best(preds, targets, images)
    return [max(candidates, key=lambda c: c[0])[1]] if candidates else []


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


def letterbox_offset(width: float, height: float, size: int) -> float:
    """``c = (pad_top - pad_left) / ratio`` of an image letterboxed to ``size x size`` (``harness.engine.augment``)."""
    r = min(size / height, size / width)
    nw, nh = max(1, round(width * r)), max(1, round(height * r))
    left, top = int(round((size - nw) / 2 - 0.1)), int(round((size - nh) / 2 - 0.1))
    return (top - left) / r


def check_run(
    detector: str,
    dets: Sequence[Mapping[str, Any]],
    gt: Mapping[str, Any],
    num_classes: int,
    allow: bool = False,
    imgsz: int | None = None,
) -> list[str]:
    """``harness run``: the agreement check on a detector plugin's held-out predictions (COCO results in the thermal
    frame) against the fold's ground truth ``gt``, before they are scored or stored. A finding stops the run with a
    ``PluginError`` naming the detector, unless ``allow`` (``eval.allow_degenerate``): then the findings come back as
    labels for the stored result (none when the set is plausible). Image ids are the harness's own here, so the
    image shift is not looked for. ``imgsz``: the square input the images were letterboxed to (for the y-first
    reading of non-square frames)."""
    from harness.errors import PluginError

    targets, ids = coco_targets(gt)
    preds = coco_preds(dets)
    offsets = None
    if imgsz:
        sizes = {int(im["id"]): (float(im["width"]), float(im["height"])) for im in gt.get("images") or []}
        offsets = [letterbox_offset(*sizes[i], imgsz) if i in sizes else 0.0 for i, _, _, _ in preds]
    found = check(preds, targets, ids, num_classes, only=CHECKS[:4], offsets=offsets)
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
