"""``harness screen``: a run's detector over raw DJI captures, with the run's own sensing, encoding and model.

One small run is trained per module (the example TinyDet on the tiny synthetic M3T set, fold P1 held out, one
epoch at 64 px, about 5 s); every test screens flights made from the same raw P1 captures.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from report_fixtures import cli, tiny_run
from screen_helpers import POSITIONS, p1_flight, upscaled_flight

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]

REPO = Path(__file__).resolve().parent.parent
REAL = REPO.parent / "shared" / "data" / "dji-m3t-rjpeg"


@dataclass
class Trained:
    run: Path
    homographies: Path  # the prepared dataset's homographies.yaml (one per inspection group)
    tiny: Path
    root: Path

    @property
    def eval_conf(self) -> str:
        return "0.001"


@pytest.fixture(scope="module")
def trained(tiny_source, tmp_path_factory):  # noqa: F811
    root = tmp_path_factory.mktemp("screen")
    with tiny_run(tiny_source, root, "P1", "screen-test") as run:
        yield Trained(run, next((root / "cache" / "m3t-synth").glob("*/homographies.yaml")), tiny_source, root)


def _screen(trained: Trained, flight: Path, out: Path, *extra: str, code: int = 0) -> str:
    return cli(["screen", str(flight), "--run", str(trained.run), "--out", str(out), "--no-progress", *extra], code)


def _file_route(trained: Trained) -> list[str]:
    """The registration the run's data used for P1 (the prepared homographies file, group P1-01)."""
    return ["--homography", str(trained.homographies), "--group", "P1-01"]


@pytest.fixture(scope="module")
def screened(trained, tmp_path_factory):
    """The P1 flight screened at the run's NMS threshold (every detection the run stored is a finding)."""
    flight = p1_flight(trained.tiny, tmp_path_factory.mktemp("flight") / "P1")
    out = tmp_path_factory.mktemp("out") / "screen"
    text = _screen(trained, flight, out, *_file_route(trained), "--conf", trained.eval_conf)
    return flight, out, text


def _frames(out: Path) -> dict[str, dict]:
    return {json.loads(p.read_text())["frame"]: json.loads(p.read_text()) for p in (out / "frames").glob("*.json")}


# ------------------------------------------------------------------------------------------------ flights
def test_captures_pair_by_name_and_other_files_are_ignored(tmp_path):
    from harness.screen import find_captures

    for name in (
        "DJI_20240101120000_0001_W.JPG",
        "DJI_20240101120000_0001_T.JPG",
        "DJI_20240101120000_0001_Z.JPG",
        "DJI_20240101120005_0002_W.jpg",
        "DJI_20240101120005_0002_T.png",
        "DJI_20240101120009_0003_V.MP4",
        "DJI_20240101120012_0004_W.JPG",
        "DJI_20240101120015_0005_T.JPG",
        "notes.txt",
        "sub/DJI_X_0006_W.JPG",
        "sub/DJI_X_0006_T.JPG",
    ):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(b"x")
    flight = find_captures(tmp_path)
    assert [c.name for c in flight.captures] == ["DJI_20240101120000_0001", "DJI_20240101120005_0002", "sub/DJI_X_0006"]
    assert flight.captures[1].thermal.name == "DJI_20240101120005_0002_T.png"
    assert sorted((Path(p).name, r.split(":")[0]) for p, r in flight.bad) == [
        ("DJI_20240101120012_0004_W.JPG", "no thermal partner"),
        ("DJI_20240101120015_0005_T.JPG", "no wide partner"),
    ]
    assert flight.ignored == 3  # the zoom capture, the video, the notes


def test_distort_points_undoes_undistort_points():
    from harness.sensing.calibration import CameraModel, distort_points, undistort_points, undistorted_camera

    cam = CameraModel.ideal(900.0, (1200, 900))
    cam.dist[:2] = (-0.12, 0.05)
    new_cam, _ = undistorted_camera(cam, 0.0)
    pts = np.random.default_rng(0).uniform((50, 40), (1150, 860), (200, 2))
    back = distort_points(undistort_points(pts, cam, new_cam), new_cam, cam)
    assert np.abs(back - pts).max() < 1e-3
    assert distort_points(np.zeros((0, 2)), new_cam, cam).shape == (0, 2)


# ------------------------------------------------------------------------------------------------ no skew
def test_screen_gives_exactly_the_runs_held_out_predictions(trained, screened):
    """Same captures, same model: the boxes and scores of the run's stored P1 predictions, to the last digit."""
    flight, out, text = screened
    stored = json.loads((trained.run / "predictions.json").read_text())
    gt = json.loads((trained.run / "gt.json").read_text())
    image_of = {Path(i["file_name"]).name.replace("_W.JPG", ""): i["id"] for i in gt["images"]}
    frames = _frames(out)
    assert sorted(frames) == sorted(POSITIONS) == sorted(image_of)
    assert "2 frame(s) now" in text
    for name, rec in frames.items():
        want = [(d["category_id"], d["bbox"], d["score"]) for d in stored if d["image_id"] == image_of[name]]
        got = [(f["class_id"] + 1, f["bbox"], f["score"]) for f in rec["findings"]]
        assert want and got == want, name
        assert rec["route"] == "file" and rec["reduction"] == 1
    manifest = json.loads((out / "manifest.json").read_text())
    counts = {"captures": 2, "screened": 2, "with_findings": 2, "failed": 0, "ignored_files": 3}
    assert {k: manifest["frames"][k] for k in counts} == counts


def test_a_default_screen_gives_the_runs_predictions_under_the_screening_route(trained, screened, tmp_path):
    """No option but --run and --out: the group registered automatically, pooled over both captures, and the
    findings exactly the predictions `harness score-route` stored for the run under that route."""
    from harness.screen.route import score_screening_route

    flight, _, _ = screened
    result = score_screening_route(trained.run)
    _screen(trained, flight, tmp_path / "default")
    threshold = json.loads((tmp_path / "default" / "manifest.json").read_text())["model"]["threshold"]
    stored = {f["frame"].split("/")[-1]: (int(i), f) for i, f in result["frames"]["automatic"].items()}
    frames = _frames(tmp_path / "default")
    found = 0
    assert sorted(frames) == sorted(stored) == sorted(POSITIONS)
    for name, rec in frames.items():
        iid, want_frame = stored[name]
        assert rec["route"] == want_frame["route"] == "auto (group G01)"
        assert rec["registration"] == want_frame["registration"] and rec["registration"]["frames"] == 2
        want = sorted(
            (d["category_id"], d["bbox"], d["score"])
            for d in result["predictions"]["automatic"]
            if d["image_id"] == iid and d["score"] >= threshold
        )
        assert sorted((f["class_id"] + 1, f["bbox"], f["score"]) for f in rec["findings"]) == want, name
        found += len(want)
    assert found > 0


def test_the_model_input_is_the_prepared_sample_bit_for_bit(trained, screened):
    """Below the findings: the front end's [R, G, B, C2] and temperature map are the run's prepared samples."""
    from harness.cache import PreparedDataset
    from harness.plugins import get_host
    from harness.screen.flight import find_captures
    from harness.screen.frontend import FrontEnd, FrontEndSettings
    from harness.screen.job import ScreenRequest, load_homography, load_model, resolve_cameras

    flight, _, _ = screened
    req = ScreenRequest(flight=flight, out=trained.root / "unused", run=trained.run)
    sm = load_model(req)
    rgb_cam, th_cam, _ = resolve_cameras(req, sm)
    fe = FrontEnd(
        FrontEndSettings(
            sm.sensing,
            sm.encoding.name,
            sm.encoding_params,
            rgb_cam,
            th_cam,
            load_homography(trained.homographies, "P1-01"),
        ),
        sm.encoding,
    )
    prepared = PreparedDataset(trained.homographies.parent)
    index = {Path(r["meta"]["file_name"]).name: i for i, r in enumerate(prepared.records)}
    enc = get_host().encoding("c2")
    for cap in find_captures(flight).captures:
        frame = fe.process(cap)
        i = index[cap.rgb.name]
        assert np.array_equal(frame.image, np.dstack((prepared.rgb(i), prepared.channel(i, enc, {}))))
        assert np.array_equal(frame.thermal, prepared[i].thermal, equal_nan=True)


def test_the_default_threshold_is_the_runs_operating_point(trained, screened, tmp_path):
    flight, full, _ = screened
    text = _screen(trained, flight, tmp_path / "op", *_file_route(trained))
    op = json.loads((trained.run / "metrics.json").read_text())["metrics"]["conf_threshold"]
    assert f"threshold {op:g}" in text
    for name, rec in _frames(tmp_path / "op").items():
        assert rec["findings"] == [f for f in _frames(full)[name]["findings"] if f["score"] >= op]


# ------------------------------------------------------------------------------------------------ outputs
def _csv(out: Path) -> list[dict[str, str]]:
    with open(out / "findings.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_box_temperatures_are_statistics_of_the_decoded_map(screened):
    """Every finding's min, mean, max, P95 and ring contrast, recomputed on the R-JPEG's own decoded map."""
    from harness.sensing.radiometry import read_thermal

    flight, out, _ = screened
    rows = _csv(out)
    assert rows
    maps = {}
    for row in rows:
        if row["thermal_file"] not in maps:
            maps[row["thermal_file"]] = read_thermal(flight / row["thermal_file"])[0].astype(np.float64)
        t = maps[row["thermal_file"]]
        x0, y0, x1, y1 = (float(row[f"thermal_{k}"]) for k in ("x0", "y0", "x1", "y1"))
        cols = [j for j in range(t.shape[1]) if x0 <= j + 0.5 < x1]
        rws = [i for i in range(t.shape[0]) if y0 <= i + 0.5 < y1]
        inside = t[np.ix_(rws, cols)]
        expect = {
            "t_min": inside.min(),
            "t_mean": inside.mean(),
            "t_max": inside.max(),
            "t_p95": np.percentile(inside, 95),
        }
        r = max(2, math.ceil(0.25 * min(len(rws), len(cols))))
        yy, xx = np.mgrid[0 : t.shape[0], 0 : t.shape[1]]
        near = (yy >= rws[0] - r) & (yy <= rws[-1] + r) & (xx >= cols[0] - r) & (xx <= cols[-1] + r)
        box = (yy >= rws[0]) & (yy <= rws[-1]) & (xx >= cols[0]) & (xx <= cols[-1])
        expect["t_ring"] = np.median(t[near & ~box])
        expect["delta_t"] = expect["t_mean"] - expect["t_ring"]
        for key, value in expect.items():
            assert float(row[key]) == pytest.approx(value, abs=6e-4), (row["frame"], key)


def test_positions_and_outputs_of_a_screen(screened):
    flight, out, _ = screened
    rows = _csv(out)
    for row in rows:
        pos = POSITIONS[row["frame"]]
        assert float(row["lat"]) == pytest.approx(pos["lat"], abs=1e-8)
        assert float(row["gimbal_yaw"]) == pytest.approx(pos["gimbal_yaw"], abs=1e-2)
        assert float(row["alt_abs"]) == pytest.approx(pos["alt_abs"], abs=1e-3)
    geo = json.loads((out / "findings.geojson").read_text())
    assert len(geo["features"]) == len(rows)
    first = geo["features"][0]
    assert first["geometry"]["coordinates"] == pytest.approx(
        [POSITIONS[first["properties"]["frame"]][k] for k in ("lon", "lat", "alt_abs")]
    )
    assert sorted(p.name for p in (out / "overlays").iterdir()) == [f"{n}.jpg" for n in sorted(POSITIONS)]
    html = (out / "index.html").read_text()
    counts = {}
    for row in rows:
        counts[row["class"]] = counts.get(row["class"], 0) + 1
    for cls, n in counts.items():
        assert f"<tr><td>{cls}</td><td class='r'>{n}</td></tr>" in html
    assert "<svg class='map'" in html and "2 captures with GPS" in html
    manifest = json.loads((out / "manifest.json").read_text())
    from harness import __version__
    from harness.screen.frontend import sha1_bytes

    assert manifest["harness_version"] == __version__ and manifest["state"] == "finished"
    assert manifest["model"]["weights_sha1"] == sha1_bytes((Path(manifest["model"]["weights"])).read_bytes())
    assert manifest["model"]["run"]["key"]["fold"] == "P1" and manifest["config"]["meta"]["detector"] == "tinydet"
    for item in manifest["inputs"]:
        assert item["thermal_sha1"] == sha1_bytes((flight / item["thermal"]).read_bytes())
    assert manifest["frontend"]["cameras_from"]["rgb"].startswith("the run's prepared data")


@pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool (Debian libimage-exiftool-perl) not installed")
def test_gps_and_gimbal_equal_what_exiftool_reads(tmp_path):
    """The real M3T files (which carry no XMP: both say nothing), then the same files with DJI XMP written in."""
    from harness.screen import add_xmp, read_position

    files = sorted(REAL.glob("m3t_?.jpg"))
    if len(files) != 3:
        pytest.skip(f"the real M3T files are not at {REAL}")
    values = {
        "lat": -33.86785123,
        "lon": 151.20732411,
        "alt_abs": 58.123,
        "alt_rel": -3.5,
        "gimbal_yaw": -179.9,
        "gimbal_pitch": -90.0,
        "gimbal_roll": 0.1,
        "flight_yaw": 12.34,
    }
    written = []
    for k, f in enumerate(files):
        copy = tmp_path / f"DJI_20220723151219_{k:04d}_T.JPG"
        copy.write_bytes(add_xmp(f.read_bytes(), {**values, "lat": values["lat"] + k * 1e-6}))
        written.append(copy)
    names = {
        "lat": "GPSLatitude",
        "lon": "GPSLongitude",
        "alt_abs": "AbsoluteAltitude",
        "alt_rel": "RelativeAltitude",
        "gimbal_yaw": "GimbalYawDegree",
        "gimbal_pitch": "GimbalPitchDegree",
        "gimbal_roll": "GimbalRollDegree",
        "flight_yaw": "FlightYawDegree",
    }
    proc = subprocess.run(
        ["exiftool", "-j", "-n", "-XMP-drone-dji:all", *map(str, files + written)],
        capture_output=True,
        text=True,
        check=True,
    )
    by_file = {Path(r["SourceFile"]).name: r for r in json.loads(proc.stdout)}
    for path in files + written:
        ours = {k: v for k, v in read_position(path.read_bytes(), str(path)).to_dict().items() if k in names}
        theirs = {k: (float(by_file[path.name][n]) if n in by_file[path.name] else None) for k, n in names.items()}
        assert ours == pytest.approx(theirs, abs=1e-9) if theirs["lat"] is not None else ours == theirs, path.name
    assert all(v is None for v in read_position(files[0].read_bytes()).to_dict().values())


# ------------------------------------------------------------------------------------------------ real flights
def test_bad_files_are_named_and_skipped_and_the_rest_screened(trained, tmp_path):
    flight = p1_flight(trained.tiny, tmp_path / "flight")
    good_t = flight / "DJI_20240512094000_0001_T.JPG"
    (flight / "DJI_20240512094001_0003_W.JPG").write_bytes(b"not a jpeg at all")  # garbage wide image
    shutil.copy(good_t, flight / "DJI_20240512094001_0003_T.JPG")
    shutil.copy(flight / "DJI_20240512094000_0001_W.JPG", flight / "DJI_20240512094002_0004_W.JPG")
    data = good_t.read_bytes()
    (flight / "DJI_20240512094002_0004_T.JPG").write_bytes(data[: len(data) // 3])  # cut R-JPEG
    shutil.copy(flight / "DJI_20240512094000_0001_W.JPG", flight / "DJI_20240512094003_0005_W.JPG")  # no partner
    text = _screen(trained, flight, tmp_path / "out", *_file_route(trained), code=1)
    assert "3 bad file(s), skipped:" in text
    for bad in (
        "DJI_20240512094001_0003_W.JPG: not a JPEG file",
        "DJI_20240512094002_0004_T.JPG: truncated JPEG",
        "DJI_20240512094003_0005_W.JPG: no thermal partner",
    ):
        assert f"{flight}/{bad}" in text, bad
    assert sorted(_frames(tmp_path / "out")) == sorted(POSITIONS)
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["frames"]["screened"] == 2 and len(manifest["failures"]) == 3

    (flight / "DJI_20240512094003_0005_W.JPG").unlink()
    text = _screen(trained, flight, tmp_path / "ff", *_file_route(trained), "--fail-fast", code=2)
    assert "DJI_20240512094001_0003_W.JPG: not a JPEG file" in text and "--fail-fast: stopped" in text
    assert sorted(_frames(tmp_path / "ff")) == ["DJI_20240512094000_0001"]  # the frame before it is kept


def test_a_rerun_skips_frames_done_and_refuses_other_settings(trained, screened, tmp_path):
    flight, _, _ = screened
    out = tmp_path / "again"
    _screen(trained, flight, out, *_file_route(trained))
    text = _screen(trained, flight, out, *_file_route(trained))
    assert "screened 0 frame(s) now, 2 earlier" in text
    changed = tmp_path / "changed"
    shutil.copytree(flight, changed)
    first = changed / "DJI_20240512094000_0001_W.JPG"
    first.write_bytes(first.read_bytes() + b"\x00")  # bytes after the image: a new file, the same picture
    shutil.copytree(out, tmp_path / "again2")
    assert "screened 1 frame(s) now, 1 earlier" in _screen(trained, changed, tmp_path / "again2", *_file_route(trained))
    text = _screen(trained, flight, out, *_file_route(trained), "--conf", "0.5", code=2)
    assert "holds a screen with another model or other settings" in text
    assert "screened 2 frame(s) now" in _screen(trained, flight, out, *_file_route(trained), "--conf", "0.5", "--force")


def test_workers_give_the_same_findings(trained, screened, tmp_path):
    flight, out, _ = screened
    _screen(trained, flight, tmp_path / "two", *_file_route(trained), "--conf", trained.eval_conf, "--workers", "2")
    one, two = _frames(out), _frames(tmp_path / "two")
    assert {n: r["findings"] for n, r in one.items()} == {n: r["findings"] for n, r in two.items()}


def test_the_front_end_beside_the_model_changes_nothing(trained, screened, tmp_path):
    """The front end of the next capture in a thread while the model runs (the default) or before it: the same
    frames, registrations included (the group's second capture waits for the first's). The file route is exact;
    an automatic registration can move in its last digits with what else runs in the process (OpenCV's and
    NumPy's buffers), about 1e-7 of a pixel."""
    from harness.screen import ScreenRequest, screen

    flight, _, _ = screened
    for route in ([trained.homographies, "P1-01"], [None, None]):
        recs = []
        for overlap in (True, False):
            out = tmp_path / f"{route[1]}-{overlap}"
            screen(
                ScreenRequest(
                    flight=flight,
                    out=out,
                    run=trained.run,
                    conf=0.001,
                    progress=False,
                    homography=route[0],
                    group=route[1],
                    overlap=overlap,
                )
            )
            recs.append(_frames(out))
            assert len(recs[-1]) == 2 and all(r["timings"]["model_cpu"] >= 0 for r in recs[-1].values())
            timings = json.loads((out / "manifest.json").read_text())["timings"]
            assert timings["overlapped"] is overlap and timings["frontend_over_model_cpu"] > 0
        a, b = (
            {
                n: {k: v for k, v in r.items() if k not in ("timings", "H_rgb_to_aligned", "registered", "findings")}
                for n, r in x.items()
            }
            for x in recs
        )
        assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)  # NaN != NaN
        for n in recs[0]:
            assert np.allclose(recs[0][n]["H_rgb_to_aligned"], recs[1][n]["H_rgb_to_aligned"], rtol=1e-6, atol=1e-6)
        if route[0] is not None:
            assert [r["findings"] for r in recs[0].values()] == [r["findings"] for r in recs[1].values()]
        else:
            assert [r["route"] for _, r in sorted(recs[0].items())] == ["auto (group G01)", "auto (group G01)"]
            _close(recs[0], recs[1], 1e-4, 0.01)


def test_the_front_end_thread_clocks_its_own_cpu_time():
    """What tells the model's CPU time from the front end's when both run at once."""
    import time

    from harness.screen.job import FrontEndThread

    def spin(seconds: float) -> float:
        t0 = time.thread_time()
        while time.thread_time() - t0 < seconds:
            pass
        return time.thread_time() - t0

    thread = FrontEndThread()
    try:
        if thread.cpu() is None:
            pytest.skip("no per-thread CPU clock on this system")
        c0 = thread.cpu()
        spun = thread.submit(spin, 0.05).result()
        spin(0.05)  # the caller's own CPU time is not the thread's
        assert spun <= thread.cpu() - c0 < spun + 0.04
    finally:
        thread.shutdown()


def test_the_wide_header_is_read_without_a_pass_over_the_picture(tmp_path, monkeypatch):
    """A wide JPEG that ends with its EOI marker: the header from its first bytes, the same segments and size as a
    full read; a cut one is still an error, and trailing data after the picture takes the full read."""
    import cv2

    from harness.errors import DataError
    from harness.screen.frontend import HEADER_BYTES, read_header
    from harness.sensing import jpeg

    rng = np.random.default_rng(0)
    ok, enc = cv2.imencode(".jpg", rng.integers(0, 256, (800, 1000, 3), dtype=np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    exif = jpeg.build_exif({"Make": "DJI", "FocalLengthIn35mmFilm": 24})
    data = b"\xff\xd8" + jpeg.segment(jpeg.APP1, exif) + enc.tobytes()[2:]
    assert len(data) > 2 * HEADER_BYTES
    scanned: list[int] = []
    find_eoi = jpeg._find_eoi
    monkeypatch.setattr(jpeg, "_find_eoi", lambda d, start: scanned.append(len(d) - start) or find_eoi(d, start))
    full = jpeg.read_segments(data, "wide.jpg")
    head = read_header(data, Path("wide.jpg"))
    assert (head.segments, head.width, head.height, head.components) == (
        full.segments,
        full.width,
        full.height,
        full.components,
    ) and (head.width, head.height) == (1000, 800)
    assert scanned[0] > 2 * HEADER_BYTES and scanned[1] < HEADER_BYTES
    with pytest.raises(DataError, match="wide.jpg: truncated JPEG"):
        read_header(data[: len(data) // 2], Path("wide.jpg"))
    assert read_header(data + b"trailer", Path("wide.jpg")).segments == full.segments
    assert scanned[-1] > 2 * HEADER_BYTES


def test_a_rejected_registration_is_listed(trained, tmp_path):
    """The wide image of another project beside a P1 thermal frame: the automatic registration's check fails."""
    flight = tmp_path / "flight"
    flight.mkdir()
    shutil.copy(trained.tiny / "images" / "P1" / "DJI_20240512094000_0001_T.JPG", flight)
    shutil.copy(
        trained.tiny / "images" / "P3" / "DJI_20240721131001_0001_W.JPG", flight / "DJI_20240512094000_0001_W.JPG"
    )
    text = _screen(trained, flight, tmp_path / "prior", "--conf", "0.001")
    assert (
        "registration check failed, screened with the factory prior: DJI_20240512094000_0001 (one frame only, "
        "and its structure correlation" in text
    )
    assert "expected registration error about 2.9 px" in text  # 1.4 % of the 160x128 frame's diagonal
    (rec,) = _frames(tmp_path / "prior").values()
    assert rec["route"] == "prior (automatic registration rejected)" and rec["registration"]["ok"] is False
    assert rec["registration"]["expected_error_px"] == 2.9
    assert all(f["expected_error_px"] == 2.9 for f in rec["findings"]) and rec["findings"]
    with open(tmp_path / "prior" / "findings.csv", newline="") as f:
        assert {row["expected_error_px"] for row in csv.DictReader(f)} == {"2.90"}
    to_check = (tmp_path / "prior" / "index.html").read_text().split("Frames to check")[1]
    assert "DJI_20240512094000_0001" in to_check and "expected registration error about 2.9 px" in to_check
    text = _screen(trained, flight, tmp_path / "skip", "--fallback", "skip", code=1)
    assert "automatic registration rejected" in text and not _frames(tmp_path / "skip")


def test_a_group_registers_once(trained, screened, tmp_path):
    """Both P1 captures are 5 s apart: one inspection group, registered once from the evidence of both."""
    flight, _, _ = screened
    _screen(trained, flight, tmp_path / "group", "--conf", "0.001")
    recs = _frames(tmp_path / "group")
    first, second = (recs[n] for n in sorted(recs))
    for rec in (first, second):
        assert rec["route"] == "auto (group G01)" and rec["registration"]["ok"] is True
        assert rec["registration"]["pooled"] is True and rec["registration"]["frames"] == 2
        assert rec["registered"]["group"] == "G01"
    assert first["registration"] == second["registration"]
    assert np.allclose(np.linalg.inv(first["H_rgb_to_aligned"]) @ second["H_rgb_to_aligned"], np.eye(3), atol=1e-9)
    _screen(trained, flight, tmp_path / "frame", "--conf", "0.001", "--register", "frame")
    assert [r["route"] for _, r in sorted(_frames(tmp_path / "frame").items())] == ["auto", "auto"]


# ------------------------------------------------------------------------------------------------ backends, decoding
def _close(a: dict[str, dict], b: dict[str, dict], score_tol: float, box_tol: float) -> None:
    assert sorted(a) == sorted(b)
    for name in a:
        fa = sorted(a[name]["findings"], key=lambda f: (f["class_id"], f["bbox"]))
        fb = sorted(b[name]["findings"], key=lambda f: (f["class_id"], f["bbox"]))
        assert len(fa) == len(fb), name
        for x, y in zip(fa, fb):
            assert x["class_id"] == y["class_id"]
            assert abs(x["score"] - y["score"]) <= score_tol
            assert np.abs(np.subtract(x["box_aligned"], y["box_aligned"])).max() <= box_tol


def test_onnx_runtime_gives_the_same_findings_as_pytorch(trained, screened, tmp_path):
    """Tolerance (docs/screening.md): scores within 1e-4, boxes within 0.02 px."""
    flight, out, _ = screened
    _screen(trained, flight, tmp_path / "onnx", *_file_route(trained), "--conf", trained.eval_conf, "--backend", "onnx")
    onnx = json.loads((tmp_path / "onnx" / "model.onnx.json").read_text())
    assert onnx["max_abs_diff"] <= 1e-4
    _close(_frames(out), _frames(tmp_path / "onnx"), 1e-4, 0.02)


def test_the_m3t_wide_image_is_decoded_at_a_quarter():
    """The M3T's geometry from its EXIF focal lengths (wide 24 mm at 4000x3000, thermal 40 mm at 640x512): the warp
    shrinks the wide image about 3.6x, so 1/4 (about 0.9 wide pixel per thermal pixel), and 1/8 in its 8000x6000
    mode; a frame the warp shrinks by less than 2.2x (the synthetic profiles: 1.7x) is decoded as shot."""
    from harness.screen.frontend import MIN_SAMPLING, reduction_for, source_scale
    from harness.sensing.registration import focal_prior

    for size, r in (((4000, 3000), 4), ((8000, 6000), 8)):
        f = source_scale(focal_prior(size, (640, 512), (24.0, 40.0)), (640, 512))
        assert reduction_for(f, size) == r and f / r >= MIN_SAMPLING
    assert 3.5 < source_scale(focal_prior((4000, 3000), (640, 512), (24.0, 40.0)), (640, 512)) < 3.8
    assert [reduction_for(f, (480, 360)) for f in (1.0, 1.7, 2.19, 2.2, 3.35)] == [1, 1, 1, 2, 2]
    assert reduction_for(3.6, (4002, 3000)) == 2  # sizes a reduction does not divide


def test_reduced_jpeg_decoding_where_the_warp_shrinks_the_wide_image(trained, screened, tmp_path):
    """Wide images twice the size (the warp shrinks them 3.5x): decoded at 1/2, the findings are those of a full
    decode, and the boxes in the wide image are twice those of the original flight."""
    from harness.screen.frontend import scale_change
    from harness.sensing.calibration import CameraModel
    from harness.sensing.registration import load_homography_entries, save_homographies

    flight = upscaled_flight(trained.tiny, tmp_path / "wide")
    cam = CameraModel.load(trained.tiny / "calibration" / "wide_camera.yaml")
    cam2 = cam.scaled((2 * cam.image_size[0], 2 * cam.image_size[1])).save(tmp_path / "wide_camera.yaml")
    H = load_homography_entries(trained.homographies)["P1-01"].H @ np.linalg.inv(scale_change(2))
    save_homographies(tmp_path / "h.yaml", {"P1-01": H})
    args = ["--homography", str(tmp_path / "h.yaml"), "--rgb-camera", str(cam2), "--conf", trained.eval_conf]
    _screen(trained, flight, tmp_path / "auto", *args)
    _screen(trained, flight, tmp_path / "full", *args, "--rgb-decode", "full")
    reduced, full = _frames(tmp_path / "auto"), _frames(tmp_path / "full")
    assert {r["reduction"] for r in reduced.values()} == {2} and {r["reduction"] for r in full.values()} == {1}
    _close(full, reduced, 1e-3, 0.5)
    original = _frames(screened[1])
    for name in original:
        for f, g in zip(original[name]["findings"][:20], full[name]["findings"][:20]):
            if f["bbox"] == g["bbox"]:
                assert np.allclose(np.multiply(f["box_rgb"], 2), g["box_rgb"], atol=0.6)


def test_reduced_decoding_changes_the_model_input_little(trained, tmp_path):
    from harness.encodings import ENCODINGS
    from harness.screen.flight import find_captures
    from harness.screen.frontend import FrontEnd, FrontEndSettings
    from harness.sensing.calibration import CameraModel

    flight = upscaled_flight(trained.tiny, tmp_path / "wide")
    cam = CameraModel.load(trained.tiny / "calibration" / "wide_camera.yaml")
    cam2 = cam.scaled((2 * cam.image_size[0], 2 * cam.image_size[1])).to_dict()
    c2 = next(e for e in ENCODINGS if e.name == "c2")
    cap = find_captures(flight).captures[0]
    images = [
        FrontEnd(
            FrontEndSettings({"registration": {"method": "focal"}}, "c2", rgb_camera=cam2, rgb_decode=mode), c2
        ).process(cap)
        for mode in ("full", "auto")
    ]
    assert [f.reduction for f in images] == [1, 2]
    a, b = (f.image.astype(np.int16) for f in images)
    assert np.abs(a[..., :3] - b[..., :3]).mean() < 1.2  # grey levels (measured 0.84)
    assert np.array_equal(a[..., 3], b[..., 3])  # the temperature map is never touched


def test_screening_with_a_weights_file(trained, screened, tmp_path):
    """``--weights`` with the detector and dataset: the run's findings again when configured like the run."""
    flight, out, _ = screened
    sets = [a for s in ["protocol.imgsz=64", "eval.batch=16"] for a in ("--set", s)]
    cli(
        [
            "screen",
            str(flight),
            "--weights",
            str(trained.run / "checkpoints" / "best.pt"),
            "--detector",
            "tinydet",
            "--dataset",
            "m3t-synth",
            *sets,
            "--out",
            str(tmp_path / "w"),
            "--no-progress",
            *_file_route(trained),
            "--rgb-camera",
            str(trained.tiny / "calibration" / "wide_camera.yaml"),
            "--conf",
            trained.eval_conf,
        ]
    )
    _close(_frames(out), _frames(tmp_path / "w"), 0.0, 0.0)
    text = cli(
        [
            "screen",
            str(flight),
            "--weights",
            str(trained.run / "checkpoints" / "best.pt"),
            "--out",
            str(tmp_path / "x"),
        ],
        code=2,
    )
    assert "--weights needs --detector NAME and --dataset NAME" in text
