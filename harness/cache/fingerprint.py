"""A compact per-sample fingerprint of prepared samples, and the measured difference between two of them.

A content digest (``PreparedDataset.content_digest``) says whether two sets of samples are identical; it cannot say
by how much they differ. Reference results are kept comparable across library releases by a fingerprint small enough
to ship beside them: per sample its image id, size, boxes and labels exactly, and per picture (the RGB image, the
aligned thermal picture, each encoding's channel) a grid of ``TILE`` x ``TILE`` tiles, each tile its 32-bit digest
and the sum of its values. Two fingerprints give the largest box shift, and per picture the share of tiles whose
pixels differ and the largest change of a tile's mean value: what a library release changes (a float32 ulp on a box
corner, one grey level on a few hundred pixels) stays far below what another seed, profile or sensing option changes
(every tile, and boxes by pixels).

``TOLERANCE`` holds the limits under which two sets of samples are treated as the same samples, measured as
docs/benchmark.md ("Matching across library releases") describes: OpenCV 5.0.0 against 5.1.0 on the default synthetic
set moved 691 of 4,472 box coordinates by at most 3.1e-5 px (one float32 ulp) and 426 of 27.5 million RGB values by
one grey level (the largest change of a tile's mean: 0.001), and left temperatures and every encoding identical;
OpenCV 4.14.0 against 5.0.0, a major release, moved boxes by at most 2.5e-4 px and 8 % of RGB values by up to 3
grey levels (largest tile-mean change 0.058). Changes a user makes move far more: RGB warped without antialiasing
moves a tile mean by up to 1.2 grey levels, nearest-neighbour resampling by 2.4, another generator seed changes the
boxes themselves. The share of changed tiles is reported, not limited: a major release changes every tile a little.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

#: Side of a fingerprint tile, in pixels.
TILE = 32
#: The fingerprint format (stored as ``format`` in the file).
FORMAT = 1


@dataclass(frozen=True)
class Tolerance:
    """Limits under which samples that are not byte-identical still count as the same samples."""

    box_px: float = 0.01  # largest shift of any box coordinate, in pixels
    tile_mean: float = 0.25  # largest change of one tile's mean value (grey levels; degrees C for temperatures)

    def describe(self) -> str:
        return (
            f"images, sizes and labels identical, boxes within {self.box_px:g} px, no {TILE}-px tile's mean value "
            f"moved by more than {self.tile_mean:g} (grey levels, or degrees C)"
        )


TOLERANCE = Tolerance()


def _planes(prepared: Any, encodings: Sequence[tuple[Any, Mapping[str, Any]]]) -> list[str]:
    return ["rgb", "aligned"] + [f"enc:{enc.name}" for enc, _ in encodings if getattr(enc, "channels", 1)]


def compute(prepared: Any, encodings: Sequence[tuple[Any, Mapping[str, Any]]] = ()) -> dict[str, np.ndarray]:
    """The fingerprint of every sample of ``prepared`` (a ``PreparedDataset``), with the channels of ``encodings``
    (``(EncodingSpec, params)`` pairs), as arrays keyed as they are stored (``save``)."""
    n = len(prepared.records)
    ids = np.zeros(n, np.int64)
    shapes = np.zeros((n, 2), np.int32)
    nbox = np.zeros(n, np.int32)
    boxes: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    planes = _planes(prepared, encodings)
    tiles: dict[str, tuple[list[int], list[float], list[int]]] = {p: ([], [], []) for p in planes}
    for i in range(n):
        r = prepared.records[i]
        ids[i] = int(r["image_id"])
        b, lab = prepared.targets(i)
        crowd_b, crowd_l = prepared.crowd_targets(i)
        b = np.concatenate([np.asarray(b, np.float32).reshape(-1, 4), np.asarray(crowd_b, np.float32).reshape(-1, 4)])
        lab = np.concatenate([np.asarray(lab, np.int64).reshape(-1), np.asarray(crowd_l, np.int64).reshape(-1)])
        nbox[i] = len(b)
        boxes.append(b)
        labels.append(lab)
        rgb = prepared.rgb(i)
        shapes[i] = rgb.shape[:2]
        sample = prepared[i]
        pictures: dict[str, np.ndarray | None] = {
            "rgb": rgb,
            "aligned": sample.thermal if sample.thermal is not None else sample.ir8,
        }
        for enc, params in encodings:
            if getattr(enc, "channels", 1):
                pictures[f"enc:{enc.name}"] = prepared.channel(i, enc, dict(params))
        for name in planes:
            _add_tiles(tiles[name], pictures.get(name))
    out: dict[str, np.ndarray] = {
        "format": np.array([FORMAT, TILE], np.int32),
        "ids": ids,
        "shape": shapes,
        "nbox": nbox,
        "boxes": np.concatenate(boxes) if boxes else np.zeros((0, 4), np.float32),
        "labels": (np.concatenate(labels) if labels else np.zeros(0, np.int64)).astype(np.int32),
    }
    for name, (digests, sums, counts) in tiles.items():
        out[f"{name}/hash"] = np.asarray(digests, np.uint32)
        out[f"{name}/sum"] = np.asarray(sums, np.float64)
        out[f"{name}/count"] = np.asarray(counts, np.int32)
    return out


def _add_tiles(into: tuple[list[int], list[float], list[int]], img: np.ndarray | None) -> None:
    """Append the digest, sum and value count of every ``TILE`` x ``TILE`` tile of ``img`` (row-major)."""
    if img is None:
        return
    arr = np.asarray(img)
    h, w = arr.shape[:2]
    digests, sums, counts = into
    wide = arr.astype(np.float64)
    for y in range(0, h, TILE):
        for x in range(0, w, TILE):
            t = np.ascontiguousarray(arr[y : y + TILE, x : x + TILE])
            digests.append(int.from_bytes(hashlib.blake2b(t.data, digest_size=4).digest(), "little"))
            block = wide[y : y + TILE, x : x + TILE]
            finite = np.isfinite(block)
            sums.append(float(block[finite].sum()))
            counts.append(int(finite.sum()))


def save(path: str | Path, fp: Mapping[str, np.ndarray]) -> None:
    """Write a fingerprint (compressed ``.npz``), atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez_compressed(f, allow_pickle=False, **dict(fp))
    tmp.replace(path)


def load(path: str | Path) -> dict[str, np.ndarray]:
    with np.load(Path(path), allow_pickle=False) as z:
        out = {k: z[k] for k in z.files}
    if "format" not in out or int(out["format"][0]) != FORMAT:
        raise ValueError(f"{path}: not a sample fingerprint of format {FORMAT}")
    return out


# ------------------------------------------------------------------------------------------------- comparing
@dataclass
class PictureDifference:
    tiles: int
    changed: int
    largest_mean_change: float

    @property
    def share(self) -> float:
        return self.changed / self.tiles if self.tiles else 0.0


@dataclass
class Difference:
    """What differs between two fingerprints: ``other`` lists differences no tolerance covers (other images, sizes,
    labels, numbers of boxes, a picture only one side has); otherwise the largest box shift and per picture the
    changed tiles."""

    other: list[str] = field(default_factory=list)
    box_shift: float = 0.0
    boxes_moved: int = 0
    box_values: int = 0
    pictures: dict[str, PictureDifference] = field(default_factory=dict)

    @property
    def identical(self) -> bool:
        return not self.other and self.boxes_moved == 0 and not any(p.changed for p in self.pictures.values())

    def within(self, tol: Tolerance = TOLERANCE) -> bool:
        return (
            not self.other
            and self.box_shift <= tol.box_px
            and all(p.largest_mean_change <= tol.tile_mean for p in self.pictures.values())
        )

    def describe(self) -> str:
        """One sentence: ``boxes moved by at most 3.1e-05 px (691 of 4,472 coordinates); rgb: 2.1 % of tiles
        changed, largest tile-mean change 0.004; aligned, enc:c2 identical``."""
        if self.other:
            return "; ".join(self.other[:3]) + (" ..." if len(self.other) > 3 else "")
        parts = [
            f"boxes moved by at most {self.box_shift:.2g} px ({self.boxes_moved:,} of {self.box_values:,} coordinates)"
            if self.boxes_moved
            else "boxes identical"
        ]
        same = [name for name, p in self.pictures.items() if not p.changed]
        for name, p in self.pictures.items():
            if p.changed:
                parts.append(
                    f"{_label(name)}: {100 * p.share:.2g} % of {TILE}-px tiles changed ({p.changed:,} of {p.tiles:,}), "
                    f"largest tile-mean change {p.largest_mean_change:.2g}"
                )
        if same:
            parts.append(f"{', '.join(_label(n) for n in same)} identical")
        return "; ".join(parts)


def _label(plane: str) -> str:
    return {"rgb": "RGB pixels", "aligned": "temperatures (or 8-bit thermal)"}.get(plane, plane.replace("enc:", ""))


def compare(mine: Mapping[str, np.ndarray], ref: Mapping[str, np.ndarray], planes: Iterable[str]) -> Difference:
    """The difference of fingerprint ``mine`` from ``ref`` over the pictures ``planes`` (``rgb``, ``aligned``,
    ``enc:<name>``), matched by image id."""
    d = Difference()
    ids_m, ids_r = mine["ids"], ref["ids"]
    if len(ids_m) != len(ids_r) or set(ids_m.tolist()) != set(ids_r.tolist()):
        only_m, only_r = set(ids_m.tolist()) - set(ids_r.tolist()), set(ids_r.tolist()) - set(ids_m.tolist())
        d.other.append(
            f"other images: {len(ids_m)} samples against the references' {len(ids_r)} "
            f"({len(only_m)} image id(s) only yours, {len(only_r)} only the references')"
        )
        return d
    order = _order(ids_m, ids_r)  # mine's row of each of ref's samples
    if not np.array_equal(mine["shape"][order], ref["shape"]):
        n = int((mine["shape"][order] != ref["shape"]).any(axis=1).sum())
        d.other.append(f"other image sizes in {n} of {len(ids_r)} samples")
        return d
    if not np.array_equal(mine["nbox"][order], ref["nbox"]):
        n = int((mine["nbox"][order] != ref["nbox"]).sum())
        d.other.append(f"other numbers of boxes in {n} of {len(ids_r)} samples")
        return d
    rows = _tile_rows(np.asarray(mine["nbox"]), order)  # mine's box rows, in ref's sample order
    if not np.array_equal(mine["labels"][rows], ref["labels"]):
        d.other.append(f"other labels on {int((mine['labels'][rows] != ref['labels']).sum())} boxes")
        return d
    diff = np.abs(mine["boxes"][rows].astype(np.float64) - ref["boxes"].astype(np.float64))
    d.box_values = int(diff.size)
    d.boxes_moved = int((diff > 0).sum())
    d.box_shift = float(diff.max()) if diff.size else 0.0
    tiles_per = _tiles_per_sample(ref["shape"])
    tile_order = _tile_rows(_tiles_per_sample(mine["shape"]), order)
    for plane in planes:
        if f"{plane}/hash" not in ref or f"{plane}/hash" not in mine:
            side = "the references" if f"{plane}/hash" not in ref else "your samples"
            d.other.append(f"{_label(plane)}: not in {side}' fingerprint")
            continue
        hm, hr = mine[f"{plane}/hash"][tile_order], ref[f"{plane}/hash"]
        if len(hm) != len(hr) or len(hr) != int(tiles_per.sum()):
            d.other.append(f"{_label(plane)}: another tiling")
            continue
        changed = hm != hr
        cm, cr = mine[f"{plane}/count"][tile_order], ref[f"{plane}/count"]
        with np.errstate(divide="ignore", invalid="ignore"):
            mean_m = np.where(cm > 0, mine[f"{plane}/sum"][tile_order] / np.maximum(cm, 1), 0.0)
            mean_r = np.where(cr > 0, ref[f"{plane}/sum"] / np.maximum(cr, 1), 0.0)
        moved = np.abs(mean_m - mean_r)
        if (cm != cr).any():
            d.other.append(
                f"{_label(plane)}: missing values (NaN or masked) in other places in {int((cm != cr).sum())} tiles"
            )
        d.pictures[plane] = PictureDifference(
            int(len(hr)), int(changed.sum()), float(moved.max()) if len(moved) else 0.0
        )
    return d


def _order(ids_m: np.ndarray, ids_r: np.ndarray) -> np.ndarray:
    where = {int(v): j for j, v in enumerate(ids_m.tolist())}
    return np.asarray([where[int(v)] for v in ids_r.tolist()], np.int64)


def _tiles_per_sample(shapes: np.ndarray) -> np.ndarray:
    return ((shapes[:, 0] + TILE - 1) // TILE) * ((shapes[:, 1] + TILE - 1) // TILE)


def _tile_rows(per_sample: np.ndarray, order: np.ndarray) -> np.ndarray:
    starts = np.concatenate([[0], np.cumsum(per_sample)])
    if not len(order):
        return np.zeros(0, np.int64)
    return np.concatenate([np.arange(starts[j], starts[j + 1]) for j in order]).astype(np.int64)


__all__ = ["TILE", "TOLERANCE", "Difference", "Tolerance", "compare", "compute", "load", "save"]
