"""Radiometric decoding: real M3T R-JPEGs (when the shared samples are present), synthetic R-JPEGs written by the
project, decoded thermal files with sidecars, and clear errors for damaged or foreign files."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from conftest import SHARED
from harness.errors import DataError
from harness.sensing import jpeg
from harness.sensing.radiometry import (
    RJpeg,
    celsius_to_raw14,
    raw14_to_celsius,
    read_rjpeg,
    read_thermal,
    sidecar_path,
    write_rjpeg,
    write_thermal,
)

REAL = SHARED / "data" / "dji-m3t-rjpeg"
REAL_FILES = ["m3t_a", "m3t_b", "m3t_c"]
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} not present")


def _temperature(h=48, w=64, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    return (
        22.0 + 0.1 * xx + 3.0 * np.exp(-((xx - 20) ** 2 + (yy - 15) ** 2) / 30.0) + rng.normal(0, 0.2, (h, w))
    ).astype(np.float32)


# ---------------------------------------------------------------------------------------------- real files
@needs_real
@pytest.mark.parametrize("name", REAL_FILES)
def test_real_rjpeg_reproduces_reference_raw14_exactly(name):
    rj = read_rjpeg(REAL / f"{name}.jpg")
    ref = np.load(REAL / f"{name}_reference.npz")
    assert rj.raw14.dtype == np.uint16 and rj.raw14.shape == (512, 640)
    np.testing.assert_array_equal(rj.raw14, ref["raw14"])
    expected = ref["raw14"].astype(np.float64) / 16.0 - 273.15
    t = rj.blackbody_c()
    assert t.dtype == np.float32
    np.testing.assert_allclose(t, expected, atol=2e-5)
    np.testing.assert_array_equal(read_rjpeg(REAL / f"{name}.jpg", decoder="blackbody").temperature_c, t)


@needs_real
def test_real_rjpeg_parameters_exif_and_preview():
    rj = read_rjpeg(REAL / "m3t_a.jpg")
    assert rj.params == pytest.approx(
        {"ambient": 25.0, "distance": 5.0, "emissivity": 0.95, "humidity": 50.0, "reflected": 25.0}, abs=1e-5
    )
    assert rj.header["format"] == "iirp" and (rj.header["width"], rj.header["height"]) == (640, 512)
    assert rj.exif["Make"] == "DJI" and rj.exif["Model"] == "M3T"
    assert rj.exif["FocalLength"] == pytest.approx(9.1)
    assert rj.exif["DateTimeOriginal"] == "2022:07:23 15:12:19"
    preview = rj.preview()
    assert preview.shape == (512, 640, 3) and preview.dtype == np.uint8
    temp, info = read_thermal(REAL / "m3t_a.jpg")
    assert info["format"] == "rjpeg" and info["decoder"] == "dji" and rj.decoder == "dji"
    np.testing.assert_array_equal(temp, rj.temperature_c)
    temp, info = read_thermal(REAL / "m3t_a.jpg", decoder="blackbody")
    assert info["decoder"] == "blackbody" and info["unit"] == "raw14"
    np.testing.assert_array_equal(temp, rj.blackbody_c())


@needs_real
def test_real_rjpeg_cut_in_the_middle_of_app3_is_a_clear_error(tmp_path):
    data = (REAL / "m3t_b.jpg").read_bytes()
    layout = jpeg.read_segments(data)
    app3 = [s for s in layout.segments if s.marker == jpeg.APP3]
    cut = app3[4].offset + 1000  # inside the fifth APP3 segment
    bad = tmp_path / "cut.jpg"
    bad.write_bytes(data[:cut])
    with pytest.raises(DataError, match=r"cut\.jpg.*truncated"):
        read_rjpeg(bad)
    with pytest.raises(DataError, match="cut.jpg"):
        read_thermal(bad)


# ---------------------------------------------------------------------------------------------- synthetic R-JPEG
def test_synthetic_rjpeg_round_trip_is_exact_to_a_sixteenth_kelvin(tmp_path):
    t = _temperature()
    path = write_rjpeg(
        tmp_path / "synth.jpg",
        t,
        params={"emissivity": 0.9, "distance": 12.0, "humidity": 0.6},
        exif={"DateTimeOriginal": "2024:05:01 10:00:00"},
    )
    rj = read_rjpeg(path)
    assert isinstance(rj, RJpeg)
    np.testing.assert_array_equal(rj.raw14, np.rint((t.astype(np.float64) + 273.15) * 16).astype(np.uint16))
    assert np.abs(rj.temperature_c - t).max() <= 1 / 32 + 1e-5  # half a count of 1/16 K
    assert rj.params["emissivity"] == pytest.approx(0.9, abs=1e-6)
    assert rj.params["distance"] == pytest.approx(12.0)
    assert rj.params["humidity"] == pytest.approx(60.0, abs=1e-4)  # fraction in, percent out
    assert rj.params["reflected"] == pytest.approx(25.0)
    assert rj.exif["Model"] == "M3T" and rj.exif["DateTimeOriginal"] == "2024:05:01 10:00:00"
    assert rj.preview(grayscale=True).shape == t.shape
    # the file follows the camera's layout: APP1, APP3 x N, APP4 (256 B, iirp), APP5, then the picture
    layout = jpeg.read_segments(path.read_bytes())
    markers = [s.marker for s in layout.segments]
    assert markers[0] == jpeg.APP1 and markers.index(jpeg.APP4) > markers.index(jpeg.APP3)
    app4 = layout.payloads(jpeg.APP4)[0]
    assert len(app4) == 256 and app4[:8] == b"\xff\xd2\xd1\xffiirp"
    assert (layout.width, layout.height) == (t.shape[1], t.shape[0])


def test_synthetic_rjpeg_with_a_payload_larger_than_one_segment(tmp_path):
    t = _temperature(300, 400, seed=3)  # 240,000 bytes of raw words -> 4 APP3 segments
    rj = read_rjpeg(write_rjpeg(tmp_path / "big.jpg", t))
    assert len(jpeg.read_segments((tmp_path / "big.jpg").read_bytes()).payloads(jpeg.APP3)) == 4
    np.testing.assert_array_equal(rj.raw14, celsius_to_raw14(t))


def test_raw14_conversions_are_inverse_and_refuse_out_of_range():
    raw = np.array([[0, 4370, 16383]], dtype=np.uint16)
    np.testing.assert_array_equal(celsius_to_raw14(raw14_to_celsius(raw)), raw)
    assert raw14_to_celsius(np.array([4370]))[0] == pytest.approx(4370 / 16 - 273.15, abs=1e-5)
    with pytest.raises(DataError, match="14-bit"):
        celsius_to_raw14(np.array([800.0]))
    with pytest.raises(DataError, match="NaN"):
        celsius_to_raw14(np.array([np.nan]))


@pytest.mark.parametrize("fraction", [0.0001, 0.01, 0.3, 0.6, 0.95, 0.999])
def test_truncated_synthetic_rjpeg_is_a_data_error_naming_the_file(tmp_path, fraction):
    data = write_rjpeg(tmp_path / "ok.jpg", _temperature(300, 400)).read_bytes()
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(DataError, match="bad.jpg"):
        read_rjpeg(bad)


def test_foreign_files_are_refused_with_a_clear_message(tmp_path):
    import cv2

    plain = tmp_path / "plain.jpg"
    ok, enc = cv2.imencode(".jpg", np.full((32, 32, 3), 120, np.uint8))
    plain.write_bytes(enc.tobytes())
    with pytest.raises(DataError, match=r"plain.jpg.*no radiometric payload"):
        read_rjpeg(plain)
    png = tmp_path / "renamed.jpg"
    ok, enc = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    png.write_bytes(enc.tobytes())
    with pytest.raises(DataError, match=r"renamed.jpg.*not a JPEG"):
        read_rjpeg(png)
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    with pytest.raises(DataError, match="empty.jpg"):
        read_rjpeg(empty)
    with pytest.raises(DataError, match="not found"):
        read_rjpeg(tmp_path / "missing.jpg")


def test_payload_of_the_wrong_size_or_layout_is_refused(tmp_path):
    data = bytearray(write_rjpeg(tmp_path / "ok.jpg", _temperature(300, 400)).read_bytes())
    layout = jpeg.read_segments(bytes(data))
    last = [s for s in layout.segments if s.marker == jpeg.APP3][-1]
    # drop the last APP3 segment: the payload no longer fills the frame
    end = last.offset + 4 + len(last.payload)
    short = tmp_path / "short.jpg"
    short.write_bytes(bytes(data[: last.offset]) + bytes(data[end:]))
    with pytest.raises(DataError, match=r"short.jpg.*expected"):
        read_rjpeg(short)
    # set a low bit in a word: not the iirp layout (14-bit counts << 2)
    first = [s for s in layout.segments if s.marker == jpeg.APP3][0]
    data[first.offset + 4] |= 1
    odd = tmp_path / "odd.jpg"
    odd.write_bytes(bytes(data))
    with pytest.raises(DataError, match="low bits"):
        read_rjpeg(odd)


def test_other_dji_formats_are_refused(tmp_path):
    data = bytearray(write_rjpeg(tmp_path / "ok.jpg", _temperature()).read_bytes())
    layout = jpeg.read_segments(bytes(data))
    app4 = [s for s in layout.segments if s.marker == jpeg.APP4][0]
    data[app4.offset + 8 : app4.offset + 12] = b"girp"
    other = tmp_path / "m30t.jpg"
    other.write_bytes(bytes(data))
    with pytest.raises(DataError, match="camera 'M3T', DJI R-JPEG format 'girp': temperatures are not decoded"):
        read_rjpeg(other)


def test_exif_writer_and_reader_agree():
    payload = jpeg.build_exif(
        {
            "Make": "DJI",
            "Model": "M3T",
            "DateTimeOriginal": "2023:01:02 03:04:05",
            "FocalLength": 9.1,
            "FocalLengthIn35mmFilm": 40,
            "ExifImageWidth": 640,
        }
    )
    exif = jpeg.parse_exif(payload)
    assert exif == {
        "Make": "DJI",
        "Model": "M3T",
        "DateTimeOriginal": "2023:01:02 03:04:05",
        "FocalLength": pytest.approx(9.1),
        "FocalLengthIn35mmFilm": 40,
        "ExifImageWidth": 640,
    }
    with pytest.raises(DataError, match="cannot be written"):
        jpeg.build_exif({"NotATag": 1})
    assert jpeg.parse_exif(b"JFIF\x00") == {}
    assert jpeg.parse_exif_datetime("2023:01:02 03:04:05", "25").microsecond == 250000


# ---------------------------------------------------------------------------------------------- decoded files
@pytest.mark.parametrize(
    "unit,suffix,tol",
    [
        ("centikelvin", ".png", 0.005 + 1e-4),
        ("centikelvin", ".tif", 0.005 + 1e-4),
        ("decicelsius", ".tiff", 0.05 + 1e-4),
        ("celsius", ".tif", 0.0),
        ("celsius", ".npy", 0.0),
    ],
)
def test_thermal_files_round_trip_with_their_sidecar(tmp_path, unit, suffix, tol):
    t = _temperature(seed=1)
    path = write_thermal(tmp_path / f"frame{suffix}", t, unit=unit, params={"emissivity": 0.95})
    side = json.loads(sidecar_path(path).read_text())
    assert side["unit"] == unit and side["params"] == {"emissivity": 0.95}
    back, info = read_thermal(path)
    assert back.dtype == np.float32 and back.shape == t.shape
    assert np.abs(back - t).max() <= tol + 1e-6
    assert info["unit"] == unit and info["params"] == {"emissivity": 0.95}


def test_without_sidecar_the_dtype_decides_and_implausible_values_are_refused(tmp_path):
    import cv2
    import tifffile

    t = _temperature(seed=2)
    ck = np.rint((t + 273.15) * 100).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "ck.png"), ck)
    back, info = read_thermal(tmp_path / "ck.png")
    assert info["unit"] == "centikelvin" and np.abs(back - t).max() < 0.006
    tifffile.imwrite(tmp_path / "dc.tif", np.rint(t * 10).astype(np.int16))
    back, info = read_thermal(tmp_path / "dc.tif")
    assert info["unit"] == "decicelsius" and np.abs(back - t).max() < 0.051
    # raw APP3 words (~19,000) read as centi-Kelvin would be -83 C: plausible-looking only with a sidecar
    cv2.imwrite(str(tmp_path / "words.png"), (celsius_to_raw14(t) << 2).astype(np.uint16) * 0 + 1000)
    with pytest.raises(DataError, match=r"words.png.*not plausible; write words.png.json"):
        read_thermal(tmp_path / "words.png")
    (tmp_path / "words.png.json").write_text(json.dumps({"unit": "kelvin", "scale": 0.3, "offset": -273.15}))
    back, _ = read_thermal(tmp_path / "words.png")
    assert back[0, 0] == pytest.approx(1000 * 0.3 - 273.15, abs=1e-4)
    # a sidecar is held to the plausible range too: a scale that gives -173 C everywhere is refused
    (tmp_path / "words.png.json").write_text(json.dumps({"unit": "kelvin", "scale": 0.1, "offset": -273.15}))
    with pytest.raises(DataError, match=r"words.png: the unit of words.png.json \(kelvin\) gives 3072 of 3072 values"):
        read_thermal(tmp_path / "words.png")
    cv2.imwrite(str(tmp_path / "gray8.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(DataError, match=r"gray8.png.*8-bit"):
        read_thermal(tmp_path / "gray8.png")


def test_sidecar_errors_and_unsupported_outputs(tmp_path):
    t = _temperature()
    np.save(tmp_path / "a.npy", t.astype(np.float32))
    (tmp_path / "a.npy.json").write_text(json.dumps({"unit": "rankine"}))
    with pytest.raises(DataError, match="unknown unit 'rankine'"):
        read_thermal(tmp_path / "a.npy")
    # an unrelated a.json (no unit) beside b.npy is not taken for a sidecar
    np.save(tmp_path / "b.npy", t)
    (tmp_path / "b.json").write_text(json.dumps({"annotations": []}))
    assert read_thermal(tmp_path / "b.npy")[1]["unit"] == "celsius"
    with pytest.raises(DataError, match="PNG cannot store int16"):
        write_thermal(tmp_path / "x.png", t, unit="decicelsius")
    with pytest.raises(DataError, match="do not fit"):
        write_thermal(tmp_path / "x.tif", np.full((2, 2), 4000.0), unit="decicelsius")
    with pytest.raises(DataError, match="unsupported thermal file type"):
        read_thermal(tmp_path / "x.bmp")


def test_decode_command_writes_temperature_and_sidecar(tmp_path, cli_runner):
    t = _temperature()
    src = write_rjpeg(tmp_path / "DJI_0001_T.JPG", t)
    res = cli_runner(["sensing", "decode", str(src), "--out", str(tmp_path / "out"), "--preview"])
    assert res.exit_code == 0, res.output
    assert "DJI_0001_T.JPG" in res.output and "emissivity" in res.output
    back, info = read_thermal(tmp_path / "out" / "DJI_0001_T.png")
    assert info["unit"] == "centikelvin" and np.abs(back - t).max() < 1 / 32 + 0.006
    assert (tmp_path / "out" / "DJI_0001_T_ir8.png").exists()
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(src.read_bytes()[:5000])
    res = cli_runner(["sensing", "decode", str(bad), "--out", str(tmp_path / "out")])
    assert res.exit_code == 1 and "bad.jpg" in res.output and "Traceback" not in res.output


def test_app4_offsets_match_the_documented_layout():
    from harness.sensing.radiometry import build_app4, parse_app4

    buf = build_app4({"ambient": 20.0, "reflected": 18.5}, 640, 512)
    assert struct.unpack("<5f", buf[32:52]) == pytest.approx((20.0, 5.0, 0.95, 0.5, 18.5))
    header, params = parse_app4(buf)
    assert header["width"] == 640 and header["height"] == 512 and header["version"] == 0x200
    assert params["reflected"] == pytest.approx(18.5) and params["humidity"] == pytest.approx(50.0)
