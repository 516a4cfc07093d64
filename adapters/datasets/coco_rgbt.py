"""``coco-rgbt``: your own aligned RGB-thermal pairs, described by one COCO JSON.

Layout (``dataset.root``; every path is relative to it and may not leave it)::

    annotations.json          COCO detection file (dataset.annotations names another one)
    <any folders>/...         the RGB images and thermal frames the JSON names

The JSON is ordinary COCO with three keys added to each ``images[]`` entry::

    {"id": 1, "file_name": "rgb/a_001.png", "thermal_file_name": "thermal/a_001.png", "group": "site-a",
     "width": 640, "height": 512,                      # optional: the thermal frame's size, checked
     "homography": [[...], [...], [...]]}              # optional: RGB pixels -> thermal pixels (3x3)

and, at the top level, optionally ``"homographies": {group: 3x3}`` (one per group) and ``"folds": {fold name:
[held-out groups]}``. Boxes (``annotations[].bbox``, ``[x, y, w, h]``) are in the shared frame: the thermal
frame, which the RGB image shares when both have the same size.

What the loader does:

* **Thermal.** With ``dataset.thermal: radiometric`` (the default) each thermal file becomes a float32 temperature
  map in C: 16-bit PNG/TIFF in centi-Kelvin (what ``harness sensing decode`` writes; its sidecar's unit is
  honoured, ``dataset.thermal_scale``/``thermal_offset`` override: ``C = value * scale + offset``), float32 TIFF
  or ``.npy`` in C, or a DJI R-JPEG (decoded by ``harness.sensing.radiometry``). The C2 encoding is then
  computed from those temperatures. With ``dataset.thermal: 8bit`` the thermal files are 8-bit images, the
  sample carries no temperatures and the 8-bit encodings apply (``--encoding proxy8`` or ``ir8``).
* **Registration.** An RGB image of another size than its thermal frame is warped into the thermal frame by the
  homography of its image entry, else of its group (``harness.sensing.warp.align_pair``: perspective warp,
  common-support crop, boxes shifted by the crop origin), with the ``sensing.warp`` settings of the config
  (``crop``, ``min_box_size``, ``interpolation``, ``antialias``). Without one the pair is a counted skip
  (``size mismatch``) that says how to give one. R-JPEGs are decoded with the ``sensing.radiometry`` settings.
* **Folds.** One fold per group (leave one group out), unless the JSON has ``folds`` (or the config sets
  ``protocol.folds``).
* **Bad input.** The shared COCO checks apply (``adapters.datasets._coco``: ids as the evaluation reads them,
  ``"100"`` is image 100). A malformed JSON, duplicate image, file or category ids, and folds naming unknown groups
  are ``DataError``s naming the file. A pair that cannot be used (missing partner, unreadable file, size mismatch,
  no group, mostly non-finite temperatures) is a counted skip with its reason. An annotation that cannot be used
  (unknown image or category id, malformed box, box outside the image, duplicate id) is a counted skip too, which
  the preparation's plausibility guard then refuses unless accepted (``harness.input_guard``); boxes reaching past
  the edge are clipped and counted in a note.
* **Disk.** An 8-bit pair that is not warped names its two files (``pixel_files``): the compact cache references
  them instead of copying their pixels.
"""

from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from adapters.datasets._coco import box_reading, read_coco
from adapters.datasets._eightbit import (
    BoxStats,
    ImageReadError,
    clip_boxes,
    file_stat,
    read_rgb,
    read_thermal8,
    resolve_root,
    source_parts,
    stat_digest,
    xywh_to_xyxy,
)
from adapters.datasets._paired import SkipPair
from harness.api import DatasetSpec, Fold, PrepareReport
from harness.errors import ConfigError, DataError, HarnessError
from harness.hookspecs import hookimpl
from harness.io import safe_join
from harness.sample import AlignedSample
from harness.sensing.options import SensingOptions
from harness.sensing.pipeline import ir8_from_temperature

log = logging.getLogger(__name__)

DATASET = "coco-rgbt"
ROOT_ENV = "HARNESS_COCO_RGBT_ROOT"
DESCRIPTION = "your own aligned RGB-thermal pairs described by one COCO JSON; set dataset.root"
ANNOTATIONS = "annotations.json"
THERMAL_KINDS = ("radiometric", "8bit")
#: centi-Kelvin, what ``harness sensing decode`` writes: C = value * 0.01 - 273.15
CENTIKELVIN = (0.01, -273.15)
OPTIONS = {
    "root": f"the folder the COCO JSON's paths are relative to (default: ${ROOT_ENV})",
    "annotations": f"the COCO JSON, relative to root (default {ANNOTATIONS})",
    "thermal": "radiometric (temperatures: 16-bit centi-Kelvin, float C, R-JPEG) or 8bit (default radiometric)",
    "thermal_scale": "C = value * scale + offset for integer thermal images (default: sidecar, else 0.01)",
    "thermal_offset": "see thermal_scale (default: sidecar, else -273.15)",
}
#: Bumped when the adapter's output changes for the same input files (part of the cache key).
ADAPTER_VERSION = 1


@dataclass
class PairEntry:
    """One ``images[]`` entry of the JSON and its annotations."""

    image_id: int
    file_name: str
    thermal_file_name: str | None
    group: str
    width: int | None
    height: int | None
    homography: np.ndarray | None
    #: (annotation id, [x, y, w, h], label)
    boxes: list[tuple[Any, list[float], int]] = field(default_factory=list)
    #: per box: ``iscrowd`` set (a crowd region: ignored by the evaluation, never a training instance)
    crowd: list[bool] = field(default_factory=list)


@dataclass
class CocoRgbt:
    """What the JSON says: categories in label order, the pairs, the folds, and the counted problems."""

    path: Path
    categories: tuple[str, ...]
    pairs: list[PairEntry]
    folds: dict[str, tuple[str, ...]] | None
    homographies: dict[str, np.ndarray]
    issues: list[tuple[str, str]]


def _homography(value: Any, where: str) -> np.ndarray:
    """A 3x3 finite, invertible matrix from nested lists; ``DataError`` naming ``where`` otherwise."""
    try:
        H = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: homography must be a 3x3 list of numbers, got {str(value)[:80]}") from None
    if H.shape != (3, 3) or not np.isfinite(H).all():
        raise DataError(f"{where}: homography must be a 3x3 list of finite numbers, got shape {H.shape}")
    if abs(np.linalg.det(H)) < 1e-12:
        raise DataError(f"{where}: homography is singular (determinant 0)")
    return H


def read_coco_rgbt(path: Path) -> CocoRgbt:
    """Parse the COCO JSON of a ``coco-rgbt`` dataset (see the module docstring), through the shared COCO checks
    (``adapters.datasets._coco``: ids, duplicates, unusable annotations).

    Structural problems are ``DataError``s naming the file; single bad entries are returned as ``issues``
    (``(where, reason)``), which the source turns into counted skips.
    """
    checked = read_coco(path, "set dataset.annotations to the COCO JSON's path relative to dataset.root")
    coco, cats = checked.raw, checked.categories
    if not cats:
        raise DataError(f"{path}: 'categories' is empty; list the categories as {{'id': 1, 'name': '...'}}")
    order = sorted(cats)
    label_of = {cid: k for k, cid in enumerate(order)}

    group_h: dict[str, np.ndarray] = {}
    raw_h = coco.get("homographies") or {}
    if not isinstance(raw_h, dict):
        raise DataError(f"{path}: 'homographies' must map group names to 3x3 matrices")
    for g, value in raw_h.items():
        group_h[str(g)] = _homography(value, f"{path}: homographies[{g!r}]")

    pairs: dict[int, PairEntry] = {}
    issues: list[tuple[str, str]] = list(checked.issues)
    for image in checked.images:
        entry, iid, fname = image.entry, image.id, image.file_name
        H = None
        if entry.get("homography") is not None:
            try:
                H = _homography(entry["homography"], f"image {image.original_id!r} ({fname})")
            except DataError as exc:
                issues.append((fname, f"homography malformed: {exc}"))
                continue
        group = entry.get("group")
        pairs[iid] = PairEntry(
            iid,
            fname,
            entry.get("thermal_file_name"),
            str(group) if group not in (None, "") else "",
            image.width,
            image.height,
            H,
        )
    for ann in checked.annotations:
        pair = pairs.get(ann.image_id)
        if pair is not None:  # not an image left out above for its malformed homography
            pair.boxes.append((ann.id, ann.bbox, label_of[ann.category_id]))
            pair.crowd.append(bool(ann.entry.get("iscrowd")))

    folds = None
    if coco.get("folds") is not None:
        raw = coco["folds"]
        if not isinstance(raw, dict) or not raw:
            raise DataError(f"{path}: 'folds' must map fold names to lists of held-out groups, got {str(raw)[:80]}")
        present = {p.group for p in pairs.values() if p.group}
        folds = {}
        for name, held in raw.items():
            held_t = (str(held),) if isinstance(held, str) else tuple(str(g) for g in (held or ()))
            missing = [g for g in held_t if g not in present]
            if not held_t or missing:
                raise DataError(
                    f"{path}: fold {name!r} holds out {', '.join(map(repr, missing)) or 'no group'}; "
                    f"the groups of the images are {', '.join(sorted(present)) or 'none'}"
                )
            folds[str(name)] = held_t
    return CocoRgbt(
        path, tuple(cats[c] for c in order), sorted(pairs.values(), key=lambda p: p.image_id), folds, group_h, issues
    )


# ------------------------------------------------------------------------------------------------ thermal files
def read_temperature(
    path: Path, scale: float | None = None, offset: float | None = None, sensing: SensingOptions | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """Temperature in C (float32 HxW) from a radiometric thermal file, and how it was read.

    Integer images: ``C = value * scale + offset`` with ``scale``/``offset`` when given, else the sidecar's
    unit (``harness.sensing.radiometry.read_sidecar``), else centi-Kelvin. Float images are C. ``.jpg``: a DJI
    R-JPEG, decoded with ``sensing``'s decoder and measurement overrides. Raises ``SkipPair`` with the reason
    for an 8-bit image, an unreadable file, non-finite or implausible values.
    """
    from harness.sensing import plausible
    from harness.sensing.radiometry import (
        UNITS,
        load_thermal_array,
        read_sidecar,
        read_thermal,
        route_meta,
        sidecar_route,
    )

    if path.suffix.lower() in (".jpg", ".jpeg"):
        try:
            opts = sensing or SensingOptions()
            temp, info = read_thermal(path, **opts.thermal_kwargs())
        except ConfigError:
            raise
        except HarnessError as exc:
            raise SkipPair(f"thermal unreadable: {exc}") from None
        return temp, {"unit": info.get("unit"), "format": "rjpeg", **route_meta(info)}
    try:
        arr = load_thermal_array(path)
    except DataError as exc:
        raise SkipPair(f"thermal unreadable: {exc}") from None
    if arr.dtype == np.uint8:
        raise SkipPair(
            f"8-bit thermal: {path.name} holds no temperatures; for 8-bit thermal images set "
            "dataset.thermal=8bit (and use --encoding proxy8 or ir8)"
        )
    nodata = None
    stated = False  # the unit was stated (by a sidecar or the dataset options): a unit mix-up only warns
    if arr.dtype.kind in "iu":
        if scale is not None or offset is not None:
            s, o = (CENTIKELVIN[0] if scale is None else scale), (CENTIKELVIN[1] if offset is None else offset)
            unit, stated = "dataset.thermal_scale/offset", True
        else:
            try:
                side = read_sidecar(path)
            except DataError as exc:
                raise SkipPair(f"thermal unreadable: {exc}") from None
            nodata = side.get("nodata") if side else None  # what `harness sensing decode` writes for a missing pixel
            if side and ("scale" in side or "offset" in side):
                s, o = float(side.get("scale", 1.0)), float(side.get("offset", 0.0))
                unit, stated = str(side.get("unit") or "sidecar"), True
            elif side and side.get("unit") in UNITS:
                (s, o), unit, stated = UNITS[side["unit"]], str(side["unit"]), True
            else:
                (s, o), unit = CENTIKELVIN, "centikelvin"
        temp = (arr.astype(np.float64) * s + o).astype(np.float32)
        if isinstance(nodata, (int, float)) and not isinstance(nodata, bool):
            temp[arr == nodata] = np.nan
    elif arr.dtype.kind == "f":
        temp, unit = arr.astype(np.float32), "celsius"
    else:
        raise SkipPair(f"thermal unreadable: {path.name}: unsupported pixel type {arr.dtype}")
    finite = np.isfinite(temp)
    if not finite.all():  # a few missing pixels stay NaN, left out downstream; mostly missing is a counted skip
        from harness.sensing.c2 import valid_mask

        try:
            valid_mask(temp, path.name)
        except HarnessError as exc:
            raise SkipPair(f"non-finite temperatures: {exc}") from None
        temp = np.where(finite, temp, np.float32(np.nan))
    lo, hi = float(np.nanmin(temp)), float(np.nanmax(temp))
    try:  # garbage and unit mix-ups (Kelvin, Fahrenheit, 8-bit counts): a skip saying what was seen, as every
        # thermal input is checked (harness.sensing.plausible); a few values outside the range become missing
        plausible.check(temp, path.name, f"read as {unit}", declared=stated)
    except DataError as exc:
        fix = (
            "float files are read as degrees C: write them in C"
            if arr.dtype.kind == "f"
            else f"write a sidecar {path.name}.json with its 'unit' or set dataset.thermal_scale and thermal_offset "
            "(C = value * scale + offset)"
        )
        raise SkipPair(f"implausible temperatures: {exc}; {fix}") from None
    try:  # mostly outside the range: a skip
        from harness.sensing.c2 import valid_mask

        valid_mask(temp, path.name)
    except HarnessError:
        raise SkipPair(
            f"implausible temperatures: {path.name} read as {unit} spans {lo:.1f}..{hi:.1f} C; "
            "set dataset.thermal_scale and thermal_offset (C = value * scale + offset)"
        ) from None
    try:  # a file decoded by the approximate or converter route stays labelled
        route = route_meta(sidecar_route(read_sidecar(path)))
    except DataError:
        route = {}
    return temp, {"unit": unit, "format": path.suffix.lower().lstrip("."), **route}


# ------------------------------------------------------------------------------------------------ the source
class CocoRgbtSource:
    """An opened ``coco-rgbt`` dataset (``harness.api.DatasetSource``)."""

    name = DATASET

    def __init__(
        self,
        root: Path,
        annotations: str = ANNOTATIONS,
        thermal: str = "radiometric",
        thermal_scale: float | None = None,
        thermal_offset: float | None = None,
        sensing: SensingOptions | None = None,
    ):
        self.root = root
        self.ann_path = safe_join(root, annotations, "dataset.annotations")
        self.thermal, self.scale, self.offset = thermal, thermal_scale, thermal_offset
        self.sensing = sensing or SensingOptions()
        self.coco = read_coco_rgbt(self.ann_path)
        self.categories = self.coco.categories
        self.issues = list(self.coco.issues)
        self.pairs: list[PairEntry] = []
        for p in self.coco.pairs:
            if not p.group:
                self.issues.append(
                    (
                        p.file_name,
                        f"no group: image {p.image_id} has no 'group' (the unit folds "
                        "hold out); give every images[] entry one",
                    )
                )
                continue
            self.pairs.append(p)
        if self.coco.folds is not None:
            present = {p.group for p in self.pairs}
            for name, held in self.coco.folds.items():
                if not set(held) & present:
                    raise DataError(
                        f"{self.ann_path}: fold {name!r} holds out {', '.join(held)}, which has no usable image"
                    )

    def __len__(self) -> int:
        return len(self.pairs)

    def groups(self) -> list[str]:
        return sorted({p.group for p in self.pairs})

    def folds(self) -> list[Fold]:
        groups = self.groups()
        if self.coco.folds is None:
            return [Fold(g, tuple(x for x in groups if x != g), (g,)) for g in groups]
        return [
            Fold(name, tuple(g for g in groups if g not in held), tuple(g for g in held if g in groups))
            for name, held in self.coco.folds.items()
        ]

    def fingerprint(self) -> str:
        annotations = hashlib.sha1(self.ann_path.read_bytes()).hexdigest()
        parts = source_parts(DATASET, ADAPTER_VERSION, self.root, self.thermal, self.scale, self.offset, annotations)
        for p in self.pairs:
            for rel in (p.file_name, p.thermal_file_name):
                parts.append((rel, self._stat(rel)))
                if rel and self.thermal == "radiometric":  # a sidecar changes the unit
                    parts.append(self._stat(f"{rel}.json"))
        return stat_digest(parts)

    def _stat(self, rel: str | None) -> Any:
        if not rel:
            return None
        try:
            return file_stat(safe_join(self.root, rel, "path"))
        except DataError:
            return "outside"

    def pixel_files(self, sample: AlignedSample) -> tuple[Path, Path] | None:
        """The RGB and thermal files an 8-bit sample's pixels come from, so that the compact cache references them
        instead of copying them (the cache checks that they decode to exactly these pixels); ``None`` for a warped
        pair or radiometric thermal, whose pixels are not a file's."""
        meta = sample.meta if isinstance(sample.meta, dict) else {}
        if self.thermal != "8bit" or "H_rgb_to_frame" in meta:
            return None
        try:
            return (
                safe_join(self.root, str(meta["file_name"]), "file_name"),
                safe_join(self.root, str(meta["thermal_file"]), "thermal_file_name"),
            )
        except (KeyError, DataError):
            return None

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        for where, reason in self.issues:
            report.skip(where, reason)
        stats = BoxStats()
        warped = 0
        self._written: list[tuple[list[float], int, int]] = []  # every box as written, with its frame's size
        instances = 0  # boxes that are objects, not crowd regions
        for p in self.pairs:
            try:
                sample, box_stats = self._sample(p, report)
            except SkipPair as exc:
                log.warning("%s: skipped %s (%s)", DATASET, p.file_name, exc)
                report.skip(p.file_name, str(exc))
                continue
            stats.add(box_stats)
            warped += "H_rgb_to_frame" in sample.meta
            instances += len(sample.boxes) - len(sample.meta.get("crowd") or [])
            yield sample
        problem = box_reading(self._written)
        if problem:
            raise DataError(f"{self.ann_path}: {problem}. Nothing was cached")
        if stats.crowd and not instances:
            raise DataError(
                f"{self.ann_path}: every one of its {stats.crowd} box(es) is a crowd region (iscrowd 1): nothing to "
                "train on or to score (COCO ignores detections on crowd regions). Objects take iscrowd 0. Nothing "
                "was cached"
            )
        if stats.clipped:
            report.note(f"{stats.clipped} box(es) reaching past the image edge were clipped to it")
        if stats.crowd:
            report.note(
                f"{stats.crowd} crowd box(es) (iscrowd 1) kept as crowd regions: the evaluation ignores "
                "detections on them, as COCO does, and training does not use them as instances"
            )
        if warped:
            report.note(
                f"{warped} RGB image(s) of another size were warped into the thermal frame by their "
                "homography" + (" and cropped to the common support" if self.sensing.warp.crop else "")
            )

    def _path(self, rel: Any, what: str, p: PairEntry) -> Path:
        try:
            path = safe_join(self.root, str(rel), f"{self.ann_path.name}: image {p.image_id}")
        except DataError as exc:
            kind = "absolute path" if "is absolute;" in str(exc) else "path outside the dataset root"
            raise SkipPair(f"{kind}: {exc}") from None
        if not path.is_file():
            raise SkipPair(f"missing {what}: {rel} not found under {self.root}")
        return path

    def _sample(self, p: PairEntry, report: PrepareReport) -> tuple[AlignedSample, BoxStats]:
        if not p.thermal_file_name:
            raise SkipPair(f"missing thermal partner: image {p.image_id} has no 'thermal_file_name'")
        rgb_path = self._path(p.file_name, "RGB image", p)
        t_path = self._path(p.thermal_file_name, "thermal partner", p)
        try:
            rgb = read_rgb(rgb_path)
        except ImageReadError as exc:
            raise SkipPair(f"RGB unreadable: {exc}") from None
        info: dict[str, Any]
        if self.thermal == "radiometric":
            temp, info = read_temperature(t_path, self.scale, self.offset, self.sensing)
            thermal: np.ndarray | None = temp
            ir8 = ir8_from_temperature(temp)
        else:
            try:
                ir8, colour = read_thermal8(t_path)
            except ImageReadError as exc:
                raise SkipPair(f"thermal unreadable: {exc}") from None
            thermal, info = None, {"unit": None, "format": "8bit", "colour": colour}
        h, w = ir8.shape
        if p.width is not None and p.height is not None and (p.width, p.height) != (w, h):
            rgb_size = (p.width, p.height) == (rgb.shape[1], rgb.shape[0])
            raise SkipPair(
                f"size mismatch: the JSON says {p.width}x{p.height}"
                + (" (the RGB image's size)" if rgb_size else "")
                + f", the thermal frame {p.thermal_file_name} is {w}x{h}; images[].width and height are the thermal "
                "frame's size (or leave them out)"
            )
        H = p.homography if p.homography is not None else self.coco.homographies.get(p.group)
        if H is None and rgb.shape[:2] != (h, w):
            raise SkipPair(
                f"size mismatch: RGB {p.file_name} is {rgb.shape[1]}x{rgb.shape[0]}, thermal "
                f"{p.thermal_file_name} is {w}x{h}; give the RGB -> thermal homography as "
                f"images[].homography or homographies[{p.group!r}] in the JSON"
            )
        self._written += [(list(b[1]), w, h) for b in p.boxes]
        xywh = np.asarray([b[1] for b in p.boxes], np.float64).reshape(-1, 4)
        labels = np.asarray([b[2] for b in p.boxes], np.int64)
        ids = [b[0] for b in p.boxes]
        boxes, keep, clipped = clip_boxes(xywh_to_xyxy(xywh), w, h)
        for i in np.nonzero(~keep)[0]:
            report.skip(
                f"{self.ann_path.name}#annotation={ids[i]}",
                f"annotation box outside the image: {xywh[i].tolist()} in the {w}x{h} thermal frame",
            )
        crowd = np.asarray(p.crowd, bool).reshape(-1)[keep]
        boxes, labels, ids = boxes[keep], labels[keep], [a for a, k in zip(ids, keep) if k]
        stats = BoxStats(kept=int(keep.sum()), clipped=clipped, degenerate=0)
        from harness.sensing.radiometry import ROUTE_META_KEYS

        meta: dict[str, Any] = {
            "file_name": p.file_name,
            "thermal_file": p.thermal_file_name,
            "ann_ids": ids,
            "thermal_unit": info.get("unit"),
            "thermal_format": info.get("format"),
            **{k: v for k, v in info.items() if k in ROUTE_META_KEYS},
        }
        if H is None:
            _mark_crowd(meta, crowd, stats)
            sample = AlignedSample(
                image_id=p.image_id,
                rgb=rgb,
                thermal=thermal,
                ir8=ir8,
                boxes=boxes,
                labels=labels,
                group=p.group,
                meta=meta,
            )
            return sample, stats
        from harness.sensing.warp import align_pair

        try:
            warp = self.sensing.warp
            pair = align_pair(
                rgb,
                thermal,
                ir8,
                boxes,
                labels,
                H,
                boxes_frame="thermal",
                crop=warp.crop,
                min_box_size=warp.min_box_size,
                interpolation=warp.interpolation,
                antialias=warp.antialias,
            )
        except DataError as exc:
            raise SkipPair(f"registration failed: {exc}") from None
        meta["ann_ids"] = [a for a, k in zip(ids, pair.kept) if k]
        _mark_crowd(meta, crowd[np.asarray(pair.kept, bool)], stats)
        dropped = int((~pair.kept).sum())
        if dropped:
            report.note(f"{p.file_name}: {dropped} box(es) outside the common support of RGB and thermal dropped")
        return pair.to_sample(p.image_id, p.group, meta), stats


def _mark_crowd(meta: dict[str, Any], crowd: np.ndarray, stats: BoxStats) -> None:
    """``meta["crowd"]``: the indices of the sample's crowd boxes (``iscrowd`` 1), when it has any; the prepared
    cache keeps them as crowd regions (``PreparedDataset.targets`` leaves them out, its COCO files mark them)."""
    if crowd.any():
        meta["crowd"] = [int(k) for k in np.flatnonzero(crowd)]
        stats.crowd += int(crowd.sum())


def open_coco_rgbt(
    root: str | Path | None = None,
    annotations: str = ANNOTATIONS,
    thermal: str = "radiometric",
    thermal_scale: float | None = None,
    thermal_offset: float | None = None,
    sensing: Mapping[str, Any] | None = None,
) -> CocoRgbtSource:
    """Open a ``coco-rgbt`` dataset (the options are the ``dataset:`` config keys, see ``OPTIONS``; ``sensing`` is
    the config's ``sensing`` section, which the host passes because this function names it)."""
    if thermal not in THERMAL_KINDS:
        raise ConfigError(
            f"dataset {DATASET!r}: option 'thermal' must be one of {', '.join(THERMAL_KINDS)}, got {thermal!r}"
        )
    for key, value in (("thermal_scale", thermal_scale), ("thermal_offset", thermal_offset)):
        if value is not None and (
            isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
        ):
            raise ConfigError(f"dataset {DATASET!r}: option {key!r} must be a number, got {value!r}")
    if thermal_scale is not None and thermal_scale == 0:
        raise ConfigError(f"dataset {DATASET!r}: option 'thermal_scale' must not be 0")
    if not isinstance(annotations, str) or not annotations:
        raise ConfigError(f"dataset {DATASET!r}: option 'annotations' must be a file name, got {annotations!r}")
    from harness.sensing.warp import _INTERP

    opts = SensingOptions.from_config(sensing)
    if opts.warp.interpolation not in _INTERP:
        raise ConfigError(
            f"sensing.warp.interpolation must be one of {', '.join(_INTERP)}, got {opts.warp.interpolation!r}"
        )
    path = resolve_root(root, ROOT_ENV, DATASET, ())
    return CocoRgbtSource(path, annotations, thermal, thermal_scale, thermal_offset, opts)


#: Radiometric thermal, encoded as C2 unless a run names another encoding, on the default protocol (``DatasetSpec``'s
#: defaults); the categories come from the COCO JSON.
SPEC = DatasetSpec(name=DATASET, open=open_coco_rgbt, categories=(), description=DESCRIPTION, root_env=ROOT_ENV)


@hookimpl
def register_datasets(register: Any) -> None:
    register(SPEC)
