"""A tiny ``coco-rgbt`` folder made by the tests: aligned RGB PNGs, 16-bit centi-Kelvin PNGs and one COCO JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

CATEGORIES = [{"id": 1, "name": "hot_spot"}, {"id": 2, "name": "window"}]
GROUPS = ("site-a", "site-b", "site-c")
W, H = 64, 48


def temperature(k: int) -> np.ndarray:
    """A facade at about 18 C with a warm patch (hot_spot) and a cool pane (window) that move with ``k``."""
    rng = np.random.default_rng(k)
    t = 18.0 + 0.2 * rng.standard_normal((H, W))
    x = 6 + (k * 3) % 30
    t[10:20, x : x + 10] += 6.0
    t[28:40, 40:52] -= 4.0
    return t.astype(np.float32)


def boxes(k: int) -> list[tuple[int, list[float]]]:
    x = 6 + (k * 3) % 30
    return [(1, [float(x), 10.0, 10.0, 10.0]), (2, [40.0, 28.0, 12.0, 12.0])]


def centikelvin(t: np.ndarray) -> np.ndarray:
    return np.rint((t.astype(np.float64) + 273.15) * 100).astype(np.uint16)


def make_coco_rgbt(root: Path, n: int = 12, groups: tuple[str, ...] = GROUPS) -> Path:
    """``n`` aligned pairs (RGB PNG + 16-bit centi-Kelvin PNG, no sidecar) spread over ``groups``."""
    import cv2

    (root / "rgb").mkdir(parents=True, exist_ok=True)
    (root / "thermal").mkdir(parents=True, exist_ok=True)
    images, anns = [], []
    for k in range(n):
        t = temperature(k)
        grey = np.clip((t - 10) * 12, 0, 255).astype(np.uint8)
        rgb = np.stack([grey, np.roll(grey, 1, axis=1), 255 - grey], axis=2)
        cv2.imwrite(str(root / "rgb" / f"{k:03d}.png"), rgb[:, :, ::-1])
        cv2.imwrite(str(root / "thermal" / f"{k:03d}.png"), centikelvin(t))
        images.append(
            {
                "id": k + 1,
                "file_name": f"rgb/{k:03d}.png",
                "thermal_file_name": f"thermal/{k:03d}.png",
                "group": groups[k % len(groups)],
                "width": W,
                "height": H,
            }
        )
        for cat, bbox in boxes(k):
            anns.append(
                {
                    "id": len(anns) + 1,
                    "image_id": k + 1,
                    "category_id": cat,
                    "bbox": bbox,
                    "area": bbox[2] * bbox[3],
                    "iscrowd": 0,
                }
            )
    write_json(root, {"images": images, "annotations": anns, "categories": CATEGORIES})
    return root


def read_json(root: Path) -> dict[str, Any]:
    return json.loads((root / "annotations.json").read_text())


def write_json(root: Path, coco: dict[str, Any]) -> None:
    (root / "annotations.json").write_text(json.dumps(coco))


def prepare_coco_rgbt(root: Path, cache: Path, *accept: str) -> Any:
    """``harness prepare`` of the ``coco-rgbt`` folder ``root`` into ``cache`` with the default protocol, accepting
    the input guard's findings ``accept`` (``"all"`` for every one)."""
    from harness.cache import prepare
    from harness.config import load_config

    cfg = load_config(protocol="default")
    cfg["dataset"] = {"root": str(root)}
    cfg["inputs"] = {"accept": list(accept)}
    return prepare("coco-rgbt", cfg, cache_root=cache, progress=False)
