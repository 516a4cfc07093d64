"""The ``example-folders`` dataset: aligned RGB + temperature pairs kept in one folder per site.

Layout (``dataset.root``)::

    <site>/<stem>.rgb.png        RGB, already in the thermal frame (same width and height as the thermal map)
    <site>/<stem>.thermal.npy    float32 temperature in degrees C, H x W
    <site>/<stem>.boxes.csv      one box per line: category,x1,y1,x2,y2 (thermal-frame pixels); may be empty

The site folder is the group: the folds leave one site out. ``harness example-data DIR`` writes a small folder of
this layout to try the plugin with.
"""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from harness import AlignedSample, DatasetSpec, Fold, hookimpl
from harness.api import PrepareReport
from harness.errors import ConfigError, DataError

NAME = "example-folders"
CATEGORIES = ("hot_spot", "window")
ROOT_ENV = "EXAMPLE_FOLDERS_ROOT"
#: Bumped when this plugin's samples change for the same files: part of the fingerprint, so caches are redone.
VERSION = 1


class ExampleFoldersSource:
    """An opened ``example-folders`` dataset: the ``harness.api.DatasetSource`` contract, method by method."""

    name = NAME
    categories = CATEGORIES  # label k is CATEGORIES[k]; COCO category_id k + 1

    def __init__(self, root: Path, min_box: float = 1.0):
        self.root, self.min_box = root, min_box
        # one entry per RGB image, in a stable order (the sample order must not depend on the file system)
        self.stems = sorted(p.with_name(p.name[: -len(".rgb.png")]) for p in root.glob("*/*.rgb.png"))
        if not self.stems:
            raise DataError(f"dataset {NAME!r}: no <site>/<stem>.rgb.png under {root}")

    def __len__(self) -> int:  # optional: gives `harness prepare` a progress bar with a total
        return len(self.stems)

    def groups(self) -> list[str]:
        return sorted({s.parent.name for s in self.stems})

    def folds(self) -> list[Fold]:
        sites = self.groups()
        return [Fold(site, tuple(s for s in sites if s != site), (site,)) for site in sites]

    def fingerprint(self) -> str:
        """Changes when a file is added, removed, rewritten, or an option changes: the cache key of `prepare`."""
        h = hashlib.sha1(f"{NAME} {VERSION} {self.root.resolve()} {self.min_box}".encode())
        for p in sorted(self.root.glob("*/*.*")):
            st = p.stat()
            h.update(f"{p.relative_to(self.root)} {st.st_size} {st.st_mtime_ns}\n".encode())
        return h.hexdigest()

    def samples(self, report: PrepareReport) -> Iterator[AlignedSample]:
        for image_id, stem in enumerate(self.stems, start=1):
            name = f"{stem.parent.name}/{stem.name}"
            try:
                rgb, temp, boxes, labels = self._read(stem)
            except _Skip as exc:  # a bad pair is a counted skip with its reason, never an exception
                report.skip(name, str(exc))
                continue
            yield AlignedSample(
                image_id=image_id,  # unique within the dataset, an int
                rgb=rgb,  # uint8 H x W x 3, R G B
                thermal=temp,  # float32 H x W, degrees C, finite
                ir8=_preview(temp),  # uint8 H x W
                boxes=boxes,  # float32 N x 4, xyxy inside [0, W] x [0, H]
                labels=labels,  # int64 N, 0-based
                group=stem.parent.name,
                meta={"file_name": f"{name}.rgb.png", "thermal_file": f"{name}.thermal.npy"},
            )

    def _read(self, stem: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        import cv2

        bgr = cv2.imread(str(stem.with_name(stem.name + ".rgb.png")), cv2.IMREAD_COLOR)
        if bgr is None:
            raise _Skip("RGB unreadable: not a decodable PNG")
        tpath = stem.with_name(stem.name + ".thermal.npy")
        if not tpath.exists():
            raise _Skip(f"missing thermal partner: {tpath.name} not found")
        temp = np.load(tpath, allow_pickle=False)
        if temp.ndim != 2 or temp.dtype.kind != "f":
            raise _Skip(f"thermal not a float temperature map: dtype {temp.dtype}, shape {temp.shape}")
        if not np.isfinite(temp).all():
            raise _Skip(f"non-finite temperatures: {int((~np.isfinite(temp)).sum())} pixel(s)")
        h, w = temp.shape
        if bgr.shape[:2] != (h, w):
            raise _Skip(f"size mismatch: RGB {bgr.shape[1]}x{bgr.shape[0]}, thermal {w}x{h}")
        boxes, labels = [], []
        bpath = stem.with_name(stem.name + ".boxes.csv")
        rows = list(csv.reader(bpath.open())) if bpath.exists() else []
        for row in rows:
            if not row:
                continue
            if len(row) != 5 or row[0] not in CATEGORIES:
                raise _Skip(
                    f"bad box line {','.join(row)!r}: expected category,x1,y1,x2,y2 with a category in "
                    f"{', '.join(CATEGORIES)}"
                )
            x1, y1, x2, y2 = np.clip(np.asarray(row[1:], np.float64), 0, [w, h, w, h])
            if x2 - x1 >= self.min_box and y2 - y1 >= self.min_box:
                boxes.append([x1, y1, x2, y2])
                labels.append(CATEGORIES.index(row[0]))
        return (
            np.ascontiguousarray(bgr[:, :, ::-1]),
            temp.astype(np.float32),
            np.asarray(boxes, np.float32).reshape(-1, 4),
            np.asarray(labels, np.int64),
        )


class _Skip(Exception):
    pass


def _preview(temp: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(temp, [1, 99])
    return np.clip((temp - lo) * 255.0 / max(hi - lo, 1e-3), 0, 255).astype(np.uint8)


def open_example(root: str | Path | None = None, min_box: float = 1.0) -> ExampleFoldersSource:
    """``DatasetSpec.open``: ``root`` is ``dataset.root`` (None: ``$EXAMPLE_FOLDERS_ROOT``); ``min_box`` is the
    option ``dataset.min_box``. There is no ``sensing`` parameter: the pairs are already aligned, so the host does
    not pass the ``sensing`` section."""
    import os

    root = root or os.environ.get(ROOT_ENV)
    if not root:
        raise DataError(f"dataset {NAME!r}: set dataset.root (or --root, or ${ROOT_ENV}) to the data folder")
    if isinstance(min_box, bool) or not isinstance(min_box, (int, float)) or min_box < 0:
        raise ConfigError(f"dataset {NAME!r}: option 'min_box' must be a number >= 0, got {min_box!r}")
    path = Path(root)
    if not path.is_dir():
        raise DataError(f"dataset {NAME!r}: {path} is not a folder")
    return ExampleFoldersSource(path, float(min_box))


def make_example(
    root: str | Path, sites: int = 3, per_site: int = 4, size: tuple[int, int] = (64, 48), seed: int = 0
) -> Path:
    """Write ``sites x per_site`` pairs: a facade at about 18 C with one warm patch and one cool window each."""
    import cv2

    root = Path(root)
    w, h = size
    rng = np.random.default_rng(seed)
    for s in range(sites):
        site = root / f"site{s + 1}"
        site.mkdir(parents=True, exist_ok=True)
        for k in range(per_site):
            t = 18.0 + 0.2 * rng.standard_normal((h, w))
            x, y = int(rng.integers(2, w // 2 - 10)), int(rng.integers(2, h - 12))
            t[y : y + 10, x : x + 10] += 6.0
            t[h // 2 - 6 : h // 2 + 6, w - 20 : w - 8] -= 4.0
            grey = np.clip((t - 10) * 12, 0, 255).astype(np.uint8)
            cv2.imwrite(str(site / f"{k:03d}.rgb.png"), np.stack([255 - grey, grey, grey], axis=2))
            np.save(site / f"{k:03d}.thermal.npy", t.astype(np.float32))
            (site / f"{k:03d}.boxes.csv").write_text(
                f"hot_spot,{x},{y},{x + 10},{y + 10}\nwindow,{w - 20},{h // 2 - 6},{w - 8},{h // 2 + 6}\n"
            )
    return root


SPEC = DatasetSpec(
    name=NAME,
    open=open_example,
    categories=CATEGORIES,
    description="example plugin: aligned RGB PNG + temperature .npy pairs, one folder per site",
    thermal="radiometric",
    default_encoding="c2",
    # the protocol YAML ships in this package (package data in pyproject.toml)
    protocol="harness_example_dataset:protocol.yaml",
    root_env=ROOT_ENV,
)


@hookimpl
def register_datasets(register: Any) -> None:
    register(SPEC)


@hookimpl
def register_commands(cli: Any) -> None:
    import click

    @cli.command(name="example-data")
    @click.argument("folder", type=click.Path(file_okay=False, path_type=Path))
    @click.option("--sites", type=int, default=3, show_default=True, help="Sites (groups, one fold each) to write.")
    @click.option("--per-site", type=int, default=4, show_default=True, help="Image pairs per site.")
    def example_data(folder: Path, sites: int, per_site: int) -> None:
        """Write a small example-folders dataset to FOLDER."""
        make_example(folder, sites, per_site)
        click.echo(f"{sites * per_site} pairs in {folder}")
