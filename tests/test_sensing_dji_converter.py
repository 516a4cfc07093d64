"""The converter route: a stand-in for DJI's ``dji_irp`` (written by the test, nothing of DJI's) decodes the files
the harness cannot correct, through ``read_thermal``, ``harness sensing decode`` and a dataset's prepare step; its
arguments, temporary files, failures, time-outs and wrong output sizes are checked."""

from __future__ import annotations

import json
import os
import stat
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED
from harness.errors import ConfigError, DataError
from harness.sensing import dji_converter, jpeg
from harness.sensing import dji_correction as dc
from harness.sensing.radiometry import read_rjpeg, read_thermal, write_rjpeg

CAMERAS = SHARED / "data" / "dji-rjpeg-cameras"
needs_cameras = pytest.mark.skipif(not CAMERAS.is_dir(), reason=f"{CAMERAS} not present")

STANDIN = '''#!{python}
"""A stand-in for DJI's dji_irp: records its arguments, then behaves as STANDIN_MODE says."""
import json, os, subprocess, sys, time
args = sys.argv[1:]
log = os.environ["STANDIN_LOG"]
out = args[args.index("-o") + 1] if "-o" in args else args[-1]
with open(log, "a") as f:
    f.write(json.dumps({{"args": args, "cwd": os.getcwd(), "out": out}}) + "\\n")
mode = os.environ.get("STANDIN_MODE", "ok")
w, h = (int(v) for v in os.environ["STANDIN_SIZE"].split("x"))
if mode == "fail":
    sys.stderr.write("dirp_create_from_rjpeg failed (-2)\\n")
    sys.exit(3)
if mode == "hang":
    subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    time.sleep(60)
n = w * h - (7 if mode == "short" else 0)
values = [20.0 + (i % 97) / 10.0 for i in range(n)]
if mode == "nodata" and values:
    values[0] = -273.15
if mode != "nooutput":
    import struct
    with open(out, "wb") as f:
        f.write(struct.pack("<%df" % n, *values))
'''


def known(w: int, h: int) -> np.ndarray:
    """What the stand-in writes for a ``w`` x ``h`` frame (float32)."""
    return (20.0 + (np.arange(w * h) % 97) / 10.0).astype(np.float32).reshape(h, w)


@pytest.fixture
def standin(tmp_path, monkeypatch):
    """``dji_irp`` on PATH: the stand-in, logging to a file; returns (folder, log path)."""
    folder = tmp_path / "sdk"
    folder.mkdir()
    exe = folder / "dji_irp"
    exe.write_text(STANDIN.format(python=sys.executable))
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ.get('PATH', '')}")
    monkeypatch.setenv("STANDIN_LOG", str(log))
    monkeypatch.setenv("STANDIN_SIZE", "20x16")
    monkeypatch.delenv("STANDIN_MODE", raising=False)
    return folder, log


def calls(log: Path) -> list[dict]:
    return [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []


def builtin_table_file(path: Path, params: dict | None = None, scene: np.ndarray | None = None) -> Path:
    """A camera-layout iirp file whose APP5 says "the camera's built-in table" (as four of five public M2EA files):
    the harness cannot correct it. ``scene``: its temperatures in C (default 30 C everywhere, 20x16)."""
    src = write_rjpeg(
        path.with_name("src_" + path.name),
        np.full((16, 20), 30.0, np.float32) if scene is None else scene,
        params=params or {"emissivity": 0.9, "distance": 7.0, "humidity": 40.0, "reflected": 21.0, "ambient": 21.0},
    ).read_bytes()
    seg = next(s for s in jpeg.read_segments(src).segments if s.marker == jpeg.APP5)
    end = seg.offset + 4 + len(seg.payload)
    path.write_bytes(src[: seg.offset] + jpeg.segment(jpeg.APP5, b"\xff" * (dc.HEADER_BYTES + 0x1C00)) + src[end:])
    return path


def test_dji_irp_on_path_decodes_a_file_the_harness_cannot_correct(standin, tmp_path):
    _, log = standin
    path = builtin_table_file(tmp_path / "m2ea.jpg")
    with pytest.raises(dc.UnsupportedCorrection, match="--converter dji_irp"):
        read_rjpeg(path)
    conv = dji_converter.resolve("dji_irp")
    temp, info = read_thermal(path, converter=conv)
    np.testing.assert_array_equal(temp, known(20, 16))
    assert info["decoder"] == "converter" and info["route"] == "converter: DJI Thermal SDK dji_irp"
    (call,) = calls(log)
    args = call["args"]
    assert args[:4] == ["-s", str(path.resolve()), "-a", "measure"] and args[6:8] == ["--measurefmt", "float32"]
    opts = dict(zip(args[8::2], args[9::2]))
    assert opts == {"--distance": "7", "--humidity": "40", "--emissivity": "0.9", "--reflection": "21"}
    assert info["converter"]["params"] == {
        "emissivity": pytest.approx(0.9),
        "distance": 7.0,
        "humidity": 40.0,
        "reflected": 21.0,
    }
    out_dir = Path(call["out"]).parent
    assert out_dir.name.startswith("harness-convert-") and not out_dir.exists()  # the temporary folder is gone
    # overrides reach the converter
    read_thermal(path, converter=conv, overrides={"emissivity": 0.8})
    assert "0.8" in calls(log)[-1]["args"]


def test_failures_are_clear_errors_naming_the_file_and_leave_no_temporary_files(standin, tmp_path, monkeypatch):
    _, log = standin
    path = builtin_table_file(tmp_path / "f.jpg")
    conv = dji_converter.resolve("dji_irp")

    def fails(mode: str, message: str) -> None:
        monkeypatch.setenv("STANDIN_MODE", mode)
        with pytest.raises(DataError, match=message):
            read_thermal(path, converter=conv)

    fails("fail", r"f\.jpg: the converter \(dji_irp\) failed with exit status 3: dirp_create_from_rjpeg failed")
    fails("short", r"f\.jpg: the converter \(dji_irp\) wrote 1252 bytes, expected 1280 \(20x16 float32")
    fails("nooutput", r"f\.jpg: .*without writing its output")
    monkeypatch.setenv("STANDIN_MODE", "nodata")  # the SDK's "cannot measure" is missing, not -273 C
    temp, info = read_thermal(path, converter=conv)
    assert np.isnan(temp[0, 0]) and info["missing"] == 1
    for call in calls(log):
        assert not Path(call["out"]).parent.exists()


def test_a_hanging_converter_is_stopped_at_its_time_out(standin, tmp_path, monkeypatch):
    _, log = standin
    path = builtin_table_file(tmp_path / "slow.jpg")
    monkeypatch.setenv("STANDIN_MODE", "hang")
    conv = dji_converter.resolve("dji_irp", timeout_s=1.5)
    t0 = time.perf_counter()
    with pytest.raises(DataError, match=r"slow\.jpg: the converter \(dji_irp\) did not finish within 1.5 s"):
        read_thermal(path, converter=conv)
    assert time.perf_counter() - t0 < 15  # stopped, with the process it started (else the pipes would hang)
    assert not Path(calls(log)[0]["out"]).parent.exists()


def test_settings_that_cannot_work_are_config_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no dji_irp anywhere
    with pytest.raises(ConfigError, match="dji_irp is not on PATH.*--dji-irp"):
        dji_converter.resolve("dji_irp")
    with pytest.raises(ConfigError, match=r"not found at .*nowhere"):
        dji_converter.resolve(None, dji_irp=str(tmp_path / "nowhere"))
    with pytest.raises(ConfigError, match=r"\{input\} and \{output\}"):
        dji_converter.resolve("my-tool --in x")
    with pytest.raises(ConfigError, match=r"unknown placeholder \{temp\}"):
        dji_converter.resolve("tool {input} {output} {temp}")
    conv = dji_converter.resolve(f"{tmp_path / 'missing-tool'} {{input}} {{output}}")
    with pytest.raises(ConfigError, match="cannot be started"):
        read_thermal(builtin_table_file(tmp_path / "x.jpg"), converter=conv)


def test_a_command_template_names_any_other_converter(standin, tmp_path):
    folder, log = standin
    path = builtin_table_file(tmp_path / "t.jpg")
    conv = dji_converter.resolve(
        f"{folder / 'dji_irp'} --emissivity={{emissivity}} {{width}}x{{height}} {{input}} {{output}}"
    )
    temp, info = read_thermal(path, converter=conv)
    np.testing.assert_array_equal(temp, known(20, 16))
    args = calls(log)[-1]["args"]
    assert args[:3] == ["--emissivity=0.9", "20x16", str(path.resolve())]
    assert info["route"] == "converter: user command"


def test_decode_command_and_dataset_prepare_use_the_converter(standin, tmp_path, cli_runner):
    from coco_rgbt_helpers import make_coco_rgbt, read_json, write_json
    from harness.cache import prepare
    from harness.config import load_config

    folder, log = standin
    src = builtin_table_file(tmp_path / "flight" / "DJI_0001_T.jpg")
    res = cli_runner(["sensing", "decode", str(src), "--out", str(tmp_path / "out")])
    assert res.exit_code == 1 and "DJI_0001_T.jpg: camera 'M3T'" in res.output and "--converter" in res.output
    res = cli_runner(
        ["sensing", "decode", str(src), "--out", str(tmp_path / "out"), "--unit", "celsius", "--converter", "dji_irp"]
    )
    assert res.exit_code == 0, res.output
    assert "dji_irp" in res.output and "decoded 1 of 1" in res.output
    t, info = read_thermal(tmp_path / "out" / "DJI_0001_T.tif")
    np.testing.assert_array_equal(t, known(20, 16))
    side = json.loads((tmp_path / "out" / "DJI_0001_T.tif.json").read_text())
    assert side["decoder_route"] == "converter" and side["converter"]["converter"] == "dji_irp"
    assert side["decoder"] == "converter: DJI Thermal SDK dji_irp" and "built-in" in side["decoder_note"]

    root = make_coco_rgbt(tmp_path / "coco", n=6)
    coco = read_json(root)
    for k, im in enumerate(coco["images"]):
        builtin_table_file(root / "thermal" / f"{k:03d}.jpg")
        im["thermal_file_name"] = f"thermal/{k:03d}.jpg"
        im["width"], im["height"] = 20, 16
        (root / "rgb" / f"{k:03d}.png").unlink()
        import cv2

        cv2.imwrite(str(root / "rgb" / f"{k:03d}.png"), np.zeros((16, 20, 3), np.uint8))
    coco["annotations"] = [dict(a, bbox=[1.0, 1.0, 5.0, 5.0], area=25.0) for a in coco["annotations"]]
    write_json(root, coco)
    cfg = load_config(protocol="default")
    cfg["dataset"] = {"root": str(root)}
    cfg["sensing"]["radiometry"]["converter"] = "dji_irp"
    cfg["sensing"]["radiometry"]["dji_irp"] = str(folder)
    ds = prepare("coco-rgbt", cfg, cache_root=tmp_path / "cache", progress=False)
    assert len(ds) == 6
    np.testing.assert_array_equal(ds[0].thermal, known(20, 16))
    assert ds[0].meta["thermal_route"] == "converter"
    assert ds.manifest["report"]["converter_temperatures"] == {"samples": 6}


@needs_cameras
def test_hirp_through_the_converter_gets_the_parameters_the_file_states(standin, monkeypatch):
    _, log = standin
    monkeypatch.setenv("STANDIN_SIZE", "640x512")
    conv = dji_converter.resolve("dji_irp")
    temp, info = read_thermal(CAMERAS / "m3td_hirp_a.jpg", converter=conv)
    assert temp.shape == (512, 640) and info["decoder"] == "converter" and info["format_dji"] == "hirp"
    opts = dict(zip(calls(log)[-1]["args"][8::2], calls(log)[-1]["args"][9::2]))
    # what DJI's SDK reports for this file: distance 1 m, humidity 60 %, emissivity 0.95, reflection 21.6 C
    assert opts == {"--distance": "1", "--humidity": "60", "--emissivity": "0.949951", "--reflection": "21.6"}


# ------------------------------------------------------------------------------------------- the converter's unit
WRITES = """
import sys
import numpy as np
out, kind, own = sys.argv[2], sys.argv[3], np.load(sys.argv[4])
t = {"c": own + 2.0, "offset": own + 12.0, "f": own * 1.8 + 32.0}[kind]
t.astype("<f4").tofile(out)
"""


@pytest.mark.parametrize("kind, fahrenheit", [("c", False), ("offset", False), ("f", True)])
def test_a_converter_writing_fahrenheit_is_told_from_the_files_own_reading(tmp_path, kind, fahrenheit):
    """A scene of 5-45 C whose table only a converter applies: the converter's map against the file's own counts
    corrected for emissivity and the reflected temperature. C (2 C off) and a 12 C offset pass; 1.8 x C + 32 is
    refused as Fahrenheit with the numbers."""
    scene = np.linspace(5.0, 45.0, 16 * 20, dtype=np.float32).reshape(16, 20)
    params = {"emissivity": 0.95, "distance": 5.0, "humidity": 50.0, "reflected": 20.0, "ambient": 20.0}
    path = builtin_table_file(tmp_path / "m2ea.jpg", params=params, scene=scene)
    own = read_rjpeg(path, approximate=True)._own_reading({})
    assert abs(float(np.median(own)) - 25.0) < 3.0  # the counts say where the scene is, without the SDK's table
    np.save(tmp_path / "own.npy", own)
    (tmp_path / "writes.py").write_text(WRITES)
    conv = dji_converter.resolve(
        f"{sys.executable} {tmp_path / 'writes.py'} {{input}} {{output}} {kind} {tmp_path}/own.npy"
    )
    if fahrenheit:
        with pytest.raises(DataError, match=r"Fahrenheit, not C") as err:
            read_thermal(path, converter=conv)
        assert "from the file's own reading" in str(err.value) and str(path) in str(err.value)
    else:
        temp, info = read_thermal(path, converter=conv)
        assert info["decoder"] == "converter" and np.isfinite(temp).all()
