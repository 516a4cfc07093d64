"""Tiny copies of the LLVIP and FLIR-aligned releases, written by the tests in the exact public layouts.

LLVIP: ``LLVIP/{Annotations,infrared/{train,test},visible/{train,test}}`` with six-digit names (train ``01...``,
test ``19...``) and labelImg-style VOC XMLs (1-based inclusive pixel indices, ``<difficult>0</difficult>``).

FLIR-aligned in three layouts, each as the code that reads it expects: ICAFusion's (``FLIR-align-3class/
{visible,infrared}/{train,test}/`` holding the images, the labels in ``FLIR-align-3class/labels/{train,test}/``,
where ICAFusion's ``img2label_paths`` finds them by replacing the modality folder with ``labels``), YOLOv5's (an
``images/`` and a ``labels/`` folder in each modality's split, found by replacing ``/images/`` with ``/labels/``)
and the authors' release (``align/``). Visible ``FLIR_<n>_RGB.jpg``, infrared ``FLIR_<n>_PreviewData.jpeg``,
labels ``<class> <cx> <cy> <w> <h>`` normalised to the image size, classes ``person, car, bicycle``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from eightbit_fixtures import _draw, write_voc

LLVIP_FRAMES = {"train": ("010001", "010002", "010003"), "test": ("190001", "190002")}
FLIR_FRAMES = {"train": ("00002", "00003", "00005"), "test": ("08863", "08865")}
FLIR_CLASSES = ("person", "car", "bicycle")


def _boxes(rng: np.random.Generator, w: int, h: int, n: int) -> list[tuple[int, int, int, int, int]]:
    """n boxes (x, y, bw, bh, class index) inside the frame (0-based pixel columns x .. x+bw-1)."""
    out = []
    for _ in range(n):
        bw, bh = int(rng.integers(6, 20)), int(rng.integers(6, 20))
        out.append((int(rng.integers(0, w - bw)), int(rng.integers(0, h - bh)), bw, bh, int(rng.integers(0, 3))))
    return out


def write_llvip(root: Path, size: tuple[int, int] = (80, 64), seed: int = 0) -> dict:
    """Write ``LLVIP/`` under ``root``; return {stem: [(x1, y1, x2, y2)] in 0-based corners}."""
    rng = np.random.default_rng(seed)
    w, h = size
    base = Path(root) / "LLVIP"
    (base / "Annotations").mkdir(parents=True, exist_ok=True)
    expected = {}
    for split, stems in LLVIP_FRAMES.items():
        for d in ("infrared", "visible"):
            (base / d / split).mkdir(parents=True, exist_ok=True)
        for stem in stems:
            objs = _boxes(rng, w, h, 2)
            vis, th = _draw(h, w, [o[:4] for o in objs], rng)
            cv2.imwrite(str(base / "visible" / split / f"{stem}.jpg"), vis, [cv2.IMWRITE_JPEG_QUALITY, 95])
            cv2.imwrite(
                str(base / "infrared" / split / f"{stem}.jpg"), cv2.merge([th, th, th]), [cv2.IMWRITE_JPEG_QUALITY, 95]
            )
            write_voc(
                base / "Annotations" / f"{stem}.xml",
                f"{stem}.jpg",
                w,
                h,
                [("person", x + 1, y + 1, x + bw, y + bh) for x, y, bw, bh, _ in objs],
                folder="JPEGImages",
            )
            expected[stem] = [(x, y, x + bw, y + bh) for x, y, bw, bh, _ in objs]
    return expected


def write_flir_aligned(root: Path, size: tuple[int, int] = (80, 64), seed: int = 0, layout: str = "yolov5") -> dict:
    """Write ``FLIR-align-3class/`` under ``root`` in YOLOv5's layout (``<modality>/<split>/images|labels/``) or,
    with ``layout="icafusion"``, ICAFusion's (images in ``<modality>/<split>/``, labels in ``labels/<split>/``);
    return {number: (visible boxes, infrared boxes)} where each box is (x1, y1, x2, y2, class index) in pixels. The
    infrared labels are the visible ones shifted by 1 px."""
    rng = np.random.default_rng(seed)
    w, h = size
    base = Path(root) / "FLIR-align-3class"
    expected = {}
    for split, numbers in FLIR_FRAMES.items():
        for n in numbers:
            objs = _boxes(rng, w - 1, h - 1, 3)
            vis, th = _draw(h, w, [o[:4] for o in objs], rng)
            boxes = {
                "visible": [(x, y, x + bw, y + bh, c) for x, y, bw, bh, c in objs],
                "infrared": [(x + 1, y + 1, x + 1 + bw, y + 1 + bh, c) for x, y, bw, bh, c in objs],
            }
            for modality, name, img in (("visible", f"FLIR_{n}_RGB", vis), ("infrared", f"FLIR_{n}_PreviewData", th)):
                if layout == "icafusion":
                    images, labels = base / modality / split, base / "labels" / split
                else:
                    images, labels = base / modality / split / "images", base / modality / split / "labels"
                images.mkdir(parents=True, exist_ok=True)
                labels.mkdir(parents=True, exist_ok=True)
                ext = ".jpg" if modality == "visible" else ".jpeg"
                cv2.imwrite(str(images / f"{name}{ext}"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
                lines = [
                    f"{c} {(x1 + x2) / 2 / w:.6f} {(y1 + y2) / 2 / h:.6f} {(x2 - x1) / w:.6f} {(y2 - y1) / h:.6f}"
                    for x1, y1, x2, y2, c in boxes[modality]
                ]
                (labels / f"{name}.txt").write_text("\n".join(lines) + "\n")
            expected[n] = (boxes["visible"], boxes["infrared"])
    return expected


def write_flir_release(root: Path, size: tuple[int, int] = (80, 64), seed: int = 0) -> dict:
    """Write the authors' release layout ``align/{JPEGImages,Annotations}`` + ``align_{train,validation}.txt`` with
    the same frames and the same thermal boxes as ``write_flir_aligned(seed=seed)``; VOC XMLs of the thermal image in
    labelImg's 1-based inclusive convention. Returns what ``write_flir_aligned`` returns."""
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        expected = write_flir_aligned(Path(tmp), size=size, seed=seed)
        src = Path(tmp) / "FLIR-align-3class"
        base = Path(root) / "align"
        (base / "JPEGImages").mkdir(parents=True, exist_ok=True)
        (base / "Annotations").mkdir(parents=True, exist_ok=True)
        w, h = size
        for split, numbers in FLIR_FRAMES.items():
            for n in numbers:
                for modality, name in (("visible", f"FLIR_{n}_RGB.jpg"), ("infrared", f"FLIR_{n}_PreviewData.jpeg")):
                    shutil.copy(src / modality / split / "images" / name, base / "JPEGImages" / name)
                write_voc(
                    base / "Annotations" / f"FLIR_{n}_PreviewData.xml",
                    f"FLIR_{n}_PreviewData.jpeg",
                    w,
                    h,
                    [(FLIR_CLASSES[c], x1 + 1, y1 + 1, x2, y2) for x1, y1, x2, y2, c in expected[n][1]],
                    folder="JPEGImages",
                )
            listing = "align_train.txt" if split == "train" else "align_validation.txt"
            (base / listing).write_text("".join(f"FLIR_{n}_PreviewData\n" for n in numbers))
    return expected
