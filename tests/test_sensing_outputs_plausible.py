"""What ``harness sensing decode`` writes: missing pixels stay missing (nodata, counted) instead of failing the file,
a converter's values are held to the plausible temperature range, sidecars are strict JSON and state only what the
file states, and a thermal JPEG of another make found in a flight folder is not passed over."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from conftest import SHARED
from harness.errors import DataError
from harness.sensing import jpeg
from harness.sensing.radiometry import read_thermal, sidecar_path, write_rjpeg, write_thermal
from test_sensing_dji_converter import builtin_table_file
from test_sensing_dji_routes import camera_file, remap_table, xts_file

REAL = SHARED / "data" / "dji-m3t-rjpeg" / "m3t_a.jpg"

CONVERTER = """
import os, sys
import numpy as np
out, w, h = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
t = (20.0 + (np.arange(w * h) % 97) / 10.0).astype("<f4")
for k, v in enumerate(os.environ.get("CONVERTER_SPECIAL", "").split(",")):
    if v:
        t[k * 7] = float(v)
if os.environ.get("CONVERTER_ADD"):
    t += float(os.environ["CONVERTER_ADD"])
if os.environ.get("CONVERTER_ALL"):
    t[:] = float(os.environ["CONVERTER_ALL"])
t.tofile(out)
"""


def strict_json(path):
    """The file's JSON, refusing NaN and Infinity (not JSON)."""

    def refuse(name):
        raise ValueError(f"{path}: {name} is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.fixture
def converter(tmp_path):
    script = tmp_path / "conv.py"
    script.write_text(CONVERTER)
    return f"{sys.executable} {script} {{input}} {{output}} {{width}} {{height}}"


def _decode(cli_runner, *args):
    return cli_runner(["sensing", "decode", *map(str, args), "--no-progress"])


@pytest.mark.parametrize("special", ["nan", "inf", "-273.5", "nan,inf,-273.5"])
@pytest.mark.parametrize("unit", ["centikelvin", "decicelsius", "celsius"])
def test_a_converter_pixel_it_cannot_measure_stays_missing_and_the_file_is_written(
    tmp_path, cli_runner, converter, monkeypatch, special, unit
):
    src = builtin_table_file(tmp_path / "m2ea.jpg")
    monkeypatch.setenv("CONVERTER_SPECIAL", special)
    res = _decode(cli_runner, src, "--out", tmp_path / "out", "--converter", converter, "--unit", unit)
    assert res.exit_code == 0, res.output
    (written,) = [p for p in (tmp_path / "out").iterdir() if not p.name.endswith(".json")]
    side = strict_json(sidecar_path(written))
    n = len(special.split(","))
    assert side["missing"] == n and side.get("nodata") == {"centikelvin": 0, "decicelsius": -32768}.get(unit)
    t, info = read_thermal(written)
    assert info["missing"] == n and int(np.isnan(t).sum()) == n
    assert all(np.isnan(t.ravel()[k * 7]) for k in range(n))
    expected = (20.0 + (np.arange(t.size) % 97) / 10.0).reshape(t.shape)
    ok = np.isfinite(t)
    np.testing.assert_allclose(t[ok], expected[ok], atol=0.006)


def test_one_pixel_above_the_approximate_range_is_missing_not_a_lost_file(tmp_path, cli_runner):
    temps = np.full((16, 20), 25.0, np.float32)
    temps[3, 4] = 700.0  # far above what the approximation was measured for
    (tmp_path / "in").mkdir()
    src = camera_file(tmp_path / "in" / "m4t.jpg", temps, remap_table(), model="M4T")
    res = _decode(cli_runner, src, "--out", tmp_path / "out", "--approximate")
    assert res.exit_code == 0, res.output
    side = strict_json(tmp_path / "out" / "m4t.png.json")
    assert side["missing"] == 1 and side["nodata"] == 0
    t, _ = read_thermal(tmp_path / "out" / "m4t.png")
    assert np.isnan(t[3, 4]) and int(np.isnan(t).sum()) == 1


def test_write_thermal_still_refuses_a_map_with_nothing_valid(tmp_path):
    with pytest.raises(DataError, match=r"t\.png.*no valid temperature"):
        write_thermal(tmp_path / "t.png", np.full((4, 4), np.nan))


def test_a_converter_value_outside_the_plausible_range_is_missing_and_a_wrong_unit_is_refused(
    tmp_path, cli_runner, converter, monkeypatch
):
    src = builtin_table_file(tmp_path / "m2ea.jpg")
    monkeypatch.setenv("CONVERTER_SPECIAL", "1e30,-150")
    res = _decode(
        cli_runner, src, "--out", tmp_path / "a", "--converter", converter, "--unit", "celsius", "--file-type", "npy"
    )
    assert res.exit_code == 0, res.output
    side = strict_json(tmp_path / "a" / "m2ea.npy.json")
    assert side["missing"] == 2 and side["converter"]["implausible"] == 2
    t = np.load(tmp_path / "a" / "m2ea.npy")
    assert np.isnan(t.ravel()[0]) and np.isnan(t.ravel()[7]) and np.nanmax(t) < 100
    monkeypatch.delenv("CONVERTER_SPECIAL")
    monkeypatch.setenv("CONVERTER_ALL", "1e30")
    res = _decode(
        cli_runner, src, "--out", tmp_path / "b", "--converter", converter, "--unit", "celsius", "--file-type", "npy"
    )
    assert res.exit_code == 1, res.output
    assert (
        "m2ea.jpg" in res.output
        and "the converter (command) gives 320 of 320 values outside the plausible -100..800 C (from 1e+30 to 1e+30 C)"
        in res.output
    )
    assert not (tmp_path / "b" / "m2ea.npy").exists()


def test_a_sidecar_unit_that_makes_values_implausible_is_refused(tmp_path):
    path = tmp_path / "t.npy"
    np.save(path, np.full((8, 8), 30000.0, np.float32))
    sidecar_path(path).write_text(json.dumps({"unit": "celsius"}))
    with pytest.raises(DataError, match=r"t\.npy: the unit of t\.npy\.json \(celsius\) gives 64 of 64 values outside"):
        read_thermal(path)


def test_an_xt_s_sidecar_states_no_parameters_read_from_its_raw_words(tmp_path, cli_runner, converter):
    (tmp_path / "in").mkdir()
    xts_file(tmp_path / "in" / "xts.jpg", eoi=True)
    res = _decode(cli_runner, tmp_path / "in" / "xts.jpg", "--out", tmp_path / "out", "--converter", converter)
    assert res.exit_code == 0, res.output
    side = strict_json(tmp_path / "out" / "xts.png.json")
    assert side["params"] == {}  # the file states none; its APP4 holds raw words, not five float32 parameters
    assert "-" in res.output.splitlines()[2].split()[-3:-1]  # emissivity and distance shown as unknown


def _flir_jpeg(path):
    import cv2

    ok, pic = cv2.imencode(".jpg", np.zeros((12, 16, 3), np.uint8))
    exif = jpeg.segment(jpeg.APP1, jpeg.build_exif({"Make": "FLIR Systems AB", "Model": "FLIR E8"}))
    flir = jpeg.segment(jpeg.APP1, b"FLIR\x00\x01\x01\x0b" + b"FFF\x00" + bytes(120))
    path.write_bytes(b"\xff\xd8" + exif + flir + pic.tobytes()[2:])


def test_a_flir_file_in_a_dji_flight_folder_fails_naming_its_camera(tmp_path, cli_runner):
    folder = tmp_path / "flight"
    folder.mkdir()
    write_rjpeg(folder / "DJI_0001_T.JPG", np.full((8, 8), 20.0, np.float32))
    _flir_jpeg(folder / "FLIR0001.jpg")
    import cv2

    ok, visible = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    (folder / "DJI_0001_V.JPG").write_bytes(visible.tobytes())
    res = _decode(cli_runner, folder, "--out", tmp_path / "out")
    assert res.exit_code == 1, res.output
    assert "decoded 1 of 2 file(s); 1 JPEG(s) without a radiometric payload passed over; 1 failed" in res.output
    assert "FLIR0001.jpg" in res.output and "camera 'FLIR E8'" in res.output


def test_a_file_of_only_the_start_marker_says_it_is_cut_short(tmp_path):
    path = tmp_path / "two.jpg"
    path.write_bytes(b"\xff\xd8")
    with pytest.raises(DataError) as err:
        jpeg.read_segments(path.read_bytes(), path)
    text = str(err.value)
    assert "expected ff d8" not in text and "only 2 bytes (ff d8)" in text and "two.jpg" in text


@pytest.mark.skipif(not REAL.is_file(), reason=f"{REAL} not present")
def test_a_real_iirp_sidecar_is_strict_json(tmp_path, cli_runner):
    res = _decode(cli_runner, REAL, "--out", tmp_path)
    assert res.exit_code == 0, res.output
    side = strict_json(tmp_path / "m3t_a.png.json")
    assert side["correction"]["valid_up_to_c"] is None and "missing" not in side


def test_a_converter_writing_kelvin_is_refused_against_the_files_own_counts(
    tmp_path, cli_runner, converter, monkeypatch
):
    src = builtin_table_file(tmp_path / "m2ea.jpg")  # its blackbody reading is 30 C
    monkeypatch.setenv("CONVERTER_ADD", "273.15")
    res = _decode(cli_runner, src, "--out", tmp_path / "k", "--converter", converter)
    assert res.exit_code == 1, res.output
    text = " ".join(res.output.split())
    assert "m2ea.jpg" in text and "above the file's own blackbody reading: Kelvin, not C" in text
