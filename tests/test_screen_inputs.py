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


# ------------------------------------------------------------------------------------------------ exits and counts
@pytest.mark.parametrize(
    "files, says",
    [
        ((), "holds no files"),
        (("DJI_20240512094000_0001_Z.JPG", "DJI_20240512094000_0002_V.MP4"), "DJI_20240512094000_0001_Z.JPG"),
        (("IMG_0001.JPG", "IMG_0001_R.JPG"), "IMG_0001.JPG, IMG_0001_R.JPG"),
    ],
    ids=["empty", "zoom-and-video", "other-names"],
)
def test_nothing_to_screen_exits_1_and_says_why(trained, tmp_path, files, says):
    flight = tmp_path / "flight"
    flight.mkdir()
    for name in files:
        (flight / name).write_bytes(_small_jpeg())
    text = _screen(trained, flight, tmp_path / "out", code=1)
    assert "nothing was screened" in text and says in text, text
    if files:
        assert "holds no wide/thermal pair" in text and "<name>_W.JPG beside <name>_T.JPG" in text


def test_nothing_screened_because_every_capture_failed_exits_1(trained, tmp_path):
    flight = p1_flight(trained.tiny, tmp_path / "flight", extras=False)
    for wide in flight.glob("*_W.JPG"):
        wide.write_bytes(b"")
    text = _screen(trained, flight, tmp_path / "out", *_file_route(trained), code=1)
    assert "nothing was screened: of 2 capture(s), 2 failed" in text


@pytest.mark.parametrize("conf", ["1.5", "-1", "nan"])
def test_conf_must_lie_between_0_and_1(trained, tmp_path, conf):
    from harness.errors import ConfigError
    from harness.screen import ScreenRequest, screen

    flight = p1_flight(trained.tiny, tmp_path / "flight", extras=False)
    text = _screen(trained, flight, tmp_path / "out", "--conf", conf, code=2)
    assert "--conf" in text and ("0<=x<=1" in text.replace(" ", "") or "between 0 and 1" in text), text
    with pytest.raises(ConfigError, match="between 0 and 1"):
        screen(ScreenRequest(flight=flight, out=tmp_path / "lib", run=trained.run, conf=float(conf), progress=False))
    assert not (tmp_path / "out").exists() and not (tmp_path / "lib").exists()


def test_an_empty_wide_image_is_called_empty(trained, tmp_path):
    flight = p1_flight(trained.tiny, tmp_path / "flight", extras=False)
    empty = flight / "DJI_20240512094000_0001_W.JPG"
    empty.write_bytes(b"")
    text = _screen(trained, flight, tmp_path / "out", *_file_route(trained), code=1)
    assert f"{empty}: empty file (0 bytes)" in text and "copy it again from the card" in text
    assert "R-JPEG" not in text
    empty.write_bytes(b"GIF89a....")
    text = _screen(trained, flight, tmp_path / "out2", *_file_route(trained), code=1)
    assert f"{empty}: not a JPEG file" in text and "wide camera" in text and "R-JPEG" not in text


def test_the_counts_add_up(trained, tmp_path):
    flight = p1_flight(trained.tiny, tmp_path / "flight")  # with a zoom capture, a video and its subtitles
    first = sorted(POSITIONS)[0]
    broken = flight / "DJI_20240512094002_0004"
    shutil.copy(flight / f"{first}_T.JPG", f"{broken}_T.JPG")
    Path(f"{broken}_W.JPG").write_bytes(b"not a jpeg")  # a capture that fails
    shutil.copy(flight / f"{first}_W.JPG", flight / "DJI_20240512094003_0005_W.JPG")  # no partner
    text = _screen(trained, flight, tmp_path / "out", *_file_route(trained), code=1)
    c = json.loads((tmp_path / "out" / "manifest.json").read_text())["frames"]
    assert (c["captures"], c["screened"], c["failed"], c["unpaired_files"], c["ignored_files"]) == (3, 2, 1, 1, 3)
    assert c["captures"] == c["screened"] + c["failed"] + c["rejected_not_screened"] + c["not_reached"]
    line = "3 capture(s): 2 screened (2 now, 0 earlier), 1 failed; besides them 1 file(s) without a partner, 3 other"
    assert line in text and line in (tmp_path / "out" / "index.html").read_text()


def test_an_interrupted_screen_writes_the_frames_done(trained, tmp_path):
    from harness.screen import ScreenRequest, screen

    flight = p1_flight(trained.tiny, tmp_path / "flight", extras=False)
    out = tmp_path / "out"
    seen = []

    def ctrl_c(rec):
        seen.append(rec["frame"])
        raise KeyboardInterrupt

    req = ScreenRequest(
        flight=flight,
        out=out,
        run=trained.run,
        conf=0.001,
        progress=False,
        homography=trained.homographies,
        group="P1-01",
    )
    with pytest.raises(KeyboardInterrupt):
        screen(req, on_frame=ctrl_c)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["state"] == "interrupted" and manifest["frames"]["screened"] == 1 == len(seen)
    assert manifest["frames"]["not_reached"] == 1
    rows = _csv(out)
    assert rows and {r["frame"] for r in rows} == set(seen)
    html = (out / "index.html").read_text()
    assert f"{seen[0]}" in html and (out / "overlays" / f"{seen[0]}.jpg").exists()
    res = screen(req)  # a re-run goes on from there
    assert (res.screened, res.skipped_done) == (1, 1)
    assert json.loads((out / "manifest.json").read_text())["state"] == "finished"


def test_records_of_removed_captures_are_removed(trained, tmp_path):
    flight = p1_flight(trained.tiny, tmp_path / "flight", extras=False)
    out = tmp_path / "out"
    _screen(trained, flight, out, *_file_route(trained), "--conf", trained.eval_conf)
    gone = sorted(POSITIONS)[1]
    assert (out / "frames" / f"{gone}.json").exists() and (out / "overlays" / f"{gone}.jpg").exists()
    assert any(p.name.startswith(gone) for p in (out / "crops").iterdir())
    for path in flight.glob(f"{gone}_*"):
        path.unlink()
    _screen(trained, flight, out, *_file_route(trained), "--conf", trained.eval_conf)
    assert sorted(p.stem for p in (out / "frames").iterdir()) == [sorted(POSITIONS)[0]]
    assert not (out / "overlays" / f"{gone}.jpg").exists()
    assert not any(p.name.startswith(gone) for p in (out / "crops").iterdir())
    assert {r["frame"] for r in _csv(out)} == {sorted(POSITIONS)[0]}


@pytest.mark.slow  # three screens: about 30 s
def test_a_rerun_after_a_capture_was_removed_equals_a_fresh_screen_of_the_folder(trained, tmp_path):
    """The two P1 captures are one inspection group, registered pooled over both; with one removed, a re-run screens
    the other anew with the group's registration pooled over what is there now, not the one of the first call."""
    flight = p1_flight(trained.tiny, tmp_path / "flight", extras=False)
    out = tmp_path / "out"
    _screen(trained, flight, out, "--conf", trained.eval_conf)
    kept, gone = sorted(POSITIONS)
    assert _frames(out)[kept]["registration"]["frames"] == 2
    for path in flight.glob(f"{gone}_*"):
        path.unlink()
    _screen(trained, flight, out, "--conf", trained.eval_conf)
    _screen(trained, flight, tmp_path / "fresh", "--conf", trained.eval_conf)
    (resumed,), (fresh,) = _frames(out).values(), _frames(tmp_path / "fresh").values()
    for field in ("route", "registration", "registered", "H_rgb_to_aligned", "findings"):
        assert resumed[field] == fresh[field], field
    assert resumed["registered"]["members"] == [kept]


# ------------------------------------------------------------------------------------------------ decoding routes
def _m4t_flight(trained, folder: Path) -> Path:
    """The P1 captures with M4T-like thermal R-JPEGs (their emissivity table asks for DJI's re-mapping, so their
    exact temperatures need DJI's SDK) of the same temperatures."""
    from harness.sensing.pipeline import read_capture_thermal
    from test_sensing_dji_routes import camera_file, remap_table

    flight = p1_flight(trained.tiny, folder, extras=False)
    for thermal in sorted(flight.glob("*_T.JPG")):
        temp, _, _ = read_capture_thermal(thermal)
        camera_file(thermal, temp, remap_table(), model="M4T")
    return flight


def test_screen_takes_the_decoding_options_its_refusals_name_and_labels_approximate_temperatures(trained, tmp_path):
    from harness.commands import options as opt
    from harness.screen.outputs import overlay_legend

    flight = _m4t_flight(trained, tmp_path / "flight")
    text = _screen(trained, flight, tmp_path / "refused", *_file_route(trained), code=1)
    assert "camera 'M4T'" in text and "--converter dji_irp" in text and "--approximate" in text
    assert "--decoder" not in text  # an option of sensing decode only
    assert "nothing was screened: of 2 capture(s), 2 failed" in text
    from harness.cli import get_cli

    screen_cmd, decode_cmd = get_cli().commands["screen"], get_cli().commands["sensing"].commands["decode"]
    for name in ("approximate", "converter", "dji-irp", "converter-timeout"):  # the one declaration, in both
        assert name in opt.shared_options(screen_cmd) and name in opt.shared_options(decode_cmd), name
    text = _screen(
        trained, flight, tmp_path / "bad", *_file_route(trained), "--dji-irp", str(tmp_path / "nope"), code=2
    )
    assert "dji_irp not found" in text and "--dji-irp" in text

    out = tmp_path / "approx"
    text = _screen(trained, flight, out, *_file_route(trained), "--approximate", "--conf", trained.eval_conf)
    manifest = json.loads((out / "manifest.json").read_text())
    temps = manifest["temperatures"]
    bound = temps["bound_c"]  # the route's measured bound for the scene's temperatures
    assert temps["routes"] == {"approximate": 2} and temps["approximate_frames"] == 2 and 0 < bound < 1
    assert manifest["frontend"]["sensing"]["radiometry"]["approximate"] is True
    assert f"approximate temperatures in 2 frame(s): within {bound:g} C" in text
    rows = _csv(out)
    frames = _frames(out)
    for r in rows:  # each frame's own bound, the largest of them in the manifest
        want = frames[r["frame"]]["temperatures"]["temperature_bound_c"]
        assert r["temperature_route"] == "approximate" and float(r["t_bound_c"]) == want <= bound
    geo = json.loads((out / "findings.geojson").read_text())
    assert all(f["properties"]["temperature_route"] == "approximate" for f in geo["features"])
    html = (out / "index.html").read_text()
    assert "approximate temperatures in 2 frame(s)" in html and f"(approximate, &plusmn;{bound:.3f} &deg;C)" in html
    first = json.loads(next((out / "frames").glob("*.json")).read_text())
    assert "approximate" in " ".join(overlay_legend(first["findings"]))

    plain = p1_flight(trained.tiny, tmp_path / "plain", extras=False)
    _screen(trained, plain, tmp_path / "plain_out", *_file_route(trained), "--conf", trained.eval_conf)
    assert {r["temperature_route"] for r in _csv(tmp_path / "plain_out")} == {"blackbody"}
    assert all(r["t_bound_c"] == "" for r in _csv(tmp_path / "plain_out"))


# ------------------------------------------------------------------------------------------------ overlays
def _finding(k: int, box, score: float, **extra) -> dict:
    return {
        "class": "hotspot" if k % 2 else "crack",
        "class_id": k % 2,
        "score": score,
        "box_aligned": box,
        "delta_t": 1.25,
        **extra,
    }


def test_scores_get_the_decimals_they_need():
    from harness.screen.outputs import overlay_legend, score_digits

    assert score_digits([0.87, 0.62]) == 2 and score_digits([0.042, 0.5]) == 3 and score_digits([0.0042]) == 4
    assert score_digits([0.5012, 0.5034]) == 3 and score_digits([0.000012]) == 5 and score_digits([]) == 2
    lines = overlay_legend([_finding(0, [0, 0, 4, 4], 0.0042), _finding(1, [5, 5, 9, 9], 0.0031)])
    assert lines == ["1  crack 0.0042 dT +1.2C", "2  hotspot 0.0031 dT +1.2C"]
    assert not any(" 0.00 " in line for line in lines)


def test_overlay_tags_never_overlap_and_the_legend_lists_every_finding():
    from harness.screen.outputs import overlay, place_labels

    rng = np.random.default_rng(1)
    boxes = []
    for _ in range(60):  # a crowded facade: boxes piled on a few spots
        cx, cy = rng.choice([40, 90, 140]), rng.choice([30, 60])
        x0, y0 = cx + rng.uniform(-6, 6), cy + rng.uniform(-6, 6)
        boxes.append([x0, y0, x0 + rng.uniform(4, 20), y0 + rng.uniform(4, 14)])
    size = (480, 384)
    scaled = [[3 * v for v in b] for b in boxes]
    sizes = [(14 + 6 * (k >= 9), 16) for k in range(len(boxes))]
    places = place_labels(scaled, sizes, size)
    rects = [r for r, _ in places]
    for i, (x, y, w, h) in enumerate(rects):
        assert 0 <= x and 0 <= y and x + w <= size[0] and y + h <= size[1]
        for a, b, c, d in rects[:i]:
            assert x + w <= a or a + c <= x or y + h <= b or b + d <= y, (i, rects[i])
    assert any(leader for _, leader in places)  # the crowded ones are led out
    findings = [_finding(k, b, 0.9 - 0.01 * k) for k, b in enumerate(boxes)]
    rgb = np.zeros((128, 160, 3), np.uint8)
    pic = overlay(rgb, np.full((128, 160), 20.0, np.float32), findings)
    assert pic.shape[1] == 2 * 480 + 6 and pic.shape[0] > 384  # the legend strip below the two panels


def test_wide_images_of_another_size_are_told_once_naming_rgb_camera(trained, tmp_path):
    from screen_helpers import upscaled_flight

    flight = upscaled_flight(trained.tiny, tmp_path / "wide")  # twice the size the run's calibration is for
    text = _screen(trained, flight, tmp_path / "out", *_file_route(trained), code=1)
    assert text.count("RGB size mismatch") == 1, text
    assert "and 1 more wide image(s) of that size: RGB size mismatch: the image is" in text
    assert "give the calibration of the camera that took these images with --rgb-camera FILE" in text
    assert "nothing was screened: of 2 capture(s), 2 failed" in text
    html = (tmp_path / "out" / "index.html").read_text()
    assert html.count("RGB size mismatch") == 1
    assert len(json.loads((tmp_path / "out" / "manifest.json").read_text())["failures"]) == 2  # every file kept
