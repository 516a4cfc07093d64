"""Flights for the screening tests, made from the tiny synthetic M3T set (its raw captures are in DJI layout)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

#: a plausible DJI position per capture of project P1 (what the XMP of the test flights carries)
POSITIONS = {
    "DJI_20240512094000_0001": {
        "lat": 48.13743215,
        "lon": 11.57549012,
        "alt_abs": 541.234,
        "alt_rel": 22.5,
        "gimbal_yaw": 91.3,
        "gimbal_pitch": -2.1,
        "gimbal_roll": 0.0,
        "flight_yaw": 90.8,
    },
    "DJI_20240512094005_0002": {
        "lat": 48.13744102,
        "lon": 11.57553311,
        "alt_abs": 541.301,
        "alt_rel": 22.6,
        "gimbal_yaw": 90.9,
        "gimbal_pitch": -1.8,
        "gimbal_roll": 0.0,
        "flight_yaw": 90.1,
    },
}


def p1_flight(tiny: Path, folder: Path, xmp: bool = True, extras: bool = True) -> Path:
    """The P1 captures of the tiny set as a drone writes them: wide and thermal JPEGs with DJI XMP positions, and
    (``extras``) a zoom capture, a video and its subtitle file that a screen must ignore."""
    from harness.screen import add_xmp

    folder.mkdir(parents=True, exist_ok=True)
    for src in sorted((tiny / "images" / "P1").iterdir()):
        data = src.read_bytes()
        capture = src.stem.rsplit("_", 1)[0]
        if xmp:
            data = add_xmp(data, POSITIONS[capture])
        (folder / src.name).write_bytes(data)
    if extras:
        first = sorted((tiny / "images" / "P1").glob("*_W.JPG"))[0]
        shutil.copy(first, folder / first.name.replace("_W.", "_Z."))
        (folder / "DJI_20240512094010_0003_V.MP4").write_bytes(b"\x00\x00\x00\x18ftypmp42")
        (folder / "DJI_20240512094010_0003_V.SRT").write_text("1\n00:00:00,000 --> 00:00:01,000\n")
    return folder


def upscaled_flight(tiny: Path, folder: Path, factor: int = 2) -> Path:
    """The P1 captures with every wide image enlarged ``factor`` times (EXIF kept): a wide frame the warp shrinks
    by more than 2x, as on the real M3T (4000x3000 wide beside 640x512 thermal)."""
    import cv2

    from harness.sensing import jpeg

    folder.mkdir(parents=True, exist_ok=True)
    for src in sorted((tiny / "images" / "P1").iterdir()):
        if not src.name.endswith("_W.JPG"):
            shutil.copy(src, folder / src.name)
            continue
        data = src.read_bytes()
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        big = cv2.resize(img, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)
        ok, enc = cv2.imencode(".jpg", big, [cv2.IMWRITE_JPEG_QUALITY, 92])
        assert ok
        exif = next(
            p for p in jpeg.read_segments(data, src, require_eoi=False).payloads(jpeg.APP1) if p.startswith(b"Exif")
        )
        (folder / src.name).write_bytes(b"\xff\xd8" + jpeg.segment(jpeg.APP1, exif) + enc.tobytes()[2:])
    return folder
