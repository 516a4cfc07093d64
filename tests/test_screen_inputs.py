"""``harness screen`` on flights as DJI writes them, and what it says when a flight gives it nothing to do.

Positions from DJI's XMP in both spellings of the longitude and from EXIF GPS (exiftool is the reference), the
decoding options a refusal names, exit statuses and counts that add up, an interrupted screen, stale frame records,
and overlays an inspector can read. The tests that screen train one small run for the module (as ``test_screen``).
"""

# ruff: noqa: F811 - the tests take the imported ``trained`` fixture by name
from __future__ import annotations

import csv
import json
import logging
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from screen_helpers import POSITIONS, p1_flight
from test_screen import _file_route, _frames, _screen, trained  # noqa: F401 - the module's run

pytestmark = [pytest.mark.usefixtures("one_torch_thread")]

needs_exiftool = pytest.mark.skipif(
    shutil.which("exiftool") is None, reason="exiftool (Debian libimage-exiftool-perl) not installed"
)
#: (latitude, longitude) in each of the four hemisphere combinations
HEMISPHERES = {
    "NE": (48.13743215, 11.57549012),
    "NW": (40.71277912, -74.00597488),
    "SE": (-33.86785123, 151.20732411),
    "SW": (-22.90684711, -43.17289635),
}


def _csv(out: Path) -> list[dict]:
    with open(out / "findings.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _small_jpeg() -> bytes:
    import cv2

    img = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    ok, enc = cv2.imencode(".jpg", img)
    assert ok
    return enc.tobytes()


def _exiftool(paths: list[Path], *tags: str) -> dict[str, dict]:
    proc = subprocess.run(
        ["exiftool", "-j", "-n", "-G", *tags, *map(str, paths)], capture_output=True, text=True, check=True
    )
    return {Path(r["SourceFile"]).name: r for r in json.loads(proc.stdout)}


# ------------------------------------------------------------------------------------------------ positions
@needs_exiftool
def test_positions_equal_exiftool_in_every_hemisphere_in_both_xmp_spellings_and_exif_only(tmp_path):
    from harness.screen import add_xmp, read_position
    from harness.screen.position import add_exif_gps

    plain = _small_jpeg()
    files: dict[str, tuple[Path, str]] = {}
    for k, (hemi, (lat, lon)) in enumerate(HEMISPHERES.items()):
        alt = 541.234 if hemi.startswith("N") else -12.5  # below sea level in the south: GPSAltitudeRef 1
        values = {"lat": lat, "lon": lon, "alt_abs": alt, "alt_rel": 22.5, "gimbal_yaw": -90.0 + k}
        for spelling in ("GpsLongitude", "GpsLongtitude"):
            path = tmp_path / f"xmp_{spelling}_{hemi}.jpg"
            path.write_bytes(add_xmp(plain, values, longitude=spelling))
            files[path.name] = (path, "xmp")
        path = tmp_path / f"exif_{hemi}.jpg"
        path.write_bytes(add_exif_gps(plain, lat, lon, alt))
        files[path.name] = (path, "exif")
    xmp = _exiftool([p for p, kind in files.values() if kind == "xmp"], "-XMP-drone-dji:all")
    exif = _exiftool(
        [p for p, kind in files.values() if kind == "exif"],
        "-Composite:GPSLatitude",
        "-Composite:GPSLongitude",
        "-Composite:GPSAltitude",
        "-XMP:all",
    )
    for name, (path, kind) in files.items():
        ours = read_position(path.read_bytes(), str(path))
        if kind == "xmp":
            rec = xmp[name]
            lon_key = "XMP:GPSLongtitude" if "Longtitude" in name else "XMP:GPSLongitude"
            theirs = (rec["XMP:GPSLatitude"], rec[lon_key], float(rec["XMP:AbsoluteAltitude"]))
            assert float(rec["XMP:RelativeAltitude"]) == ours.alt_rel
        else:
            rec = exif[name]
            assert not any(k.startswith("XMP") for k in rec), rec  # EXIF GPS only
            theirs = (rec["Composite:GPSLatitude"], rec["Composite:GPSLongitude"], rec["Composite:GPSAltitude"])
        assert (ours.lat, ours.lon, ours.alt_abs) == pytest.approx(theirs, abs=1e-9), name
        assert ours.gps_source == kind, name
        lat, lon = HEMISPHERES[name[-6:-4]]
        assert np.sign([ours.lat, ours.lon]).tolist() == np.sign([lat, lon]).tolist(), name


def test_xmp_wins_over_exif_and_the_thermal_xmp_over_the_wide_exif():
    from harness.screen import add_xmp
    from harness.screen.position import add_exif_gps, capture_position

    plain = _small_jpeg()
    both = add_exif_gps(add_xmp(plain, {"lat": 1.5, "lon": 2.5}), -10.0, -20.0)
    pos = capture_position((both, "w", None), None)
    assert (pos.lat, pos.lon, pos.gps_source) == (1.5, 2.5, "xmp")
    wide_exif = add_exif_gps(plain, -10.0, -20.0, 5.0)
    thermal_xmp = add_xmp(plain, {"lat": 3.25, "lon": -4.75, "gimbal_pitch": -90.0}, longitude="GpsLongtitude")
    pos = capture_position((wide_exif, "w", None), (thermal_xmp, "t", None))
    assert (pos.lat, pos.lon, pos.gimbal_pitch, pos.gps_source) == (3.25, -4.75, -90.0, "xmp")
    pos = capture_position((wide_exif, "w", None), (plain, "t", None))
    assert (pos.lat, pos.lon, pos.alt_abs, pos.gps_source) == (-10.0, -20.0, 5.0, "exif")
    pos = capture_position((plain, "w", None), (plain, "t", None))
    assert not pos.has_gps and pos.gps_source is None


def test_a_screen_labels_exif_positions_reads_longtitude_and_warns_of_frames_without_gps(
    trained,
    tmp_path,
    caplog,
):
    from harness.screen import add_xmp
    from harness.screen.position import add_exif_gps

    flight = p1_flight(trained.tiny, tmp_path / "flight", xmp=False, extras=False)
    first, second = sorted(POSITIONS)
    w1 = flight / f"{first}_W.JPG"
    w1.write_bytes(add_xmp(w1.read_bytes(), POSITIONS[first], longitude="GpsLongtitude"))
    w2 = flight / f"{second}_W.JPG"
    p2 = POSITIONS[second]
    w2.write_bytes(add_exif_gps(w2.read_bytes(), p2["lat"], -p2["lon"], p2["alt_abs"]))
    text = _screen(trained, flight, tmp_path / "out", *_file_route(trained), "--conf", trained.eval_conf)
    rows = _csv(tmp_path / "out")
    assert {r["frame"] for r in rows} == {first, second}
    for row in rows:
        want = POSITIONS[row["frame"]]
        lon = want["lon"] if row["frame"] == first else -want["lon"]
        assert float(row["lat"]) == pytest.approx(want["lat"], abs=1e-8)
        assert float(row["lon"]) == pytest.approx(lon, abs=1e-7)
        assert row["gps_source"] == ("xmp" if row["frame"] == first else "exif")
    geo = json.loads((tmp_path / "out" / "findings.geojson").read_text())
    assert all(f["geometry"] is not None for f in geo["features"])
    assert {f["properties"]["gps_source"] for f in geo["features"]} == {"xmp", "exif"}
    assert "1 from EXIF GPS" in text
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["positions"] == {"xmp": 1, "exif": 1, "none": 0}
    assert "(EXIF GPS)" in (tmp_path / "out" / "index.html").read_text()

    bare = p1_flight(trained.tiny, tmp_path / "bare", xmp=False, extras=False)
    with caplog.at_level(logging.WARNING, logger="harness.screen.job"):
        text = _screen(trained, bare, tmp_path / "bare_out", *_file_route(trained))
    assert "2 of 2 screened frame(s) carry no GPS position" in caplog.text
    assert "2 without GPS" in text
