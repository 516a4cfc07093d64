"""``harness score``: predictions made by another codebase, scored against the prepared ground truth of a fold.

The predictions are COCO results (``[{"image_id", "category_id", "bbox": [x, y, w, h], "score"}, ...]``), as
Ultralytics' ``save_json``, MMDetection, Detectron2 and YOLOv5's ``val.py`` write them. To score them on exactly the
samples every harness detector is scored on:

* **images** are matched to the fold's prepared samples by file name: each prediction's own ``file_name`` (or the
  ``image_key`` field), else its ``image_id`` looked up in an image list (``images``: the other codebase's COCO
  JSON, whose ``images`` give ``id`` and ``file_name``), else a non-numeric ``image_id`` as a file stem (Ultralytics
  writes the stem), else a numeric one as the harness's own image id. A name matches a sample by its relative path,
  else by its base name, else by its stem (only when unique), else by a numeric stem as a number. Predictions of
  images outside the fold are left out and counted; unmatched ones are counted and listed.
* **categories** are matched by name (the image list's ``categories``, or the prediction's ``category_name``),
  case and separators ignored, or through an explicit ``category_map`` (their id or name -> our name); without
  names, ids are taken as the harness's (``category_id = label + 1``). Unmatched categories are counted and shown.
* **boxes** in the original RGB or thermal image are moved into the prepared frame by the same undistortion,
  homography and crop as the ground truth (``harness.scoring.frames``); only boxes wholly outside are dropped.
* **plausibility**: before anything is scored, ids that look misread (many predictions on unknown images or in
  unknown categories, ids that fit only shifted by one) stop with what was seen (``harness.scoring.plausibility``),
  and so do the findings of the agreement check every prediction set gets, a detector plugin's in ``harness run``
  too (``harness.scoring.agreement``: scores outside 0..1, duplicates, labels that fit only shifted or rolled,
  boxes that fit only in another convention, image ids off by one), and a ``category_id`` and ``category_name``
  that disagree; unless ``allow_implausible`` (``--allow-implausible``), which labels the stored result.
* **which images were scored**: with an image list, the fold images it does not list are *missing*: they are left
  out of the ground truth, so the support differs from the trained detectors' and the sample-matched guard labels
  the comparison. Without an image list, every fold image is scored and those without any prediction are counted.

The result is stored as a run of detector ``external/NAME`` (``harness.store``), with ``predictions.json``,
``gt.json`` and ``metrics.json``, so ``harness report``, ``compare-detectors`` and the paired bootstrap show it
beside the trained detectors. Complexity is what the user gives (``params``, ``gflops``) or left empty.

Kept in one module: the image and category matching, the guards over what it matched and the scoring share one
``Matching`` record, filled and read in order from ``match_predictions`` to ``score_external``.
"""

from __future__ import annotations

import json
import logging
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Mapping, Sequence

import numpy as np

from harness.complexity import given
from harness.errors import ConfigError, DataError, StoreError
from harness.io import atomic_write_json, file_digest, read_json
from harness.report.reader import normalise_category, read_run
from harness.scoring.frames import FRAMES, image_name, to_prepared
from harness.scoring.frames import moved as unclipped
from harness.scoring.plausibility import (
    XYXY_MIN_BOXES,
    XYXY_SHARE,
    Finding,
    agreement,
    box_findings,
    corner_like,
    examples,
    mostly_outside,
    overlaps_truth,
    pct,
    shift_found,
    too_many,
)

log = logging.getLogger(__name__)

ENCODING = "external"
NOT_LISTED = "(not in the image list)"
#: How a prediction's ``bbox`` is read: COCO's ``x, y, w, h`` (the default), or corners ``x1, y1, x2, y2``.
BOX_FORMATS = ("xywh", "xyxy")


@dataclass
class Matching:
    """How the external predictions met the fold: counts and examples of what did not match."""

    predictions: int = 0
    scored: int = 0
    fold_images: int = 0
    images_scored: int = 0
    missing_images: list[str] = field(default_factory=list)
    images_without_predictions: int = 0
    unmatched_images: Counter = field(default_factory=Counter)
    outside_fold: int = 0
    unmatched_categories: Counter = field(default_factory=Counter)
    dropped_outside_frame: int = 0
    invalid: int = 0
    #: why predictions were malformed (no bbox or score, not finite, negative width or height), with examples
    invalid_reasons: Counter = field(default_factory=Counter)
    invalid_examples: list[str] = field(default_factory=list)
    #: predictions of fold images that the image list leaves out (also in ``unmatched_images``; not a misreading)
    not_listed: int = 0
    #: predictions whose image was found by reading their ``image_id`` as the harness's own image id
    by_harness_id: int = 0
    #: how many images the image list given with ``--images`` names (None without one)
    listed_images: int | None = None
    #: of those, predictions on images of other folds
    outside_fold_by_id: int = 0
    #: why the matching looks like a misreading of the ids (``harness.scoring.plausibility``)
    findings: list[Finding] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "predictions": self.predictions,
            "scored_predictions": self.scored,
            "fold_images": self.fold_images,
            "images_scored": self.images_scored,
            "missing_images": len(self.missing_images),
            "missing_examples": self.missing_images[:10],
            "images_without_predictions": self.images_without_predictions,
            "unmatched_image_predictions": sum(self.unmatched_images.values()),
            "unmatched_image_examples": [k for k, _ in self.unmatched_images.most_common(10)],
            "predictions_outside_fold": self.outside_fold,
            "unmatched_category_predictions": sum(self.unmatched_categories.values()),
            "unmatched_categories": dict(self.unmatched_categories.most_common(20)),
            "dropped_outside_frame": self.dropped_outside_frame,
            "invalid_predictions": self.invalid,
            **(
                {"invalid_reasons": dict(self.invalid_reasons), "invalid_examples": self.invalid_examples[:5]}
                if self.invalid
                else {}
            ),
            "by_harness_image_id": self.by_harness_id,
            "implausible": [f.kind for f in self.findings],
        }

    def dropped(self) -> dict[str, int]:
        """The predictions left out before scoring, by reason, as ``metrics.dropped_detections`` counts them: the
        unknown categories and images of the matching added to the evaluation's own (only non-zero counts)."""
        out = {
            "unknown_category": sum(self.unmatched_categories.values()),
            "unknown_image": sum(self.unmatched_images.values()) - self.not_listed,
            "not_in_image_list": self.not_listed,
            "outside_fold": self.outside_fold,
            "outside_frame": self.dropped_outside_frame,
            "malformed": self.invalid,
        }
        return {k: v for k, v in out.items() if v}

    def invalid_add(self, reason: str, det: Any) -> None:
        self.invalid += 1
        self.invalid_reasons[reason] += 1
        if len(self.invalid_examples) < 5:
            self.invalid_examples.append(_cut(json.dumps(det, default=str)))

    def lines(self) -> list[str]:
        out = [
            f"{self.scored} of {self.predictions} predictions scored on {self.images_scored} of "
            f"{self.fold_images} fold images"
        ]
        if self.missing_images:
            out.append(
                f"{len(self.missing_images)} fold image(s) missing from the image list (left out of the "
                f"ground truth: not sample-matched), e.g. {', '.join(self.missing_images[:3])}"
            )
        if self.images_without_predictions:
            out.append(f"{self.images_without_predictions} scored image(s) without any prediction")
        if self.unmatched_images:
            ex = ", ".join(str(k) for k, _ in self.unmatched_images.most_common(3))
            out.append(
                f"{sum(self.unmatched_images.values())} prediction(s) of {len(self.unmatched_images)} "
                f"unknown image(s) left out, e.g. {ex}"
            )
        if self.outside_fold:
            out.append(f"{self.outside_fold} prediction(s) of images outside the fold left out")
        if self.unmatched_categories:
            ex = ", ".join(f"{k} ({v})" for k, v in self.unmatched_categories.most_common(5))
            out.append(f"{sum(self.unmatched_categories.values())} prediction(s) of unknown categories left out: {ex}")
        if self.dropped_outside_frame:
            out.append(f"{self.dropped_outside_frame} box(es) fell outside the prepared frame and were left out")
        if self.invalid:
            why = ", ".join(f"{k}: {v}" for k, v in self.invalid_reasons.most_common())
            out.append(f"{self.invalid} malformed prediction(s) left out ({why}), e.g. {self.invalid_examples[0]}")
        return out


#: ``eval`` settings that change a score, with the value that leaves a stored identity as it was before they counted.
EVAL_IDENTITY = {"engine": None, "matching": None, "safit_anchor": "center", "strict": False}


def _eval_identity(ev: Mapping[str, Any]) -> dict[str, Any]:
    """The ``eval`` settings of a score's identity: engine and matching, the others where they are not the default."""
    return {k: ev.get(k) for k, default in EVAL_IDENTITY.items() if default is None or ev.get(k, default) != default}


@dataclass
class ScoreResult:
    run_path: Path
    metrics: dict[str, Any]
    matching: Matching
    state: str  # "scored" or "skipped"


class _ImageIndex:
    """Fold samples by relative path, base name, stem and numeric stem (``010001.jpg`` is also ``10001``)."""

    def __init__(self, entries: Sequence[tuple[int, Sequence[str]]]):
        self.by: list[dict[str, set[int]]] = [{}, {}, {}, {}]
        for idx, names in entries:
            for name in names:
                for level, key in enumerate(self._keys(name)):
                    if key is not None:
                        self.by[level].setdefault(key, set()).add(idx)

    @staticmethod
    def _keys(name: Any) -> tuple[str | None, ...]:
        """Relative path, base name, stem, and a numeric stem as a number (Ultralytics writes ``int(stem)``)."""
        p = PurePosixPath(str(name).replace("\\", "/"))
        return (str(p).lower(), p.name.lower(), p.stem.lower(), str(int(p.stem)) if p.stem.isdigit() else None)

    def find(self, name: Any) -> int | None:
        for level, key in enumerate(self._keys(name)):
            hit = self.by[level].get(key) if key is not None else None
            if hit and len(hit) == 1:
                return next(iter(hit))
        return None


def _load_predictions(path: Path) -> list[dict[str, Any]]:
    try:
        data = read_json(path)
    except Exception as exc:
        raise DataError(f"--predictions {path}: not readable JSON ({exc})") from None
    if isinstance(data, Mapping) and isinstance(data.get("annotations"), list):
        data = data["annotations"]  # a COCO file with detections as annotations (score required below)
    if not isinstance(data, list):
        raise DataError(f"--predictions {path}: expected a COCO results list [{{image_id, category_id, bbox, score}}]")
    return data


def _cut(text: str, width: int = 120) -> str:
    return text if len(text) <= width else text[: width - 3] + "..."


def _as_int(value: Any) -> int | None:
    """``12``, ``12.0`` and ``"12"`` as 12; anything else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str) and re.fullmatch(r"[+-]?\d+", value.strip()):
        return int(value)
    return None


def _category_resolver(
    categories: Sequence[str], names_by_id: Mapping[Any, str], mapping: Mapping[str, str] | None
) -> Any:
    """``resolve(det) -> (label or None, reference shown to the user, the id when it was read as the harness's)``."""
    ours = {normalise_category(c): i for i, c in enumerate(categories)}
    explicit = {str(k): v for k, v in (mapping or {}).items()}
    for their, our in explicit.items():
        if normalise_category(our) not in ours:
            raise ConfigError(
                f"--category-map {their}={our}: {our!r} is not a category of the dataset ({', '.join(categories)})"
            )

    def resolve(det: Mapping[str, Any]) -> tuple[int | None, str, int | None]:
        cid = det.get("category_id")
        name = det.get("category_name")
        if name is None and cid is not None:
            name = names_by_id.get(cid, names_by_id.get(str(cid)))
        if name is None and isinstance(cid, str) and _as_int(cid) is None:
            name = cid  # a class name written as category_id (some exporters do): a word can only be a name
        if name is None and cid is None:
            return None, "no category_id or category_name", None
        for key in (str(cid) if cid is not None else None, name):
            if key is not None and str(key) in explicit:
                return ours[normalise_category(explicit[str(key)])], str(key), None
        if name is not None:
            return ours.get(normalise_category(name)), str(name), None
        bare = _as_int(cid)  # no names anywhere: the harness's own ids (category_id = label + 1)
        if bare is not None and 1 <= bare <= len(categories):
            return bare - 1, str(cid), bare
        return None, str(cid), bare

    return resolve


def match_predictions(
    prepared: Any,
    val_idx: Sequence[int],
    predictions: list[dict[str, Any]],
    frame: str,
    images: Mapping[str, Any] | None = None,
    image_key: str = "file_name",
    category_map: Mapping[str, str] | None = None,
    box_format: str = "xywh",
) -> tuple[list[dict[str, Any]], list[int], Matching]:
    """External predictions -> the harness's detections on the fold (prepared frame, its image and category ids),
    the indices of the images that were scored, and the matching counts with the plausibility findings (see the
    module docstring)."""
    if frame not in FRAMES:
        raise ConfigError(f"--frame {frame!r}: use one of {', '.join(FRAMES)}")
    if box_format not in BOX_FORMATS:
        raise ConfigError(f"--box-format {box_format!r}: use one of {', '.join(BOX_FORMATS)}")
    records = prepared.records
    fold = set(int(i) for i in val_idx)
    all_entries = []
    for i, r in enumerate(records):
        meta = r.get("meta") or {}
        names = [image_name(meta, frame, r["image_id"]), meta.get("file_name"), meta.get("thermal_file")]
        all_entries.append((i, [n for n in names if n]))
    index = _ImageIndex(all_entries)
    by_id = {int(r["image_id"]): i for i, r in enumerate(records)}
    m = Matching(predictions=len(predictions), fold_images=len(fold))

    their_images: dict[Any, str] = {}
    names_by_id: dict[Any, str] = {}
    listed: set[int] | None = None
    if images is not None:
        listed = set()
        m.listed_images = len(images.get("images") or [])
        for im in images.get("images") or []:
            fname = im.get(image_key) or im.get("file_name")
            if "id" in im and fname:
                their_images[im["id"]] = str(fname)
                hit = index.find(str(fname))
                if hit is not None:
                    listed.add(hit)
        names_by_id = {c["id"]: c["name"] for c in images.get("categories") or [] if "id" in c and "name" in c}
    resolve = _category_resolver(prepared.categories, names_by_id, category_map)

    # per fold image: (box in `frame`, score, label or None, category id read as the harness's or None)
    grouped: dict[int, list[tuple[list[float], float, int | None, int | None]]] = {}
    # per fold image, in the order of ``grouped``: the label its category_id gives where a category_name was also
    # written (None elsewhere), and how often each (id, name) pair was written
    by_cid: dict[int, list[int | None]] = {}
    pairs: Counter = Counter()
    # predictions whose image id was read as the harness's: (that id, box, score, label or None)
    by_harness_id: list[tuple[int, list[float], float, int | None]] = []
    for det in predictions:
        try:
            x, y, w, h = (float(v) for v in det["bbox"])
            score = float(det["score"])
        except (KeyError, TypeError, ValueError):
            m.invalid_add("no bbox of four numbers or no score", det)
            continue
        if not all(np.isfinite([x, y, w, h, score])):
            m.invalid_add("not finite", det)
            continue
        if box_format == "xyxy":
            w, h = w - x, h - y
        if w < 0 or h < 0:
            m.invalid_add("negative width or height" if box_format == "xywh" else "x2 < x1 or y2 < y1", det)
            continue
        box = [x, y, x + w, y + h]
        image_id = det.get("image_id")
        name = det.get(image_key) or det.get("file_name")
        if name is None and image_id in their_images:
            name = their_images[image_id]
        if name is None and isinstance(image_id, str) and _as_int(image_id) is None:
            name = image_id  # a file stem as image id (Ultralytics writes the stem when it is not a number)
        label, cref, bare_cat = resolve(det)
        if name is not None:
            idx = index.find(str(name))
            ref = str(name)
        else:
            number = _as_int(image_id)
            idx = by_id.get(number) if number is not None else None
            ref = f"image_id {image_id}"
            if number is not None:
                m.by_harness_id += 1
                by_harness_id.append((number, box, score, label))
        if idx is None:
            m.unmatched_images[ref] += 1
            continue
        if idx not in fold:
            m.outside_fold += 1
            m.outside_fold_by_id += name is None
            continue
        if label is None:
            m.unmatched_categories[cref] += 1
        grouped.setdefault(idx, []).append((box, score, label, bare_cat))
        by_cid.setdefault(idx, []).append(_id_label(det, names_by_id, prepared.categories, pairs))

    # every fold image's predictions in the prepared frame (also those of unknown categories, for the guard)
    moved: dict[int, list[tuple[list[float], float, int | None, int | None]]] = {}
    for i, items in grouped.items():
        r = records[i]
        boxes, keep = to_prepared(
            np.array([b for b, _, _, _ in items]),
            frame,
            r.get("meta") or {},
            size=(r["width"], r["height"]),
            min_size=None,
            where=f"image {r['image_id']}",
        )
        moved[i] = [
            (b, score, label, bare)
            for b, (_, score, label, bare) in zip(boxes.tolist(), (it for it, k in zip(items, keep) if k))
        ]
        by_cid[i] = [c for c, k in zip(by_cid[i], keep) if k]
        if listed is None or i in listed:
            m.dropped_outside_frame += int((~keep).sum())

    scored_idx = sorted(fold if listed is None else fold & listed)
    if listed is not None:
        m.missing_images = sorted(
            str((records[i].get("meta") or {}).get("file_name", records[i]["image_id"])) for i in fold - listed
        )
        dropped_unlisted = sum(len(v) for k, v in grouped.items() if k not in listed)
        if dropped_unlisted:
            log.warning("%d prediction(s) of images the image list does not name were left out", dropped_unlisted)
            m.unmatched_images[NOT_LISTED] += dropped_unlisted
            m.not_listed = dropped_unlisted
    m.images_scored = len(scored_idx)
    dets: list[dict[str, Any]] = []
    for i in scored_idx:
        items = [it for it in moved.get(i, []) if it[2] is not None]
        if not grouped.get(i):
            m.images_without_predictions += 1
        for (x1, y1, x2, y2), score, label, _ in items:
            dets.append(
                {
                    "image_id": int(records[i]["image_id"]),
                    "category_id": int(label) + 1,  # type: ignore[arg-type]
                    "bbox": [x1, y1, x2 - x1, y2 - y1],
                    "score": score,
                }
            )
    m.scored = len(dets)
    m.findings = _findings(prepared, m, moved, by_harness_id, by_id, fold, frame)
    m.findings += _box_guard(prepared, m, grouped, fold if listed is None else fold & listed, frame, box_format)
    m.findings += _agreement(prepared, m, moved, by_cid, pairs, scored_idx)
    return dets, scored_idx, m


Moved = Mapping[int, list[tuple[list[float], float, "int | None", "int | None"]]]


def _findings(
    prepared: Any,
    m: Matching,
    moved: Moved,
    by_harness_id: list[tuple[int, list[float], float, int | None]],
    by_id: Mapping[int, int],
    fold: set[int],
    frame: str,
) -> list[Finding]:
    """What makes the matching implausible (``harness.scoring.plausibility``), with counts and examples."""
    out: list[Finding] = []
    n = m.predictions
    if too_many(m.invalid, n):
        why = ", ".join(f"{k}: {v}" for k, v in m.invalid_reasons.most_common())
        out.append(
            Finding(
                "malformed",
                f"{m.invalid} of {n} predictions ({pct(m.invalid, n)}) are malformed ({why}), "
                f"e.g. {m.invalid_examples[0]}; check --box-format (x, y, w, h or x1, y1, x2, "
                f"y2) and that every prediction has a bbox of four finite numbers and a "
                f"score",
            )
        )
    unknown = sum(m.unmatched_images.values()) - m.not_listed
    if too_many(unknown, n):
        ex = ", ".join(str(k) for k, v in m.unmatched_images.most_common(4) if k != NOT_LISTED)
        hint = (
            f"; their image_id values are not in the image list given with --images ({m.listed_images} images) "
            "and were read as the harness's image ids: give the complete list the predictions were made on"
            if m.by_harness_id and m.listed_images is not None
            else "; their image_id values were read as the harness's image ids: give the other codebase's image list "
            "with --images (for MMDetection, the annotation file it was tested on)"
            if m.by_harness_id
            else "; check --image-key and --images"
        )
        out.append(
            Finding(
                "unknown_images",
                f"{unknown} of {n} predictions ({pct(unknown, n)}) are on images the "
                f"dataset does not have, e.g. {ex}{hint}",
            )
        )
    other = m.outside_fold_by_id
    if too_many(other, n):
        out.append(
            Finding(
                "other_folds_by_id",
                f"{other} of {n} predictions ({pct(other, n)}) name images of other "
                f"folds by the harness's image ids; if these are the other codebase's "
                f"own ids, {_list_advice(m.listed_images)}",
            )
        )
    on_fold = sum(len(v) for v in moved.values())
    unknown_cat = sum(m.unmatched_categories.values())
    many_unknown_cat = too_many(unknown_cat, on_fold)
    if many_unknown_cat:
        ex = ", ".join(f"{k} ({v})" for k, v in m.unmatched_categories.most_common(4))
        out.append(
            Finding(
                "unknown_categories",
                f"{unknown_cat} of {on_fold} predictions on the fold's images "
                f"({pct(unknown_cat, on_fold)}) are in categories the dataset does "
                f"not have: {ex}",
            )
        )
    out += _category_shift(prepared, moved, sorted(fold), many_unknown_cat)
    if by_harness_id:
        out += _image_shift(prepared, by_harness_id, by_id, fold, frame, m.listed_images)
    return out


def _list_advice(listed_images: int | None) -> str:
    """What to do about image ids read as the harness's: give the other codebase's image list, or, where one was
    given, the complete one (those ids are not in it)."""
    if listed_images is None:
        return "give its image list with --images"
    return (
        f"they are not in the image list given with --images ({listed_images} images): give the complete list "
        "the predictions were made on"
    )


def _id_label(det: Mapping[str, Any], names_by_id: Mapping[Any, str], categories: Sequence[str], pairs: Counter) -> Any:
    """The label a prediction's ``category_id`` gives where it also has a ``category_name`` (the names win; this is
    the other reading), counting the (id, name) pair; None without both."""
    cid, name = det.get("category_id"), det.get("category_name")
    if cid is None or name is None:
        return None
    pairs[(str(cid), normalise_category(str(name)))] += 1
    ours = {normalise_category(c): i for i, c in enumerate(categories)}
    their = names_by_id.get(cid, names_by_id.get(str(cid)))
    if their is not None:
        return ours.get(normalise_category(their))
    bare = _as_int(cid)
    return bare - 1 if bare is not None and 1 <= bare <= len(categories) else None


#: What ``harness score`` says to do about a finding of the agreement check (``harness.scoring.agreement``).
AGREEMENT_FIXES = {
    "score_scale": "write scores as probabilities in 0..1 (percentages divided by 100, logits through the sigmoid)",
    "duplicates": "write each detection once",
    "label_shift": "map the categories with --category-map THEIR=OURS",
    "box_format": "write boxes as x, y, w, h (or corners with --box-format xyxy)",
    "image_shift": "check the image ids (and the image list given with --images)",
}


def _agreement(
    prepared: Any,
    m: Matching,
    moved: Moved,
    by_cid: Mapping[int, list[int | None]],
    pairs: Counter,
    scored: Sequence[int],
) -> list[Finding]:
    """The agreement check shared with ``harness run`` (``harness.scoring.agreement``) on the predictions of the
    scored images, for what the guards above did not find, and ``category_conflict``: ``category_id`` and
    ``category_name`` that disagree (the names are read), inconsistently, or with the ids agreeing far better."""
    from harness.scoring import agreement as ag

    records = prepared.records
    order = sorted(scored, key=lambda i: int(records[i]["image_id"]))
    preds = [(i, b, s, lab) for i in order for b, s, lab, _ in moved.get(i, [])]
    if not preds:
        return []
    # a misreading found above makes every other reading agree a little by chance: then only scores and duplicates
    misread = {f.kind for f in m.findings} - {"other_folds_by_id"}
    only = ["score_scale", "duplicates"] + ([] if misread else ["label_shift", "box_format", "image_shift"])
    out: list[Finding] = []
    n = sum(pairs.values())
    if n:  # names and ids that disagree: the names are read; say so before any other reading of the labels
        by_id: dict[str, Counter] = {}
        by_name: dict[str, Counter] = {}
        for (cid, name), c in pairs.items():
            by_id.setdefault(cid, Counter())[name] += c
            by_name.setdefault(name, Counter())[cid] += c
        odd = max(n - sum(c.most_common(1)[0][1] for c in d.values()) for d in (by_id, by_name))
        both = [(i, it, c) for i in order for it, c in zip(moved.get(i, []), by_cid[i]) if c is not None]
        as_named = ag.ap50([(i, it[0], it[1], it[2]) for i, it, _ in both], prepared.targets, order)
        as_ids = ag.ap50([(i, it[0], it[1], c) for i, it, c in both], prepared.targets, order)
        if too_many(odd, n) or ag.found(as_named, as_ids, ag.count_objects(prepared.targets, order)):
            ex = ", ".join(f"{cid}/{name}" for (cid, name), _ in pairs.most_common(4))
            out.append(
                Finding(
                    "category_conflict",
                    f"category_id and category_name disagree: {len(pairs)} id/name pairs in {n} predictions, "
                    f"e.g. {ex}{f' ({odd} against the pairing of the others)' if odd else ''}; AP50 "
                    f"{as_named or 0:.3f} by name (as read), {as_ids or 0:.3f} by id: write one of them, or map "
                    f"them with --category-map",
                )
            )
            only = only[:2]
    out += [
        Finding(f.kind, f"{f.message}; {AGREEMENT_FIXES[f.kind]}")
        for f in ag.check(preds, prepared.targets, order, len(prepared.categories), only=only)
    ]
    return out


Grouped = Mapping[int, list[tuple[list[float], float, "int | None", "int | None"]]]


def _box_guard(
    prepared: Any, m: Matching, grouped: Grouped, images: set[int], frame: str, box_format: str
) -> list[Finding]:
    """The box guard (``harness.scoring.plausibility``) on the predictions of the scored fold images: normalised
    coordinates, corners where ``x, y, w, h`` is expected, boxes mostly outside the prepared frame or agreeing with the
    ground truth far better in another frame (``--frame``)."""
    records = prepared.records
    idxs = [i for i in sorted(images) if grouped.get(i)]
    if not idxs:
        return []
    given = {i: np.array([b for b, _, _, _ in grouped[i]], dtype=np.float64).reshape(-1, 4) for i in idxs}
    size = np.concatenate([np.tile([[records[i]["width"], records[i]["height"]]], (len(given[i]), 1)) for i in idxs])
    as_given = np.concatenate([given[i] for i in idxs])
    n = len(as_given)

    def place(
        boxes: Mapping[int, np.ndarray], in_frame: str, keep_all: bool = False
    ) -> list[tuple[int | None, list[float], float, int | None]]:
        """The predictions read as ``boxes`` in the prepared frame; ``keep_all``: one entry per prediction, in order,
        a dropped one with no sample."""
        out: list[tuple[int | None, list[float], float, int | None]] = []
        for i in idxs:
            r = records[i]
            b, keep = to_prepared(
                boxes[i],
                in_frame,
                r.get("meta") or {},
                size=(r["width"], r["height"]),
                min_size=None,
                where=f"image {r['image_id']}",
            )
            kept = iter(b.tolist())
            for (_, s, lab, _), k in zip(grouped[i], keep):
                if k:
                    out.append((i, next(kept), s, lab))
                elif keep_all:
                    out.append((None, [0.0, 0.0, 0.0, 0.0], s, lab))
        return out

    def in_prepared(in_frame: str) -> np.ndarray:
        return np.concatenate([unclipped(given[i], in_frame, records[i].get("meta") or {}) for i in idxs])

    fold = sorted(idxs)
    moved_given = in_prepared(frame)
    norm = box_findings(
        moved_given,
        size[:, 0],
        size[:, 1],
        "predictions",
        "prepared frame",
        fix_outside="",
        fix_normalised="multiply x and w by the image width, y and h by its height",
        given=as_given,
        only=("normalised",),
    )
    if norm:
        return norm
    agree = agreement(place(given, frame), prepared.targets, fold)
    if box_format == "xywh":  # corners x1, y1, x2, y2 written where COCO's x, y, w, h is expected
        xywh = as_given.copy()
        xywh[:, 2:] -= xywh[:, :2]
        corners = {i: given[i].copy() for i in idxs}
        for b in corners.values():
            b[:, 2:] -= b[:, :2]  # the written w, h read as x2, y2
            b[(b[:, 2] <= b[:, 0]) | (b[:, 3] <= b[:, 1])] = np.nan
        as_corners = agreement(place(corners, frame), prepared.targets, fold)
        like = corner_like(xywh)
        k = int(like.sum())
        # nearly all look like corners, and read as corners fewer lie outside the frame and none agree less
        fewer_outside = (
            mostly_outside(
                np.concatenate([unclipped(corners[i], frame, records[i].get("meta") or {}) for i in idxs]),
                size[:, 0],
                size[:, 1],
            ).sum()
            < mostly_outside(moved_given, size[:, 0], size[:, 1]).sum()
        )
        structural = (
            n >= XYXY_MIN_BOXES and k >= XYXY_SHARE * n and fewer_outside and (as_corners or 0.0) >= (agree or 0.0)
        )
        # a file mixing the two: many predictions overlap an object only when read as corners
        only_corners = int(
            (
                overlaps_truth(place(corners, frame, keep_all=True), prepared.targets)
                & ~overlaps_truth(place(given, frame, keep_all=True), prepared.targets)
            ).sum()
        )
        mixed = too_many(only_corners, n) and only_corners >= XYXY_MIN_BOXES // 2
        if mixed and not (shift_found(agree, as_corners) or structural):
            return [
                Finding(
                    "box_format",
                    f"{only_corners} of {n} predictions ({pct(only_corners, n)}) overlap an object of their category "
                    f"only when read as corners x1, y1, x2, y2: a file mixing x, y, w, h and corner boxes? write "
                    f"every box one way (x, y, w, h, or corners with --box-format xyxy)",
                )
            ]
        if shift_found(agree, as_corners) or structural:
            seen = (
                f"; recall at IoU 0.50 {agree or 0:.0%} as x, y, w, h, {as_corners:.0%} as corners"
                if as_corners is not None
                else ""
            )
            return [
                Finding(
                    "box_format",
                    f"{k} of {n} predictions ({pct(k, n)}) have w >= x and h >= y, as corners "
                    f"x1, y1, x2, y2 do, e.g. {examples(xywh, like)}{seen}: if they are "
                    f"corners, pass --box-format xyxy",
                )
            ]
    # another frame: the boxes fit the prepared frame, or agree with the ground truth, far better read in it
    others: list[tuple[str, float, float | None]] = []
    for other in FRAMES:
        if other == frame:
            continue
        try:
            share = float(mostly_outside(in_prepared(other), size[:, 0], size[:, 1]).mean())
            others.append((other, share, agreement(place(given, other), prepared.targets, fold)))
        except (DataError, ValueError, np.linalg.LinAlgError):
            continue  # the samples record no map from that frame
    hint = "; ".join(
        f"read as --frame {o}: {share:.0%} mostly outside" + (f", recall at IoU 0.50 {a:.0%}" if a is not None else "")
        for o, share, a in others
    )
    fitting = [o for o in others if o[1] <= 0.5 and (o[2] or 0.0) > (agree or 0.0)]
    fix = f"pass --frame {max(fitting, key=lambda o: o[2] or 0.0)[0]}" if fitting else "wrong --frame or scale?"
    out = box_findings(
        moved_given,
        size[:, 0],
        size[:, 1],
        "predictions",
        "prepared frame",
        fix_outside=f"{fix} (as read with --frame {frame}" + (f"; {hint})" if hint else ")"),
        fix_normalised="",
        only=("outside",),
    )
    better = [o for o in others if shift_found(agree, o[2])]
    if better and not out:
        best = max(better, key=lambda o: o[2] or 0.0)
        out.append(
            Finding(
                "frame",
                f"the predictions agree with the ground truth far better read in another frame "
                f"(recall at IoU 0.50 {agree or 0:.0%} as --frame {frame}, {best[2]:.0%} as "
                f"--frame {best[0]}): pass --frame {best[0]}",
            )
        )
    return out


def _category_shift(prepared: Any, moved: Moved, fold: list[int], many_unknown: bool) -> list[Finding]:
    """Category ids read as the harness's that fit, or agree with the ground truth, only shifted by one."""
    cats = list(prepared.categories)
    bare = [(i, b, s, c) for i, items in moved.items() for b, s, _, c in items if c is not None]
    ids = sorted({c for _, _, _, c in bare})
    if not ids:
        return []

    def read(shift: int) -> list[tuple[int, list[float], float, int | None]]:
        return [(i, b, s, c - 1 + shift if 0 <= c - 1 + shift < len(cats) else None) for i, b, s, c in bare]

    def roll(shift: int) -> list[tuple[int, list[float], float, int | None]]:
        return [(i, b, s, (c - 1 + shift) % len(cats)) for i, b, s, c in bare]

    given = agreement(read(0), prepared.targets, fold)
    for shift in (1, -1):
        shifted = agreement(read(shift), prepared.targets, fold)
        fits_only_shifted = (ids[0] < 1 or ids[-1] > len(cats)) and all(1 <= c + shift <= len(cats) for c in ids)
        rolled = agreement(roll(shift), prepared.targets, fold) if 1 <= ids[0] and ids[-1] <= len(cats) else None
        if len(cats) > 1 and shift_found(given, rolled) and (rolled or 0.0) > (shifted or 0.0):
            mapping = ",".join(f"{c}={cats[(c - 1 + shift) % len(cats)]}" for c in range(1, len(cats) + 1))
            return [
                Finding(
                    "category_shift",
                    f"category ids {ids[0]}..{ids[-1]} match the dataset's 1..{len(cats)} only rolled by "
                    f"{shift:+d} (id {len(cats) if shift == 1 else 1} as {cats[0] if shift == 1 else cats[-1]}; "
                    f"recall at IoU 0.50 {given or 0:.0%} as read, {rolled:.0%} rolled): map them: "
                    f"--category-map {mapping}",
                )
            ]
        if shift_found(given, shifted) or (fits_only_shifted and many_unknown):
            mapping = ",".join(f"{k + 1 - shift}={c}" for k, c in enumerate(cats))
            seen = (
                f"; recall at IoU 0.50 {given or 0:.0%} as read, {shifted:.0%} shifted" if shifted is not None else ""
            )
            guess = "0-based class ids, as Ultralytics 8.0 writes them? " if shift == 1 else ""
            return [
                Finding(
                    "category_shift",
                    f"category ids {ids[0]}..{ids[-1]} match the dataset's 1..{len(cats)} "
                    f"only after a shift of {shift:+d}{seen} ({guess}map them: "
                    f"--category-map {mapping})",
                )
            ]
    return []


def _image_shift(
    prepared: Any,
    by_harness_id: list[tuple[int, list[float], float, int | None]],
    by_id: Mapping[int, int],
    fold: set[int],
    frame: str,
    listed_images: int | None = None,
) -> list[Finding]:
    """Image ids read as the harness's whose predictions agree with the ground truth only shifted by one."""

    def place(shift: int) -> list[tuple[int, list[float], float, int | None]]:
        groups: dict[int, list[tuple[list[float], float, int | None]]] = {}
        for number, b, s, label in by_harness_id:
            idx = by_id.get(number + shift)
            if idx is not None and idx in fold:
                groups.setdefault(idx, []).append((b, s, label))
        out: list[tuple[int, list[float], float, int | None]] = []
        for idx, items in groups.items():
            r = prepared.records[idx]
            boxes, keep = to_prepared(
                np.array([b for b, _, _ in items]),
                frame,
                r.get("meta") or {},
                size=(r["width"], r["height"]),
                min_size=None,
            )
            kept = (it for it, k in zip(items, keep) if k)
            out += [(idx, b, s, lab) for b, (_, s, lab) in zip(boxes.tolist(), kept)]
        return out

    given = agreement(place(0), prepared.targets, sorted(fold))
    for shift in (1, -1):
        shifted = agreement(place(shift), prepared.targets, sorted(fold))
        if shift_found(given, shifted):
            return [
                Finding(
                    "image_shift",
                    f"image ids read as the harness's match the fold's images only after a "
                    f"shift of {shift:+d} (recall at IoU 0.50 {given or 0:.0%} as read, "
                    f"{shifted:.0%} shifted): are they the other codebase's own ids? "
                    f"{_list_advice(listed_images)}",
                )
            ]
    return []


def score_external(
    dataset: str,
    fold: str,
    predictions: str | Path,
    name: str,
    frame: str = "prepared",
    images: str | Path | None = None,
    image_key: str = "file_name",
    category_map: Mapping[str, str] | None = None,
    profile: str | None = "smoke",
    config_files: Sequence[str | Path] = (),
    overrides: Sequence[str] = (),
    store: str | Path | None = None,
    root: str | None = None,
    params: float | None = None,
    gflops: float | None = None,
    force: bool = False,
    allow_implausible: bool = False,
    box_format: str = "xywh",
) -> ScoreResult:
    """Score ``predictions`` on ``fold`` of ``dataset`` and store them as run ``external/NAME`` (module docstring).

    Predictions that look misread (``harness.scoring.plausibility``) are refused with what was seen, unless
    ``allow_implausible``: then they are scored as read and the stored result is labelled."""
    from harness.cache import fold_indices, prepare, resolve_folds
    from harness.config import load_config
    from harness.evaluation import evaluate_with_config
    from harness.evaluation.analysis import store_analysis
    from harness.plugins import get_host
    from harness.store import EXTERNAL, RunKey, Store, config_hash, image_ids_hash

    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+\-]*", name or ""):
        raise ConfigError(f"--name {name!r}: use letters, digits and . _ + - (it names a folder in the store)")
    pred_path = Path(predictions)
    if not pred_path.is_file():
        raise DataError(f"--predictions {pred_path}: no such file")
    host = get_host()
    spec = host.dataset(dataset)
    cfg = load_config(profile, protocol=spec.protocol, files=config_files, overrides=overrides)
    if root is not None:
        cfg.setdefault("dataset", {})["root"] = root
    prepared = prepare(spec.name, cfg)
    folds = resolve_folds(spec, prepared, cfg, fold)
    if len(folds) != 1:
        raise ConfigError(f"--folds {fold!r} selects {len(folds)} folds of {dataset!r}; give exactly one")
    f = folds[0]
    _, val_idx = fold_indices(prepared, f)
    image_list = None
    if images is not None:
        try:
            image_list = read_json(Path(images))
        except Exception as exc:
            raise DataError(f"--images {images}: not readable JSON ({exc})") from None
    loaded = _load_predictions(pred_path)
    if not loaded:
        raise DataError(
            f"--predictions {pred_path}: holds no predictions; nothing was stored (a detector that finds "
            f"nothing on {len(val_idx)} images is more likely an export that went wrong)"
        )
    dets, scored_idx, m = match_predictions(
        prepared, val_idx, loaded, frame, image_list, image_key, category_map, box_format
    )
    if m.scored == 0 and m.predictions:
        raise DataError(
            f"--predictions {pred_path}: none of the {m.predictions} predictions matched the fold's "
            "images and categories:\n  " + "\n  ".join(m.lines() + [f"- {x}" for x in m.findings])
        )
    if m.findings and not allow_implausible:
        raise DataError(
            f"--predictions {pred_path}: implausible as read for fold {f.name} of {spec.name}, nothing "
            f"was stored:\n  "
            + "\n  ".join(f"- {x}" for x in m.findings)
            + "\nAs read:\n  "
            + "\n  ".join(m.lines())
            + "\nFix the mapping as suggested, or pass --allow-implausible to score them as read "
            "(the stored result is labelled)."
        )

    key = RunKey(spec.name, EXTERNAL + name, ENCODING, f.name, 0)
    results = Store(store or Path("results") / (profile or "default"))
    run = results.run(key)
    identity = {
        "predictions_sha1": file_digest(pred_path),
        "frame": frame,
        "image_key": image_key,
        "images_sha1": file_digest(images) if images else None,
        "category_map": dict(category_map or {}),
        "prepared_fingerprint": prepared.manifest.get("fingerprint"),
        "fold": f.name,
        "val_groups": list(f.val_groups),
        "eval": _eval_identity(cfg["eval"]),
        "params": params,
        "gflops": gflops,
    }
    if box_format != "xywh":  # the default leaves the identity of earlier scores as it was
        identity["box_format"] = box_format
    digest = config_hash(identity)
    st = run.status() or {}
    if run.is_finished() and not force:
        if st.get("config_hash") == digest:
            log.info("%s: scored earlier from the same file, skipped (use --force to redo)", key)
            return ScoreResult(run.path, read_run(run).metrics, m, "skipped")
        raise StoreError(
            f"{key} was scored earlier from other predictions or options; use --force to replace it, or another --name"
        )
    gt = prepared.coco(scored_idx)
    evaluation = evaluate_with_config(gt, dets, cfg)
    support = dict(evaluation["support"])
    support.setdefault("image_ids_sha1", image_ids_hash([int(i["id"]) for i in gt["images"]]))
    dropped = evaluation["metrics"].get("dropped_detections")
    if isinstance(dropped, dict):  # what the matching left out counts as dropped too (0 everywhere: unchanged)
        for k, v in m.dropped().items():
            dropped[k] = int(dropped.get(k, 0)) + v
    metrics = {
        "support": support,
        "metrics": evaluation["metrics"],
        "per_category": evaluation["per_category"],
        "model": {"input_kind": "external"},
        "complexity": given(params, gflops),
        "external": {
            **identity,
            "predictions": str(pred_path),
            "images": str(images) if images else None,
            "matching": m.to_dict(),
        },
    }
    if m.findings:
        metrics["labels"] = [f"implausible predictions scored as read (--allow-implausible): {x}" for x in m.findings]
        for label in metrics["labels"]:
            log.warning("%s", label)
    run.path.mkdir(parents=True, exist_ok=True)
    atomic_write_json(run.path / "score.json", {"identity": identity, "matching": m.to_dict()})
    from harness.runner import run_config

    # the configuration it was scored under, with the prepared samples it was scored on (what a gallery draws)
    run.write_config(
        run_config(
            cfg,
            key,
            {
                "prepared_fingerprint": prepared.manifest.get("fingerprint"),
                "prepared_key": str(getattr(prepared, "key", None) or prepared.manifest.get("key", "")),
                "val_groups": list(f.val_groups),
                "external": True,
            },
        )
    )
    atomic_write_json(run.predictions_path, dets, indent=None)
    atomic_write_json(run.gt_path, gt, indent=None)
    store_analysis(run, gt, dets, cfg, evaluation["metrics"].get("conf_threshold"))
    run.write_metrics(metrics)
    run.set_status("finished", config_hash=digest, error=None, fold=f.name, seed=0)
    results.write_dataset(spec)
    return ScoreResult(run.path, read_run(run).metrics, m, "scored")


def parse_category_map(text: str | None) -> dict[str, str]:
    """``"1=window,crack=crack"`` or a JSON file ``{"1": "window"}`` -> ``{their: our}``."""
    if not text:
        return {}
    p = Path(text)
    if p.suffix == ".json" and p.is_file():
        data = json.loads(p.read_text())
        if not isinstance(data, dict):
            raise ConfigError(f"--category-map {p}: expected a JSON object {{their id or name: our name}}")
        return {str(k): str(v) for k, v in data.items()}
    out = {}
    for part in text.split(","):
        if "=" not in part:
            raise ConfigError(f"--category-map {text!r}: expected THEIR=OURS pairs separated by commas")
        a, b = part.split("=", 1)
        out[a.strip()] = b.strip()
    return out
