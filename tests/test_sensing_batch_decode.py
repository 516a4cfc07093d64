"""Batch decoding of a flight: every readable R-JPEG decoded, failures listed by name, exact sidecar parameters."""

from __future__ import annotations

import json
import shutil
import struct

import numpy as np
import pytest

from conftest import SHARED
from harness.sensing import jpeg
from harness.sensing.batch import DecodeOptions, decode_batch, exact_params
from harness.sensing.radiometry import read_thermal, sidecar_path, write_rjpeg

REAL = SHARED / "data" / "dji-m3t-rjpeg" / "m3t_a.jpg"


def _temperature(h=24, w=32, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (25.0 + rng.normal(0, 0.5, (h, w))).astype(np.float32)


@pytest.fixture
def flight(tmp_path):
    """A folder of 100 good R-JPEGs with 3 bad ones among them (sorted in the middle), and a visible JPEG."""
    folder = tmp_path / "flight"
    folder.mkdir()
    good = write_rjpeg(tmp_path / "template.jpg", _temperature(), params={"emissivity": 0.93, "humidity": 55})
    for i in range(100):
        shutil.copyfile(good, folder / f"DJI_{i:04d}_T.JPG")
    data = good.read_bytes()
    (folder / "DJI_0049_T_cut.JPG").write_bytes(data[: len(data) // 2])  # cut inside the radiometric payload
    (folder / "DJI_0050_T_noise.JPG").write_bytes(b"\x00not a jpeg at all" * 10)
    (folder / "DJI_0051_T_empty.JPG").write_bytes(b"")
    import cv2

    ok, visible = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    (folder / "DJI_0052_V.JPG").write_bytes(visible.tobytes())  # the visible camera's picture: passed over
    (folder / "notes.txt").write_text("not an image")
    return folder


def test_a_flight_with_three_bad_files_decodes_the_other_hundred_and_names_the_failures(flight, tmp_path, cli_runner):
    out = tmp_path / "out"
    res = cli_runner(["sensing", "decode", str(flight), "--out", str(out), "--workers", "2"])
    assert res.exit_code == 1, res.output
    written = sorted(p.name for p in out.glob("*.png"))
    assert len(written) == 100 and written[0] == "DJI_0000_T.png" and written[-1] == "DJI_0099_T.png"
    assert len(list(out.glob("*.png.json"))) == 100
    assert not list(out.glob(".*"))  # no temporary file left behind
    tail = res.stdout[res.stdout.index("decoded 100 of 103 file(s)") :]
    assert "partly done: 3 of 103 file(s) could not be decoded" in res.stderr
    assert "1 JPEG(s) without a radiometric payload passed over; 3 failed:" in tail
    lines = tail.splitlines()[1:]
    assert len(lines) == 3
    assert [ln.split(": ")[0].strip().rsplit("/", 1)[-1] for ln in lines] == [
        "DJI_0049_T_cut.JPG",
        "DJI_0050_T_noise.JPG",
        "DJI_0051_T_empty.JPG",
    ]
    assert all(len(ln.split(": ", 1)[1]) > 5 for ln in lines)  # each with its reason
    assert "Traceback" not in res.output


def test_fail_fast_stops_at_the_first_bad_file(flight, tmp_path, cli_runner):
    out = tmp_path / "out"
    res = cli_runner(["sensing", "decode", str(flight), "--out", str(out), "--fail-fast"])
    assert res.exit_code == 2 and "DJI_0049_T_cut.JPG" in res.output
    assert len(list(out.glob("*.png"))) == 50  # DJI_0000 .. DJI_0049, each whole; none after it


def test_folders_keep_their_layout_and_files_given_directly_go_to_the_top(tmp_path):
    src = write_rjpeg(tmp_path / "a.jpg", _temperature())
    for flight in ("f1", "f2/sub"):
        (tmp_path / "in" / flight).mkdir(parents=True)
        shutil.copyfile(src, tmp_path / "in" / flight / "DJI_0001_T.JPG")
    seen = []
    res = decode_batch(
        [tmp_path / "in", src, tmp_path / "missing.jpg"],
        tmp_path / "out",
        DecodeOptions(unit="celsius"),
        progress=lambda done, total: seen.append((done, total)),
    )
    assert sorted(str(p.relative_to(tmp_path / "out")) for p in (tmp_path / "out").rglob("*.tif")) == [
        "a.tif",
        "f1/DJI_0001_T.tif",
        "f2/sub/DJI_0001_T.tif",
    ]
    assert res.failed == [(str(tmp_path / "missing.jpg"), "file not found")]
    assert seen[-1] == (3, 3)
    back, _ = read_thermal(tmp_path / "out" / "a.tif")
    assert np.abs(back - _temperature()).max() < 1 / 32 + 1e-4


def test_sidecar_records_the_measurement_parameters_exactly(tmp_path):
    src = write_rjpeg(
        tmp_path / "p.jpg",
        _temperature(),
        params={"emissivity": 0.9312345, "distance": 7.123456789, "humidity": 0.4321987, "reflected": 23.456789},
    )
    decode_batch([src], tmp_path / "out")
    side = json.loads(sidecar_path(tmp_path / "out" / "p.png").read_text())
    layout = jpeg.read_segments(src.read_bytes(), src)
    stored = struct.unpack("<5f", layout.payloads(jpeg.APP4)[0][32:52])
    names = ["ambient", "distance", "emissivity", "humidity", "reflected"]
    for name, value in zip(names, stored):
        got = side["params"][name] / (100 if name == "humidity" else 1)
        assert np.float32(got) == np.float32(value), name  # reads back to the very float32 the file stores
    assert side["params"]["emissivity"] == 0.9312345  # not rounded to six decimals (0.931234)
    assert side["params"]["humidity"] == pytest.approx(43.21987, abs=1e-5)


@pytest.mark.skipif(not REAL.exists(), reason=f"{REAL} not present")
def test_a_real_m3t_file_decodes_by_the_corrected_route_with_its_exact_parameters(tmp_path):
    res = decode_batch([REAL], tmp_path / "out")
    assert res.ok and res.decoded[0]["route"] == "dji"
    side = json.loads(sidecar_path(tmp_path / "out" / "m3t_a.png").read_text())
    assert side["params"] == exact_params(REAL.read_bytes(), REAL)
