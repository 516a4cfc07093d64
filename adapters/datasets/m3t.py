"""The M3T dataset (DJI Mavic 3 Thermal facade captures, 5 projects, 8 categories), raw or already aligned.

Two forms are read, both described in ``docs/datasets.md``:

* **raw**: ``images/<project>/<stem>_W.JPG`` (wide RGB) with its thermal partner ``<stem>_T.JPG`` (DJI R-JPEG) or
  ``<stem>_T.png|.tif|.npy`` (decoded temperature + sidecar), COCO annotations in the RGB frame, the wide camera's
  calibration, and per inspection group either a homography or landmark pairs. The sensing pipeline undistorts,
  registers, warps RGB into the thermal frame, crops to the common support and carries the boxes along.
* **aligned**: ``aligned/rgb/<project>/<stem>.png`` already in the thermal frame, ``aligned/thermal/<project>/<stem>.*``
  temperature maps, COCO annotations in the thermal frame.

An optional manifest (``m3t.yaml`` at the root, or ``dataset.manifest``) maps a user's own folder and file names
onto this layout; every path it names must stay inside the dataset root. Every bad pair is a counted skip
(``PrepareReport.skip``) and every malformed input file a ``DataError`` naming the file and what to do.

Kept in one module: manifest, annotations, source and raw aligner are the one M3T adapter, and the sensing maths they
call live in ``harness.sensing``.
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import os
import re
from dataclasses import dataclass, field, fields
from datetime import datetime
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from adapters.datasets._paired import SkipPair
from harness.api import DatasetSpec, Fold, PrepareReport
from harness.errors import ConfigError, DataError, HarnessError
from harness.hookspecs import hookimpl
from harness.io import safe_join
from harness.sample import AlignedSample
from harness.sensing.pipeline import ir8_from_temperature

log = logging.getLogger(__name__)

#: The eight M3T categories, in the order used everywhere (label = index, COCO category_id = index + 1):
#: openings and equipment first (visible geometry), then defects from the most to the least visible in RGB.
M3T_CATEGORIES = (
    "window",
    "ac_unit",
    "vent",
    "crack",
    "paint_peeling",
    "efflorescence",
    "delamination",
    "water_seepage",
)
SUPERCATEGORY = {
    "window": "opening",
    "ac_unit": "equipment",
    "vent": "equipment",
    "crack": "defect",
    "paint_peeling": "defect",
    "efflorescence": "defect",
    "delamination": "defect",
    "water_seepage": "defect",
}
#: The seed's project-grouped folds: each held out in turn, trained on the rest.
M3T_FOLDS: dict[str, tuple[str, ...]] = {"P1": ("P1",), "P2": ("P2",), "P3": ("P3",), "P4+P5": ("P4", "P5")}
#: 35-mm-equivalent focal lengths of the M3T's wide (RGB) and thermal cameras: the registration prior's scale.
M3T_FOCAL_35MM = (24.0, 40.0)
ENV_ROOT = "HARNESS_M3T_ROOT"
DESCRIPTION = "DJI M3T facade captures (raw R-JPEG + wide RGB, or already aligned); set dataset.root"
MANIFEST_NAMES = ("m3t.yaml", "m3t.yml", "m3t.json")
#: Bumped when the adapter's output changes for the same input files (part of the cache key).
ADAPTER_VERSION = 1
THERMAL_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".npy")
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
_DJI_TIME = re.compile(r"DJI_(\d{14})_")


# ------------------------------------------------------------------------------------------------ manifest
@dataclass(frozen=True)
class Manifest:
    """Where the files of an M3T-layout dataset are. Paths are relative to ``root`` and may not leave it."""

    root: Path
    format: str = "raw"  # raw | aligned
    images: str = "images"  # raw: folder of <project>/ capture folders
    rgb: str = "aligned/rgb"  # aligned: RGB in the thermal frame, <project>/<stem>.<ext>
    thermal: str = "aligned/thermal"  # aligned: temperature maps, <project>/<stem>.<ext>
    annotations: str | None = None  # default: annotations/instances_rgb.json (raw), instances_thermal.json (aligned)
    projects: Mapping[str, str] = field(default_factory=dict)  # project id -> folder name
    rgb_suffix: str = "_W"
    thermal_suffix: str = "_T"
    thermal_size: tuple[int, int] | None = None  # (width, height); None: the most common size
    rgb_camera: str | None = "calibration/wide_camera.yaml"
    thermal_camera: str | None = "calibration/thermal_camera.yaml"
    homographies: str | None = "registration/homographies.yaml"
    landmarks: str | None = "registration/landmarks.json"
    captures: str | None = "captures.csv"
    landmarks_rgb: str = "undistorted"  # frame of the landmarks' RGB points: undistorted (camera K) | raw
    categories: Mapping[str, str] = field(default_factory=dict)  # name in the annotation file -> ours or "ignore"
    source: str | None = None  # the manifest file, for messages

    PATH_KEYS = (
        "images",
        "rgb",
        "thermal",
        "annotations",
        "rgb_camera",
        "thermal_camera",
        "homographies",
        "landmarks",
        "captures",
    )

    def path(self, key: str, value: str | None = None) -> Path:
        """The absolute path of manifest entry ``key`` (or of ``value`` under it), refused if it leaves the root."""
        rel = getattr(self, key) if value is None else value
        return safe_join(self.root, rel, f"manifest key {key!r}" + (f" of {self.source}" if self.source else ""))

    def optional(self, key: str) -> Path | None:
        """Path of an optional file: ``None`` when the key is unset or the default file does not exist."""
        if getattr(self, key) is None:
            return None
        p = self.path(key)
        return p if p.exists() else None

    @property
    def annotations_path(self) -> Path:
        rel = self.annotations or (
            "annotations/instances_rgb.json" if self.format == "raw" else "annotations/instances_thermal.json"
        )
        return safe_join(self.root, rel, "manifest key 'annotations'")


def _manifest_fields() -> dict[str, Any]:
    return {f.name: f for f in fields(Manifest) if f.name not in ("root", "source")}


def load_manifest(
    root: str | Path, manifest: str | Path | None = None, overrides: Mapping[str, Any] | None = None
) -> Manifest:
    """Read the manifest (``manifest``, else ``m3t.yaml``/``m3t.json`` at ``root``, else defaults) and apply
    ``overrides`` (the ``dataset`` config section). Unknown keys and wrong types are ``DataError``s."""
    root = Path(os.path.abspath(root))  # every path below is compared against the absolute root
    data: dict[str, Any] = {}
    source: Path | None = None
    if manifest is not None:
        source = Path(manifest) if Path(manifest).is_absolute() else root / manifest
        if not source.exists():
            raise DataError(f"{source}: manifest not found (dataset.manifest)")
    else:
        source = next((root / n for n in MANIFEST_NAMES if (root / n).exists()), None)
    if source is not None:
        data = _read_manifest_file(source)
    known = _manifest_fields()
    bad_options = sorted(set(overrides or {}) - set(known))
    if bad_options:
        from harness.errors import ConfigError

        raise ConfigError(
            f"the M3T dataset does not take option(s) {', '.join(map(repr, bad_options))} "
            f"(dataset.<option>); it takes root, manifest and the manifest keys "
            f"{', '.join(sorted(known))}"
        )
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise DataError(
            f"{source or 'dataset options'}: unknown manifest key(s) {', '.join(map(repr, unknown))}; "
            f"known keys: {', '.join(sorted(known))}"
        )
    kwargs: dict[str, Any] = {}
    where = str(source or "dataset options")
    for key, value in data.items():
        kwargs[key] = _check_manifest_value(key, value, where)
    if "format" not in kwargs:
        kwargs["format"] = "aligned" if not (root / "images").exists() and (root / "aligned").exists() else "raw"
    m = Manifest(root=root, source=str(source) if source else None, **kwargs)
    for key in Manifest.PATH_KEYS:  # refuse escaping paths up front, whatever the form
        if getattr(m, key) is not None:
            m.path(key)
    _ = m.annotations_path
    key = "images" if m.format == "raw" else "rgb"
    for folder in m.projects.values():
        m.path(key, f"{getattr(m, key)}/{folder}")
    return m


def _read_manifest_file(path: Path) -> dict[str, Any]:
    if path.suffix.lower() == ".json":
        from harness.io import read_json

        data = read_json(path)
    else:
        from harness.config import read_yaml
        from harness.errors import ConfigError

        try:
            data = read_yaml(path)
        except ConfigError as exc:
            raise DataError(str(exc)) from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: a manifest is a mapping of keys to values, got {type(data).__name__}")
    return data


def _check_manifest_value(key: str, value: Any, where: str) -> Any:
    def bad(expected: str) -> DataError:
        return DataError(f"{where}: manifest key {key!r} expects {expected}, got {value!r}")

    if key == "format":
        if value not in ("raw", "aligned"):
            raise bad("'raw' or 'aligned'")
        return value
    if key in ("projects", "categories"):
        if not isinstance(value, Mapping) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in value.items()
        ):
            raise bad("a mapping of names to names")
        if key == "categories":
            for v in value.values():
                if v not in M3T_CATEGORIES and v != "ignore":
                    raise DataError(
                        f"{where}: manifest 'categories' maps to {v!r}, which is neither one of "
                        f"{', '.join(M3T_CATEGORIES)} nor 'ignore'"
                    )
        return dict(value)
    if key == "thermal_size":
        if value is None:
            return None
        if (
            not isinstance(value, (list, tuple))
            or len(value) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
        ):
            raise bad("[width, height] in pixels")
        return (int(value[0]), int(value[1]))
    if key == "landmarks_rgb":
        if value not in ("undistorted", "raw"):
            raise bad("'undistorted' (pixels of the undistorted wide image, camera K) or 'raw' (of the JPEG as shot)")
        return value
    if key in ("rgb_suffix", "thermal_suffix"):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if value is not None and not isinstance(value, str):
        raise bad("a path relative to the dataset root")
    return value


# ------------------------------------------------------------------------------------------------ annotations
@dataclass
class ImageRecord:
    """One image of the annotation file, with everything needed to find and align its pair."""

    image_id: int
    file_name: str  # as written in the annotation file, relative to the images (raw) or rgb (aligned) folder
    width: int | None
    height: int | None
    project: str = ""
    captured: datetime | None = None
    group: str = ""
    thermal_file: str | None = None
    boxes: list[tuple[int, list[float], int]] = field(default_factory=list)  # (ann id, xywh, label)


@dataclass
class Annotations:
    images: list[ImageRecord]
    issues: list[tuple[str, str]]  # (where, reason): counted skips found while reading
    ignored: int = 0  # annotations of categories mapped to "ignore"


def read_coco_annotations(
    path: Path, category_map: Mapping[str, str] | None = None, categories: Sequence[str] = M3T_CATEGORIES
) -> Annotations:
    """Parse a COCO detection file into image records with labels in ``categories`` order.

    The shared COCO checks apply (``adapters.datasets._coco``): a missing, empty or invalid file, a file without
    ``images``, a malformed or duplicate image id and a file listed twice are ``DataError``s; so is a category name
    that is neither known nor mapped in the manifest. A single bad annotation (unknown image or category id,
    malformed box, duplicate id) is returned as an issue (a counted skip, stopped by the plausibility guard).
    """
    from adapters.datasets._coco import read_coco

    checked = read_coco(path, "put the COCO file there or name it with the manifest key 'annotations'")
    cmap = dict(category_map or {})
    label_of: dict[int, int | None] = {}
    unknown: list[str] = []
    for cid, name in checked.categories.items():
        target = cmap.get(name, name)
        if target == "ignore":
            label_of[cid] = None
        elif target in categories:
            label_of[cid] = categories.index(target)
        else:
            unknown.append(name)
    if unknown:
        raise DataError(
            f"{path}: unknown category name(s) {', '.join(map(repr, unknown))}; the M3T categories are "
            f"{', '.join(categories)}. Map each to one of them (or to 'ignore') with the manifest key "
            f"'categories', e.g. categories: {{{unknown[0]!r}: crack}}"
        )

    images: dict[int, ImageRecord] = {}
    for im in checked.images:
        images[im.id] = ImageRecord(
            im.id,
            im.file_name,
            im.width,
            im.height,
            project=str(im.entry.get("project", "")),
            captured=parse_time(im.entry.get("date_captured")),
            thermal_file=im.entry.get("thermal_file_name"),
        )
    ignored = 0
    for ann in checked.annotations:
        label = label_of[ann.category_id]
        if label is None:
            ignored += 1
            continue
        images[ann.image_id].boxes.append((ann.id, ann.bbox, label))
    issues = list(checked.issues)
    return Annotations(sorted(images.values(), key=lambda r: r.file_name), issues, ignored)


def parse_time(value: Any) -> datetime | None:
    """A capture time from ISO (``2024-05-12 10:30:15``) or EXIF (``2024:05:12 10:30:15``) text."""
    if isinstance(value, datetime):
        return value
    if not isinstance(value, str) or not value.strip():
        return None
    text = value.strip()
    for fmt in (
        "%Y-%m-%d %H:%M:%S",
        "%Y-%m-%dT%H:%M:%S",
        "%Y:%m:%d %H:%M:%S",
        "%Y-%m-%d %H:%M:%S.%f",
        "%Y-%m-%dT%H:%M:%S.%f",
    ):
        try:
            return datetime.strptime(text, fmt)
        except ValueError:
            continue
    return None


def time_from_name(name: str) -> datetime | None:
    """DJI file names carry the capture time: ``DJI_20240512103015_0001_W.JPG``."""
    m = _DJI_TIME.search(name)
    if not m:
        return None
    try:
        return datetime.strptime(m.group(1), "%Y%m%d%H%M%S")
    except ValueError:
        return None


def _exif_time(path: Path) -> datetime | None:
    """EXIF ``DateTimeOriginal`` of a JPEG (None when it has none or cannot be read)."""
    if path.suffix.lower() not in (".jpg", ".jpeg"):
        return None
    from harness.sensing.registration import capture_time

    try:
        return capture_time(path)
    except HarnessError:
        return None


def clip_box_xywh(box: Sequence[float], width: int, height: int) -> tuple[list[float] | None, bool]:
    """``[x, y, w, h]`` -> clipped ``[x0, y0, x1, y1]`` inside ``[0, W] x [0, H]`` (None when nothing is left) and
    whether clipping changed it."""
    x0, y0, w, h = box
    x1, y1 = x0 + w, y0 + h
    c = [min(max(x0, 0.0), width), min(max(y0, 0.0), height), min(max(x1, 0.0), width), min(max(y1, 0.0), height)]
    if c[2] - c[0] <= 0 or c[3] - c[1] <= 0:
        return None, True
    return c, c != [x0, y0, x1, y1]


# ------------------------------------------------------------------------------------------------ the source
def _file_signature(paths: Sequence[Path], root: Path) -> str:
    h = hashlib.sha1()
    for p in paths:
        try:
            st = p.stat()
        except OSError:
            h.update(f"{p.relative_to(root)}:missing\n".encode())
            continue
        h.update(f"{p.relative_to(root)}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def _content_hash(path: Path | None) -> str:
    if path is None or not path.exists():
        return "-"
    return hashlib.sha1(path.read_bytes()).hexdigest()


class M3TSource:
    """An opened M3T-layout dataset (``harness.api.DatasetSource``)."""

    def __init__(
        self,
        manifest: Manifest,
        name: str = "m3t",
        sensing: Mapping[str, Any] | None = None,
        categories: Sequence[str] = M3T_CATEGORIES,
    ):
        self.manifest = manifest
        self.root = manifest.root
        self.name = name
        self.categories = tuple(categories)
        self.sensing = dict(sensing or {})
        self._clipped = 0
        #: what registration used per inspection group, filled while ``samples`` runs
        self.registration: dict[str, Any] = {}
        m = manifest
        base = m.path("images") if m.format == "raw" else m.path("rgb")
        if not base.is_dir():
            raise DataError(
                f"{base}: folder not found; a {m.format} M3T dataset keeps its "
                f"{'captures' if m.format == 'raw' else 'aligned RGB'} there (manifest key "
                f"{'images' if m.format == 'raw' else 'rgb'!r})"
            )
        self.base = base
        ann = read_coco_annotations(m.annotations_path, m.categories, self.categories)
        self.issues = list(ann.issues)
        self.ignored = ann.ignored
        folder_to_project = {v: k for k, v in m.projects.items()}
        self.records: list[ImageRecord] = []
        captures = self._read_captures()
        for rec in ann.images:
            try:
                safe_join(base, rec.file_name, f"{m.annotations_path.name}: image {rec.image_id}")
            except DataError as exc:
                self.issues.append((rec.file_name, f"path outside the dataset root: {exc}"))
                continue
            folder = Path(rec.file_name).parts[0] if len(Path(rec.file_name).parts) > 1 else ""
            if not rec.project:
                if m.projects:
                    if folder not in folder_to_project:
                        self.issues.append(
                            (
                                rec.file_name,
                                f"project folder not in the manifest: {folder!r} "
                                f"(known: {', '.join(sorted(folder_to_project))})",
                            )
                        )
                        continue
                    rec.project = folder_to_project[folder]
                else:
                    rec.project = folder or "all"
            cap = captures.get(rec.file_name) or captures.get(Path(rec.file_name).name)
            if cap:
                rec.captured = cap.get("time") or rec.captured
                rec.group = cap.get("group") or ""
            if rec.captured is None:
                rec.captured = time_from_name(Path(rec.file_name).name) or _exif_time(base / rec.file_name)
            self.records.append(rec)
        self._assign_groups()
        self.records.sort(key=lambda r: (r.project, r.captured or datetime.min, r.file_name))

    # -------------------------------------------------------------- index
    def _read_captures(self) -> dict[str, dict[str, Any]]:
        path = self.manifest.optional("captures")
        if path is None:
            return {}
        out: dict[str, dict[str, Any]] = {}
        try:
            with path.open(newline="", encoding="utf-8") as f:
                reader = csv.DictReader(f)
                if reader.fieldnames is None or "file" not in reader.fieldnames:
                    raise DataError(
                        f"{path}: a captures file is CSV with a 'file' column and 'time' and/or 'group' "
                        f"columns; found columns {reader.fieldnames}"
                    )
                for row in reader:
                    out[row["file"]] = {"time": parse_time(row.get("time")), "group": (row.get("group") or "").strip()}
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise DataError(f"{path}: cannot read the captures file ({exc})") from None
        return out

    def _assign_groups(self) -> None:
        """Inspection groups: an explicit group from the captures file, else a new group whenever consecutive
        captures of a project are more than ``sensing.groups.gap_s`` apart, named ``<project>-01``,
        ``<project>-02`` ... in time order (``harness.sensing.registration.group_by_capture_time``); a project
        without capture times is one group named after the project."""
        from harness.sensing.options import SensingOptions
        from harness.sensing.registration import group_by_capture_time

        gap_s = SensingOptions.from_config(self.sensing).group_gap_s

        by_project: dict[str, list[ImageRecord]] = {}
        for r in self.records:
            if not r.group:
                by_project.setdefault(r.project, []).append(r)
        for project, recs in by_project.items():
            timed = {r.file_name: r.captured for r in recs if r.captured is not None}
            groups = group_by_capture_time(timed, gap_s=gap_s, prefix=f"{project}-") if timed else {}
            for r in recs:
                r.group = groups.get(r.file_name, project)

    # -------------------------------------------------------------- DatasetSource
    def __len__(self) -> int:
        return len(self.records)

    def groups(self) -> list[str]:
        return sorted({r.project for r in self.records})

    def inspection_groups(self) -> list[str]:
        return sorted({r.group for r in self.records})

    def folds(self) -> list[Fold]:
        present = set(self.groups())
        out = []
        for name, held in M3T_FOLDS.items():
            val = tuple(g for g in held if g in present)
            if not val:
                continue
            out.append(Fold(name, tuple(sorted(present - set(val))), val))
        if not out and present:  # a dataset with other project names: leave-one-project-out
            out = [Fold(g, tuple(sorted(present - {g})), (g,)) for g in sorted(present)]
        return out

    def fingerprint(self) -> str:
        m = self.manifest
        files = sorted(p for p in self.base.rglob("*") if p.is_file())
        if m.format == "aligned":
            tdir = m.path("thermal")
            if tdir.is_dir():
                files += sorted(p for p in tdir.rglob("*") if p.is_file())
        h = hashlib.sha1()
        manifest_view = {
            k: (sorted(v.items()) if isinstance(v, Mapping) else v)
            for k, v in vars(m).items()
            if k not in ("root", "source")
        }
        h.update(
            json.dumps(
                {"adapter": ADAPTER_VERSION, "name": self.name, "manifest": manifest_view}, sort_keys=True, default=str
            ).encode()
        )
        h.update(_content_hash(m.annotations_path).encode())
        for key in ("rgb_camera", "thermal_camera", "homographies", "landmarks", "captures"):
            h.update(_content_hash(m.optional(key)).encode())
        h.update(_file_signature(files, self.root).encode())
        return h.hexdigest()

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        for where, reason in self.issues:
            report.skip(where, reason)
        if self.ignored:
            report.note(f"{self.ignored} annotation(s) of categories mapped to 'ignore' left out")
        if self.manifest.format == "raw":
            yield from self._raw_samples(report)
        else:
            yield from self._aligned_samples(report)

    # -------------------------------------------------------------- common steps
    def _read_rgb(self, path: Path) -> np.ndarray:
        import cv2

        if not path.exists():
            raise SkipPair("missing RGB file")
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise SkipPair("RGB unreadable: not a decodable image")
        return np.ascontiguousarray(img[:, :, ::-1])

    def _read_thermal(self, path: Path) -> tuple[np.ndarray, dict[str, Any]]:
        from harness.sensing.options import SensingOptions
        from harness.sensing.radiometry import read_thermal

        opts = SensingOptions.from_config(self.sensing)
        try:
            temp, info = read_thermal(path, **opts.thermal_kwargs())
        except ConfigError:
            raise  # a wrong sensing.radiometry setting is not a property of one file
        except HarnessError as exc:
            if "NaN" in str(exc) or "infinite" in str(exc):
                raise SkipPair(f"non-finite temperatures: {exc}") from None
            raise SkipPair(f"thermal unreadable: {exc}") from None
        return temp, info  # a few missing pixels stay NaN (read_thermal refuses a map of mostly missing ones)

    def _expected_thermal_size(self) -> tuple[int, int] | None:
        return self.manifest.thermal_size

    def _boxes_in(
        self, rec: ImageRecord, width: int, height: int, report: PrepareReport
    ) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """The record's boxes clipped to its image; boxes entirely outside are counted skips."""
        boxes, labels, ids = [], [], []
        clipped = 0
        for ann_id, xywh, label in rec.boxes:
            box, changed = clip_box_xywh(xywh, width, height)
            if box is None:
                report.skip(
                    f"{rec.file_name}#annotation={ann_id}",
                    f"annotation box outside the image: {xywh} in a {width}x{height} image",
                )
                continue
            clipped += changed
            boxes.append(box)
            labels.append(label)
            ids.append(ann_id)
        self._clipped += clipped
        return (np.asarray(boxes, np.float32).reshape(-1, 4), np.asarray(labels, np.int64), ids)

    # -------------------------------------------------------------- aligned form
    def _aligned_samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        from harness.sensing.radiometry import route_meta

        tdir = self.manifest.path("thermal")
        for rec in self.records:
            try:
                rgb = self._read_rgb(self.base / rec.file_name)
                tpath = self._aligned_thermal(tdir, rec)
                temp, info = self._read_thermal(tpath)
                h, w = temp.shape
                want = self._expected_thermal_size()
                if want is not None and (w, h) != want:
                    raise SkipPair(f"thermal size mismatch: {w}x{h}, expected {want[0]}x{want[1]}")
                if rgb.shape[:2] != (h, w):
                    raise SkipPair(f"RGB size mismatch: {rgb.shape[1]}x{rgb.shape[0]}, the thermal frame is {w}x{h}")
                if rec.width is not None and (rec.width, rec.height) != (w, h):
                    raise SkipPair(
                        f"image size mismatch: the annotation file says {rec.width}x{rec.height}, "
                        f"the images are {w}x{h}"
                    )
                boxes, labels, ids = self._boxes_in(rec, w, h, report)
            except SkipPair as exc:
                report.skip(rec.file_name, str(exc))
                continue
            yield AlignedSample(
                image_id=rec.image_id,
                rgb=rgb,
                thermal=temp,
                ir8=ir8_from_temperature(temp),
                boxes=boxes,
                labels=labels,
                group=rec.project,
                meta={
                    "file_name": rec.file_name,
                    "thermal_file": str(tpath.relative_to(self.root)),
                    "project": rec.project,
                    "captured": rec.captured.isoformat(sep=" ") if rec.captured else None,
                    "ann_ids": ids,
                    "origin": [0, 0],
                    "thermal_unit": info.get("unit"),
                    **route_meta(info),
                },
            )
        if self._clipped:
            report.note(f"{self._clipped} box(es) reaching past the image edge were clipped to it")

    def _aligned_thermal(self, tdir: Path, rec: ImageRecord) -> Path:
        if rec.thermal_file:
            return safe_join(tdir, rec.thermal_file, f"thermal_file_name of image {rec.image_id}")
        stem = Path(rec.file_name).with_suffix("")
        found = _find_partner(tdir / stem.parent, stem.name)
        if found is None:
            raise SkipPair("missing thermal partner: no " + f"{stem}.* in {tdir}")
        return found

    # -------------------------------------------------------------- raw form
    def _raw_samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        aligner = RawAligner(self)
        self._aligner = aligner
        for rec in self.records:
            try:
                sample = aligner.sample(rec, report)
            except SkipPair as exc:
                report.skip(rec.file_name, str(exc))
                continue
            yield sample
        aligner.finish(report)
        if self._clipped:
            report.note(f"{self._clipped} RGB-frame box(es) reaching past the image edge were clipped to it")

    def write_artifacts(self, folder: Path) -> None:
        """Called by ``harness.prepare`` before the prepared folder is published: the homographies the raw form
        used (one per inspection group, full-frame undistorted RGB -> thermal), for registration studies."""
        aligner = getattr(self, "_aligner", None)
        if aligner is not None:
            aligner.registration.save(Path(folder) / "homographies.yaml", self.name)

    def raw_captures(self, groups: Sequence[str]) -> list[tuple[int, str, Path, Path]]:
        """``(image id, capture name, wide file, thermal file)`` of the raw captures of the projects ``groups``, as
        ``harness screen`` would find them in the images folder (the capture name is the wide file's path under it
        without the suffix and extension); captures without a thermal partner are left out."""
        if self.manifest.format != "raw":
            raise DataError(f"{self.root}: an aligned M3T dataset holds no raw captures")
        out = []
        for rec in self.records:
            if rec.project not in groups:
                continue
            try:
                thermal = self.thermal_partner(rec)
            except SkipPair:
                continue
            rel = Path(rec.file_name)
            stem = rel.stem
            if self.manifest.rgb_suffix and stem.endswith(self.manifest.rgb_suffix):
                stem = stem[: -len(self.manifest.rgb_suffix)]
            out.append((rec.image_id, (rel.parent / stem).as_posix(), self.base / rec.file_name, thermal))
        return out

    def thermal_partner(self, rec: ImageRecord) -> Path:
        m = self.manifest
        if rec.thermal_file:
            return safe_join(self.base, rec.thermal_file, f"thermal_file_name of image {rec.image_id}")
        rel = Path(rec.file_name)
        stem = rel.stem
        if m.rgb_suffix and stem.endswith(m.rgb_suffix):
            stem = stem[: -len(m.rgb_suffix)]
        found = _find_partner(self.base / rel.parent, stem + m.thermal_suffix)
        if found is None:
            raise SkipPair(f"missing thermal partner: no {rel.parent / (stem + m.thermal_suffix)}.* next to the RGB")
        return found


def _find_partner(folder: Path, stem: str) -> Path | None:
    """A file named ``stem`` with a thermal extension in ``folder`` (extension case-insensitive)."""
    try:
        names = os.listdir(folder)
    except OSError:
        return None
    want = stem.lower()
    for ext in THERMAL_EXTENSIONS:
        for n in names:
            if n.lower() == want + ext:
                return folder / n
    return None


def _check_missing(temp: np.ndarray, path: Path) -> None:
    """A map may miss a few temperatures (they stay NaN and are left out downstream); one of mostly missing ones, or
    none measured, is a counted skip naming the file."""
    if not np.isfinite(temp).all():
        from harness.sensing.c2 import valid_mask

        try:
            valid_mask(temp, path.name)
        except HarnessError as exc:
            raise SkipPair(f"non-finite temperatures: {exc}") from None


# ------------------------------------------------------------------------------------------------ raw alignment
class RawAligner:
    """The sensing pipeline for one raw M3T dataset, through ``harness.sensing.pipeline.SensingContext``.

    The context undistorts both sensors and runs ``align_pair``; this class reads the pair's files and adds what the
    dataset brings: its calibration files (manifest ``rgb_camera``/``thermal_camera``, used when the
    ``sensing.undistort`` section names none) and its registration files (manifest ``homographies`` and
    ``landmarks``), whose per-group policy is ``harness.sensing.registration.dataset.DatasetRegistration``.
    """

    def __init__(self, source: M3TSource):
        from harness.sensing.calibration import CameraModel
        from harness.sensing.pipeline import SensingContext
        from harness.sensing.registration.dataset import DatasetRegistration

        self.src = source
        m = source.manifest
        self.ctx = SensingContext.from_config(source.sensing)
        self.opts = self.ctx.options
        if self.ctx.rgb_camera is None and m.optional("rgb_camera") is not None:
            self.ctx.rgb_camera = CameraModel.load(m.optional("rgb_camera"))  # type: ignore[arg-type]
        if self.ctx.thermal_camera is None and m.optional("thermal_camera") is not None:
            self.ctx.thermal_camera = CameraModel.load(m.optional("thermal_camera"))  # type: ignore[arg-type]
        self.registration = DatasetRegistration(
            self.ctx,
            m.optional("homographies"),
            m.optional("landmarks"),
            m.landmarks_rgb,
            {r.file_name: r.group for r in source.records},
            M3T_FOCAL_35MM,
        )
        self.thermal_size: tuple[int, int] | None = m.thermal_size
        self.dropped = 0

    def read_thermal(self, path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """(temperature C, 8-bit preview, info). R-JPEGs give their own palette picture as the preview."""
        from harness.sensing.options import SensingOptions
        from harness.sensing.pipeline import read_capture_thermal

        if path.suffix.lower() in (".jpg", ".jpeg"):  # the reading `harness screen` shares
            try:
                return read_capture_thermal(path, SensingOptions.from_config(self.src.sensing))
            except ConfigError:
                raise  # a wrong sensing.radiometry setting is not a property of one file
            except HarnessError as exc:
                raise SkipPair(f"thermal unreadable: {exc}") from None
        temp, info = self.src._read_thermal(path)
        return temp, ir8_from_temperature(temp), info

    # ---------------------------------------------------------------- one pair
    def sample(self, rec: ImageRecord, report: PrepareReport) -> AlignedSample:
        from harness.sensing.radiometry import route_meta

        src = self.src
        tpath = src.thermal_partner(rec)
        rgb = src._read_rgb(src.base / rec.file_name)
        temp, ir8, info = self.read_thermal(tpath)
        _check_missing(temp, tpath)
        th, tw = temp.shape
        if self.thermal_size is None:
            self.thermal_size = (tw, th)
            report.note(
                f"thermal frame size {tw}x{th} taken from the first pair (set thermal_size in the manifest to fix it)"
            )
        if (tw, th) != self.thermal_size:
            raise SkipPair(f"thermal size mismatch: {tw}x{th}, expected {self.thermal_size[0]}x{self.thermal_size[1]}")
        rh, rw = rgb.shape[:2]
        if rec.width is not None and rec.height is not None and (rec.width, rec.height) != (rw, rh):
            raise SkipPair(
                f"RGB size mismatch: the annotation file says {rec.width}x{rec.height}, the image is {rw}x{rh}"
            )
        cam = self.ctx.rgb_camera
        if cam is not None and cam.image_size != (rw, rh):
            raise SkipPair(
                f"RGB size mismatch: the camera calibration is for {cam.image_size[0]}x{cam.image_size[1]}, "
                f"the image is {rw}x{rh}"
            )
        boxes, labels, ids = src._boxes_in(rec, rw, rh, report)
        self.registration.register_group(rec.group)
        prior = self.registration.prior((rw, rh), (tw, th))
        try:
            pair = self.ctx.align_capture(rgb, temp, ir8, boxes, labels, rec.group, boxes_frame="rgb", prior=prior)
        except HarnessError as exc:
            raise SkipPair(
                f"registration failed: {exc}"
                if "registration" in str(exc) or "homography" in str(exc)
                else f"alignment failed: {exc}"
            ) from None
        self.dropped += pair.dropped
        kept_ids = [i for i, k in zip(ids, pair.kept) if k]
        return pair.to_sample(
            rec.image_id,
            rec.project,
            {
                "file_name": rec.file_name,
                "thermal_file": str(tpath.relative_to(src.root)),
                "project": rec.project,
                "inspection_group": rec.group,
                "captured": rec.captured.isoformat(sep=" ") if rec.captured else None,
                "ann_ids": kept_ids,
                "thermal_format": info.get("format"),
                **route_meta(info),
            },
        )

    def finish(self, report: PrepareReport) -> None:
        if self.dropped:
            report.note(
                f"{self.dropped} RGB-frame box(es) fell outside the thermal frame (or below "
                f"{self.opts.warp.min_box_size} px) after registration and were left out"
            )
        self.src.registration.update({g: self.registration.how(g) for g in sorted(self.ctx.entries)})
        for line in self.registration.notes():
            report.note(line)


# ------------------------------------------------------------------------------------------------ opening
def open_m3t(
    root: str | Path | None = None,
    manifest: str | Path | None = None,
    sensing: Mapping[str, Any] | None = None,
    name: str = "m3t",
    **overrides: Any,
) -> M3TSource:
    """Open an M3T-layout dataset at ``root`` (or ``$HARNESS_M3T_ROOT``). ``overrides`` are manifest keys."""
    if root is None:
        root = os.environ.get(ENV_ROOT)
    if not root:
        raise DataError(
            f"dataset {name!r}: no data folder. Set dataset.root (--set dataset.root=/path/to/M3T) or "
            f"the environment variable {ENV_ROOT}; the layout is described in docs/datasets.md. "
            "To try the harness without the release, use --dataset m3t-synth."
        )
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"dataset {name!r}: {root} is not a folder (dataset.root / {ENV_ROOT})")
    m = load_manifest(root, manifest, overrides)
    return M3TSource(m, name=name, sensing=sensing)


def m3t_spec(name: str, open: Callable[..., Any], description: str, root_env: str | None = None) -> DatasetSpec:
    """The spec of a dataset this adapter reads (the release, the synthetic set): the M3T categories, radiometric
    thermal encoded as C2 unless a run names another encoding (``DatasetSpec``'s defaults), the 4-fold protocol and
    a sensing stage."""
    return DatasetSpec(
        name, open, M3T_CATEGORIES, description, protocol="m3t-4fold", root_env=root_env, sensing_stage=True
    )


@hookimpl
def register_datasets(register: Any) -> None:
    register(m3t_spec("m3t", open_m3t, DESCRIPTION, ENV_ROOT))
