"""No silent route: files the harness cannot correct are refused by default (naming camera, format and both
options), the labelled approximate route keeps to its measured bound and says so in every output, one impossible
file does not stop a flight, and the smaller gaps (XT S, 1280x1024 M30T, a folder named like a file) are closed."""

from __future__ import annotations

import json
import re
import struct

import numpy as np
import pytest

from conftest import SHARED
from harness.errors import DataError
from harness.sensing import dji_approximate, dji_formats, jpeg
from harness.sensing import dji_correction as dc
from harness.sensing.batch import DecodeOptions, decode_batch, format_failures
from harness.sensing.radiometry import read_rjpeg, read_thermal, write_rjpeg
from test_sensing_dji_correction import _table, _with_app5

CAMERAS = SHARED / "data" / "dji-rjpeg-cameras"
needs_cameras = pytest.mark.skipif(not CAMERAS.is_dir(), reason=f"{CAMERAS} not present")


def camera_file(path, temps, app5: bytes, model: str = "M3T", **params):
    """A camera-layout iirp R-JPEG of ``temps`` (blackbody) with the given APP5 payload."""
    p = {"emissivity": 0.95, "distance": 5.0, "humidity": 50.0, "reflected": 25.0, "ambient": 25.0, **params}
    work = path.parent.parent / f"w_{path.parent.name}_{path.name}"  # outside the folder a batch searches
    src = write_rjpeg(work, np.asarray(temps, np.float32), params=p, exif={"Model": model}).read_bytes()
    path.write_bytes(_with_app5(src, app5))
    return path


def remap_table() -> bytes:
    """A table whose header asks for DJI's emissivity re-mapping (as the M4T's and H30T's do)."""
    data = bytearray(_table(fill=15800))
    struct.pack_into("<H", data, 8, 1)  # w[4]: the emissivity-table flag
    return bytes(data)


BUILTIN = b"\xff" * (dc.HEADER_BYTES + dc.OLD_TABLE_BYTES)  # "the camera's built-in default table"


# ---------------------------------------------------------------------------------------------- the M4T file
@needs_cameras
def test_m4t_approximate_route_is_labelled_and_within_its_measured_bound():
    ref = np.load(CAMERAS / "m4t_iirp_reference.npz")["temp_c"]
    temp, info = read_thermal(CAMERAS / "m4t_iirp.jpg", approximate=True)
    rec = info["approximate"]
    assert info["decoder"] == "approximate" and rec["label"] == "approximate temperatures"
    assert rec["approximation"] == "emissivity-remap-skipped" and rec["bound_c"] == 0.009  # scene below 30 C
    assert "approximate temperatures (within 0.009 C" in info["route"]
    assert np.abs(temp.astype(np.float64) - ref).max() <= rec["bound_c"]


@needs_cameras
def test_c2_from_approximate_temperatures_is_within_one_grey_level_of_c2_from_the_sdk():
    from harness.sensing.c2 import c2_uint8

    ref = np.load(CAMERAS / "m4t_iirp_reference.npz")["temp_c"]
    temp, _ = read_thermal(CAMERAS / "m4t_iirp.jpg", approximate=True)
    d = np.abs(c2_uint8(temp).astype(int) - c2_uint8(ref).astype(int))
    assert (d <= 1).mean() >= 0.999


@needs_cameras
@pytest.mark.parametrize("name", ["m3td_hirp_a", "m3td_hirp_b", "m3td_hirp_c"])
def test_hirp_has_no_approximate_route_and_says_why(name):
    refused = rf"{name}\.jpg: camera 'M3TD'.*'hirp'.*--converter dji_irp.*no approximate route"
    with pytest.raises(dji_formats.UnsupportedFormat, match=refused):
        read_thermal(CAMERAS / f"{name}.jpg", approximate=True)


# ---------------------------------------------------------------------------------------------- approximate
def test_remapping_tables_are_refused_by_default_and_approximate_on_request(tmp_path):
    path = camera_file(tmp_path / "m4t_like.jpg", np.full((12, 16), 20.0), remap_table(), model="M4T")
    with pytest.raises(
        dc.UnsupportedCorrection,
        match=r"m4t_like\.jpg: camera 'M4T', DJI R-JPEG format 'iirp' "
        r"\(APP4 format version 0x200\).*re-mapping.*--converter "
        r"dji_irp.*--approximate.*measured within 3.2 C",
    ):
        read_thermal(path)
    temp, info = read_thermal(path, approximate=True)
    skipped = dc.parse_app5(remap_table(), 0x200, skip_emissivity_remap=True)
    exact = dc.correct_raw14(read_rjpeg(path, decoder="blackbody").raw14, skipped, 0.95, 5.0, 50.0, 25.0, 25.0)
    np.testing.assert_array_equal(temp, exact)  # DJI's correction with the file's own table, re-mapping left out
    assert info["approximate"]["bound_c"] == 0.009 and info["correction"]["approximation"] == "emissivity-remap-skipped"
    with pytest.raises(
        DataError,
        match=r"m4t_like\.jpg: the approximate route .* measured for emissivity "
        r"0.6-0.98 only; emissivity 0.3",
    ):
        read_thermal(path, approximate=True, overrides={"emissivity": 0.3})


def test_builtin_tables_approximate_with_the_balance_the_file_allows_and_hot_pixels_go_missing(tmp_path):
    t = np.full((12, 16), 40.0, np.float32)
    t[0, 0] = 90.0  # above the measured range (63 C)
    path = camera_file(
        tmp_path / "m2ea_like.jpg", t, BUILTIN, model="MAVIC2-ENTERPRISE-ADVANCED", emissivity=0.9, reflected=20.0
    )
    temp, info = read_thermal(path, approximate=True)
    w = lambda c: (c + 273.15) ** 4  # noqa: E731
    t0 = read_rjpeg(path, decoder="blackbody").blackbody_c().astype(np.float64)
    expected = ((w(t0) - 0.1 * w(20.0)) / 0.9) ** 0.25 - 273.15  # emissivity and reflection, transmission 1
    assert np.isnan(temp[0, 0]) and info["missing"] == 1 and info["approximate"]["missing_above_range"] == 1
    assert np.abs(temp[1:, 1:] - expected[1:, 1:]).max() < 1e-3
    assert info["approximate"]["bound_c"] == 4.4 and info["approximate"]["approximation"] == "builtin-tau-unity"


def test_decode_command_labels_approximate_files_in_the_table_and_the_sidecar(tmp_path, cli_runner):
    path = camera_file(tmp_path / "a.jpg", np.full((12, 16), 20.0), remap_table(), model="M4T")
    res = cli_runner(["sensing", "decode", str(path), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1 and "camera 'M4T'" in res.output and "--approximate" in res.output
    assert not (tmp_path / "o" / "a.png").exists()
    res = cli_runner(["sensing", "decode", str(path), "--out", str(tmp_path / "o"), "--approximate"])
    assert res.exit_code == 0, res.output
    assert "approx. +-0.009 C" in res.output and "1 with approximate temperatures" in res.output
    side = json.loads((tmp_path / "o" / "a.png.json").read_text())
    assert side["temperatures"] == "approximate temperatures" and side["approximate"]["bound_c"] == 0.009
    assert side["decoder_route"] == "approximate" and side["decoder"].startswith("approximate: approximate tem")
    from harness.sensing.radiometry import route_meta

    _, info = read_thermal(tmp_path / "o" / "a.png")  # read back (as a dataset would): still labelled
    assert route_meta(info) == {
        "thermal_route": "approximate",
        "temperatures": "approximate temperatures",
        "temperature_bound_c": 0.009,
        "approximation": "emissivity-remap-skipped",
    }


# ---------------------------------------------------------------------------------------------- batches
def test_an_impossible_emissivity_fails_that_file_only(tmp_path, cli_runner):
    flight = tmp_path / "flight"
    flight.mkdir()
    for k in range(3):
        camera_file(flight / f"DJI_{k:04d}_T.jpg", np.full((12, 16), 30.0 + k), _table(fill=15000))
    camera_file(flight / "DJI_0009_T.jpg", np.full((12, 16), 30.0), _table(fill=15000), emissivity=0.0)
    res = cli_runner(["sensing", "decode", str(flight), "--out", str(tmp_path / "out")])
    assert res.exit_code == 1, res.output
    assert "decoded 3 of 4 file(s); 1 failed" in res.output
    assert "DJI_0009_T.jpg: APP4 measurement parameter emissivity=0.0 is outside 0.0001..1" in res.output
    assert sorted(p.name for p in (tmp_path / "out").glob("*.png")) == [f"DJI_{k:04d}_T.png" for k in range(3)]
    assert "Traceback" not in res.output
    # an override of the impossible value decodes it
    res = cli_runner(
        ["sensing", "decode", str(flight / "DJI_0009_T.jpg"), "--out", str(tmp_path / "o2"), "--emissivity", "0.9"]
    )
    assert res.exit_code == 0, res.output


def test_a_folder_named_like_a_file_or_holding_no_rjpeg_is_not_a_success(tmp_path, cli_runner):
    odd = tmp_path / "x.jpg"
    odd.mkdir()
    res = cli_runner(["sensing", "decode", str(odd), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1
    assert "x.jpg: a folder without any .jpg/.jpeg file" in res.output
    result = decode_batch([], tmp_path / "o2", DecodeOptions())
    assert not result.ok and "nothing to decode" in format_failures(result)


# ---------------------------------------------------------------------------------------------- smaller gaps
def test_original_raw_of_a_1280x1024_picture_with_a_640x512_frame(tmp_path):
    import cv2

    t = (20.0 + np.arange(48 * 64).reshape(48, 64) / 1000).astype(np.float32)
    small = write_rjpeg(tmp_path / "s.jpg", t, exif={"Model": "M30T"}).read_bytes()
    layout = jpeg.read_segments(small)
    app5 = next(s for s in layout.segments if s.marker == jpeg.APP5)
    head = small[: app5.offset + 4 + len(app5.payload)]
    ok, big = cv2.imencode(".jpg", np.zeros((96, 128, 3), np.uint8))  # the super-resolution picture, twice the size
    path = tmp_path / "m30t_uhr.jpg"
    path.write_bytes(head + big.tobytes()[2:])
    assert jpeg.read_segments(path.read_bytes()).width == 128
    fmt, model, raw = dji_formats.read_original_raw(path)
    assert (fmt, model, raw.shape) == ("iirp", "M30T", (48, 64))
    np.testing.assert_array_equal(raw, read_rjpeg(path).raw14)


def xts_file(path, eoi: bool) -> bytes:
    """An XT S-like file: EXIF model 'XT S', 'Plug' block in APP2, curve in APP3, raw words in APP4; the picture
    ends without an EOI marker when ``eoi`` is false (as two public XT S files do)."""
    import cv2

    words = (5000 + np.arange(16 * 12) % 300).astype("<u2")
    ok, pic = cv2.imencode(".jpg", np.zeros((12, 16, 3), np.uint8))
    body = pic.tobytes()[2:]
    if not eoi:
        body = body[:-2]
    data = (
        b"\xff\xd8"
        + jpeg.segment(jpeg.APP1, jpeg.build_exif({"Make": "DJI", "Model": "XT S"}))
        + jpeg.segment(jpeg.APP2, b"Plug" + bytes(60))
        + jpeg.segment(jpeg.APP3, bytes(256))
        + jpeg.segment(jpeg.APP4, words.tobytes())
        + body
    )
    path.write_bytes(data)
    return words.reshape(12, 16)


def test_xt_s_files_are_refused_naming_camera_and_format_even_without_an_end_marker(tmp_path):
    for eoi in (True, False):
        path = tmp_path / f"xts_{eoi}.jpg"
        words = xts_file(path, eoi)
        with pytest.raises(
            dji_formats.UnsupportedFormat,
            match=r"camera 'XT S', DJI R-JPEG format 'dirp-g'.*"
            r"--converter dji_irp",
        ):
            read_rjpeg(path)
        fmt, model, raw = dji_formats.read_original_raw(path)
        assert (fmt, model) == ("dirp-g", "XT S")
        np.testing.assert_array_equal(raw, words)


def test_a_cut_file_of_a_decoded_format_is_still_a_truncation_error(tmp_path):
    data = write_rjpeg(tmp_path / "ok.jpg", np.full((8, 8), 20.0, np.float32)).read_bytes()
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(data[:-2])
    with pytest.raises(DataError, match=r"cut\.jpg: truncated JPEG: the picture data has no end-of-image marker"):
        read_rjpeg(cut)


def test_the_bounds_are_ordered_and_cover_the_emissivity_they_name():
    for approx in dji_approximate.APPROXIMATIONS.values():
        uppers = [u for u, _ in approx.bands]
        assert uppers == sorted(uppers) and approx.emissivity[0] < approx.emissivity[1] <= 1.0
        for (u1, b1), (u2, b2) in zip(approx.bands_high_emissivity, approx.bands):
            assert u1 == u2 and b1 <= b2  # the tighter bands are tighter


# ---------------------------------------------------------------------------------------------- datasets, reports
def test_a_dataset_prepared_on_approximate_temperatures_says_so(tmp_path):
    import cv2

    from coco_rgbt_helpers import make_coco_rgbt, read_json, write_json
    from harness.cache import prepare
    from harness.config import load_config

    root = make_coco_rgbt(tmp_path / "coco", n=6)
    coco = read_json(root)
    for k, im in enumerate(coco["images"]):
        camera_file(root / "thermal" / f"{k:03d}.jpg", np.full((16, 20), 18.0 + k), remap_table(), model="M4T")
        im.update(thermal_file_name=f"thermal/{k:03d}.jpg", width=20, height=16)
        cv2.imwrite(str(root / "rgb" / f"{k:03d}.png"), np.zeros((16, 20, 3), np.uint8))
    coco["annotations"] = [dict(a, bbox=[1.0, 1.0, 5.0, 5.0], area=25.0) for a in coco["annotations"]]
    write_json(root, coco)
    cfg = load_config(protocol="default")
    cfg["dataset"] = {"root": str(root)}
    with pytest.raises(DataError, match="no usable image pairs"):  # refused by default: nothing silently cached
        prepare("coco-rgbt", cfg, cache_root=tmp_path / "cache", progress=False)
    cfg["sensing"]["radiometry"]["approximate"] = True
    ds = prepare("coco-rgbt", cfg, cache_root=tmp_path / "cache", progress=False)
    rep = ds.manifest["report"]
    assert rep["approximate_temperatures"] == {
        "label": "approximate temperatures",
        "samples": 6,
        "bound_c": 0.009,
        "approximations": ["emissivity-remap-skipped"],
    }
    assert any("6 sample(s) hold approximate temperatures" in n for n in rep["notes"])
    assert ds[0].meta["temperatures"] == "approximate temperatures" and ds[0].meta["temperature_bound_c"] == 0.009


def test_every_number_of_a_report_on_approximate_temperatures_is_marked(tmp_path):
    from harness.report.reader import StoreView, read_run
    from harness.report.run_tables import category_table as run_categories
    from harness.report.run_tables import fold_table
    from harness.report.tables import ablation_tables, category_table, project_table
    from harness.runner import RunOutcome, RunSummary
    from harness.store import RunKey
    from report_fixtures import synthetic_store

    store = synthetic_store(
        tmp_path / "store",
        folds=("P1", "P2"),
        per_fold=4,
        detectors={"alpha": "strong", "beta": "weak"},
        encodings={"alpha": ["ir8"]},
        profiles={"alpha": (2.0e6, 5.0), "beta": (1.0e6, 3.0)},
    )
    approx = {
        "label": "approximate temperatures",
        "samples": 8,
        "bound_c": 0.2,
        "approximations": ["emissivity-remap-skipped"],
    }
    for fold in ("P1", "P2"):
        run = store.run(RunKey("synth", "alpha", "c2", fold, 0))
        run.write_metrics({**run.read_metrics(), "temperatures": approx})
    view = StoreView(store)
    table = project_table(view, "synth")
    text = table.to_text()
    rows = {r["detector"]: r for r in table.rows}
    mean = table.cell(rows["alpha"], next(c for c in table.columns if c.key == "mAP50"))
    assert mean.endswith(" ~") and not table.cell(
        rows["beta"], next(c for c in table.columns if c.key == "mAP50")
    ).endswith("~")
    assert "~ measured on approximate temperatures (alpha/c2: within 0.2 C" in text
    params = next(c for c in table.columns if c.key == "params")  # the model's size rests on no temperature
    assert table.cell(rows["alpha"], params) == "2"
    assert "~" in table.to_markdown()
    cats = category_table(view, "synth")
    row = cats.rows[0]
    assert cats.cell(row, next(c for c in cats.columns if c.key == "alpha/c2:AP50")).endswith(" ~")
    assert not cats.cell(row, next(c for c in cats.columns if c.key == "beta/c2:AP50")).endswith("~")
    summary = RunSummary("alpha", "synth", "c2", "test", store.root, {}, ["window", "crack"])
    for fold in ("P1", "P2"):
        run = store.run(RunKey("synth", "alpha", "c2", fold, 0))
        summary.results.append(RunOutcome(read_run(run), "skipped", 4, 4))
    printed = fold_table(summary)
    body = [line for line in printed.splitlines() if line.startswith("P1")][0]
    marks = re.findall(r"\d\.\d{3}( ~)?", body)  # P, R, mAP50, mAP50:95 (those the run scored)
    assert marks and all(m == " ~" for m in marks)
    assert "~ measured on approximate temperatures (within 0.2 C" in printed
    assert "~ measured on approximate temperatures" in run_categories(summary)
    from harness.compare import build_table

    compared = build_table(store.root, ["synth"], allow_mismatched=True).to_text()
    alpha = next(line for line in compared.splitlines() if " alpha " in line and " c2 " in line)
    beta = next(line for line in compared.splitlines() if " beta " in line)
    assert alpha.count(" ~") == 2 and "~" not in beta and "~ measured on approximate temperatures" in compared
    (abl,), _ = ablation_tables(view, "synth", ["window"])
    by_enc = {r["encoding"]: r for r in abl.rows}
    m50 = next(c for c in abl.columns if c.key == "mAP50")
    assert abl.cell(by_enc["c2"], m50).endswith(" ~") and not abl.cell(by_enc["ir8"], m50).endswith("~")
