"""The homographies file: one entry per inspection group, a YAML a person can read and edit."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import DataError
from harness.sensing.registration.homography import homography_from_similarity, image_center, normalize


@dataclass
class HomographyEntry:
    """One group's registration as stored in the homographies file."""

    H: np.ndarray
    method: str = "manual"  # landmarks | similarity | auto | focal | manual
    similarity: dict[str, float] | None = None
    rgb_size: tuple[int, int] | None = None
    thermal_size: tuple[int, int] | None = None
    quality: dict[str, Any] = field(default_factory=dict)
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"method": self.method}
        if self.method == "similarity" and self.similarity is not None:
            out["similarity"] = {k: float(v) for k, v in self.similarity.items()}
        else:
            out["H"] = [[float(f"{v:.10g}") for v in row] for row in normalize(self.H)]
        if self.rgb_size:
            out["rgb_size"] = [int(v) for v in self.rgb_size]
        if self.thermal_size:
            out["thermal_size"] = [int(v) for v in self.thermal_size]
        if self.quality:
            out["quality"] = self.quality
        if self.note:
            out["note"] = self.note
        return out


def entry_from_similarity(
    params: Mapping[str, float], rgb_size: tuple[int, int] | None, thermal_size: tuple[int, int] | None, note: str = ""
) -> HomographyEntry:
    """An entry defined by similarity parameters about the image centres (origin when a size is unknown)."""
    missing = {"tx", "ty", "theta_deg", "scale"} - set(params)
    if missing:
        raise DataError(f"similarity parameters lack {sorted(missing)}; give tx, ty, theta_deg, scale")
    H = homography_from_similarity(
        float(params["tx"]),
        float(params["ty"]),
        float(params["theta_deg"]),
        float(params["scale"]),
        image_center(rgb_size) if rgb_size else (0.0, 0.0),
        image_center(thermal_size) if thermal_size else (0.0, 0.0),
    )
    return HomographyEntry(
        H,
        "similarity",
        {k: float(params[k]) for k in ("tx", "ty", "theta_deg", "scale")},
        rgb_size,
        thermal_size,
        note=note,
    )


HOMOGRAPHY_FILE_HEADER = """\
# RGB -> thermal homographies, one per inspection group: thermal pixel ~ H @ [x_rgb, y_rgb, 1].
# Edit freely. An entry is either
#   H: 3x3 matrix (row-major), or
#   similarity: {tx, ty, theta_deg, scale}   # u = scale * R(theta) (x - c_rgb) + c_thermal + (tx, ty)
# where c_rgb / c_thermal are the image centres ((w-1)/2, (h-1)/2) from rgb_size / thermal_size [w, h].
# When both are present, H wins.
"""


def save_homographies(
    path: str | Path, homographies: Mapping[str, np.ndarray | HomographyEntry], meta: Mapping[str, Any] | None = None
) -> Path:
    """Write ``{group: H or HomographyEntry}`` as a commented, human-editable YAML file."""
    from harness.config import dump_yaml
    from harness.io import atomic_write_text

    groups = {}
    for group, value in homographies.items():
        entry = value if isinstance(value, HomographyEntry) else HomographyEntry(np.asarray(value))
        groups[str(group)] = entry.to_dict()
    body: dict[str, Any] = {"schema": 1, "groups": groups}
    if meta:
        body["meta"] = dict(meta)
    return atomic_write_text(path, HOMOGRAPHY_FILE_HEADER + dump_yaml(body))


def load_homography_entries(path: str | Path) -> dict[str, HomographyEntry]:
    """Every group's entry of a homographies file (``H`` computed from ``similarity`` where needed)."""
    from harness.config import read_yaml
    from harness.errors import ConfigError

    path = Path(path)
    try:
        data = read_yaml(path)
    except ConfigError as exc:
        raise DataError(str(exc)) from None
    groups = data.get("groups")
    if not isinstance(groups, dict) or not groups:
        raise DataError(f"{path}: expected a 'groups' mapping {{group: {{H: ... or similarity: ...}}}}")
    out: dict[str, HomographyEntry] = {}
    for group, raw in groups.items():
        where = f"{path}: group {group!r}"
        if not isinstance(raw, dict):
            raise DataError(f"{where}: expected a mapping with 'H' or 'similarity'")
        rgb_size = tuple(raw["rgb_size"]) if raw.get("rgb_size") else None
        thermal_size = tuple(raw["thermal_size"]) if raw.get("thermal_size") else None
        if "H" in raw:
            try:
                H = np.asarray(raw["H"], dtype=np.float64)
            except (TypeError, ValueError):
                raise DataError(f"{where}: H is not a 3x3 matrix of numbers") from None
            if H.shape != (3, 3):
                raise DataError(f"{where}: H has shape {H.shape}, expected 3x3")
            try:
                H = normalize(H)
            except DataError as exc:
                raise DataError(f"{where}: {exc}") from None
            entry = HomographyEntry(
                H,
                str(raw.get("method", "manual")),
                raw.get("similarity"),
                rgb_size,  # type: ignore[arg-type]
                thermal_size,
                dict(raw.get("quality", {}) or {}),
                str(raw.get("note", "")),
            )
        elif "similarity" in raw:
            try:
                entry = entry_from_similarity(
                    raw["similarity"],
                    rgb_size,
                    thermal_size,  # type: ignore[arg-type]
                    note=str(raw.get("note", "")),
                )
            except (DataError, TypeError, ValueError) as exc:
                raise DataError(f"{where}: {exc}") from None
        else:
            raise DataError(f"{where}: needs 'H' or 'similarity'")
        out[str(group)] = entry
    return out


def load_homographies(path: str | Path) -> dict[str, np.ndarray]:
    """``{group: H}`` from a homographies file written by ``save_homographies`` (or by hand)."""
    return {g: e.H for g, e in load_homography_entries(path).items()}


def support_boxes(entries: Mapping[str, HomographyEntry]) -> dict[str, tuple[int, int, int, int]]:
    """Common-support box of every entry that records both image sizes (thermal frame, x1/y1 exclusive)."""
    from harness.sensing.warp import common_support_box, support_mask

    out = {}
    for group, e in entries.items():
        if e.rgb_size and e.thermal_size:
            mask = support_mask(e.H, e.rgb_size, (e.thermal_size[1], e.thermal_size[0]))
            if mask.any():
                out[group] = common_support_box(mask)
    return out
