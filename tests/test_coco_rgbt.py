"""``coco-rgbt``: aligned RGB-thermal pairs described by one COCO JSON, through prepare, folds and run; every bad
input is a clear error or a counted skip with its reason."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from coco_rgbt_helpers import H, W, centikelvin, make_coco_rgbt, read_json, temperature, write_json
from datasets_helpers import edited_json, skip_reasons, write_or_remove
from harness.contracts import encode
from harness.errors import ConfigError, DataError


@pytest.fixture(scope="module")
def pairs_source(tmp_path_factory) -> Path:
    return make_coco_rgbt(tmp_path_factory.mktemp("coco-rgbt-src") / "d")


@pytest.fixture
def pairs(pairs_source, tmp_path) -> Path:
    """A private copy that a test may damage."""
    return Path(shutil.copytree(pairs_source, tmp_path / "d"))


def _prepare(root: Path, cache: Path, **options):
    from harness.cache import prepare
    from harness.config import load_config

    cfg = load_config(protocol="default")
    cfg["dataset"] = {"root": str(root), **options}
    return prepare("coco-rgbt", cfg, cache_root=cache, progress=False)


def _skipped(ds) -> list[list[str]]:
    return ds.manifest["report"]["skipped_files"]


def _prepare_skipping(root: Path, cache: Path, kept: int, skips: dict[str, int]) -> dict[str, str]:
    """Prepare, check that ``kept`` samples remain and what was skipped (counted by reason); the reason of each file."""
    ds = _prepare(root, cache)
    assert len(ds) == kept and skip_reasons(ds) == skips
    return dict(_skipped(ds))


# ------------------------------------------------------------------------------------------- end to end (CLI)
@pytest.mark.slow
def test_prepare_folds_and_run_through_the_cli(pairs_source, tmp_path, cli_runner):
    root, cache = str(pairs_source), str(tmp_path / "cache")
    res = cli_runner(["prepare", "--dataset", "coco-rgbt", "--root", root, "--cache", cache])
    assert res.exit_code == 0, res.output
    assert "prepared coco-rgbt: 12 aligned samples, 24 instances" in res.output and "skipped pairs: 0" in res.output

    res = cli_runner(["folds", "--dataset", "coco-rgbt", "--root", root, "--cache", cache])
    assert res.exit_code == 0, res.output
    rows = [line.split() for line in res.output.splitlines() if line.startswith("site-")]
    assert [r[0] for r in rows] == ["site-a", "site-b", "site-c"]
    assert all(r[2:] == ["8", "16", "4", "8"] for r in rows)  # train images/instances, val images/instances

    store = tmp_path / "store"
    env = {"HARNESS_CACHE": cache}
    res = cli_runner(
        [
            "run",
            "--detector",
            "ours",
            "--dataset",
            "coco-rgbt",
            "--root",
            root,
            "--folds",
            "all",
            "--profile",
            "smoke",
            "--set",
            "protocol.epochs=1",
            "--store",
            str(store),
            "--no-progress",
            # smaller and faster than the smoke profile's YOLOv8s at 160 px; the path is the same
            "--set",
            "protocol.imgsz=64",
            "--set",
            "model.scale=n",
            "--set",
            "train.threads=1",
        ],
        env=env,
    )
    assert res.exit_code == 0, res.output
    for fold in ("site-a", "site-b", "site-c"):
        metrics = json.loads((store / "coco-rgbt" / "ours" / "c2" / fold / "seed0" / "metrics.json").read_text())
        assert metrics["support"]["images"] == 4 and metrics["support"]["instances"] == 8
        assert metrics["train"]["epochs_run"] == 1


# ------------------------------------------------------------------------------------------- the samples
def test_thermal_is_the_decoded_temperature_and_c2_is_computed_from_it(pairs_source, tmp_path):
    from harness.plugins import get_host
    from harness.sensing.c2 import c2_uint8

    ds = _prepare(pairs_source, tmp_path / "c")
    assert ds.radiometric and list(ds.categories) == ["hot_spot", "window"]
    c2 = get_host().encoding("c2")
    for i in range(len(ds)):
        sample = ds[i]
        k = sample.image_id - 1
        decoded = (centikelvin(temperature(k)).astype(np.float64) * 0.01 - 273.15).astype(np.float32)
        np.testing.assert_array_equal(sample.thermal, decoded)
        np.testing.assert_array_equal(encode(c2, sample), c2_uint8(decoded))
        assert sample.group == ("site-a", "site-b", "site-c")[k % 3]
    first = ds[0]
    np.testing.assert_allclose(first.boxes, [[6, 10, 16, 20], [40, 28, 52, 40]])
    assert first.labels.tolist() == [0, 1] and first.meta["thermal_unit"] == "centikelvin"


def test_folds_given_in_the_json_replace_one_fold_per_group(pairs, tmp_path):
    from harness.cache import resolve_folds
    from harness.config import load_config

    with edited_json(pairs / "annotations.json") as coco:
        coco["folds"] = {"ab": ["site-a", "site-b"], "c": ["site-c"]}
    ds = _prepare(pairs, tmp_path / "c")
    folds = resolve_folds("coco-rgbt", ds, load_config(protocol="default"))
    assert [(f.name, f.val_groups, f.train_groups) for f in folds] == [
        ("ab", ("site-a", "site-b"), ("site-c",)),
        ("c", ("site-c",), ("site-a", "site-b")),
    ]


def test_tiff_in_centikelvin_or_celsius_rjpeg_and_sidecar_units_are_read(pairs, tmp_path):
    import tifffile

    from harness.sensing.radiometry import write_rjpeg, write_thermal

    coco = read_json(pairs)
    t0, t1, t2 = temperature(0), temperature(1), temperature(2)
    tifffile.imwrite(pairs / "thermal" / "000.tif", t0)
    write_rjpeg(pairs / "thermal" / "001.jpg", t1)
    write_thermal(pairs / "thermal" / "002.tif", t2, unit="decicelsius")  # int16 + sidecar naming the unit
    tifffile.imwrite(pairs / "thermal" / "003.tif", centikelvin(temperature(3)))  # uint16, no sidecar
    for k, ext in ((0, "tif"), (1, "jpg"), (2, "tif"), (3, "tif")):
        coco["images"][k]["thermal_file_name"] = f"thermal/{k:03d}.{ext}"
    write_json(pairs, coco)
    ds = _prepare(pairs, tmp_path / "c")
    assert len(ds) == 12 and skip_reasons(ds) == {}
    by_id = {ds[i].image_id: ds[i] for i in range(len(ds))}
    np.testing.assert_array_equal(by_id[1].thermal, t0)
    assert np.abs(by_id[2].thermal - t1).max() < 0.1  # R-JPEG raw14 counts: 1/16 K steps
    assert np.abs(by_id[3].thermal - t2).max() <= 0.05 + 1e-6  # deci-Celsius rounding
    assert by_id[3].meta["thermal_unit"] == "decicelsius" and by_id[2].meta["thermal_format"] == "rjpeg"
    assert by_id[4].meta["thermal_unit"] == "centikelvin" and by_id[4].meta["thermal_format"] == "tif"
    assert np.abs(by_id[4].thermal - temperature(3)).max() <= 0.005 + 1e-4


def test_scale_and_offset_options_override_the_default_unit(pairs, tmp_path):
    import cv2

    with edited_json(pairs / "annotations.json") as coco:
        coco["images"] = coco["images"][:3]  # one per group
        coco["annotations"] = [a for a in coco["annotations"] if a["image_id"] <= 3]
    for k in range(3):  # deci-Kelvin
        cv2.imwrite(str(pairs / "thermal" / f"{k:03d}.png"), np.rint((temperature(k) + 273.15) * 10).astype(np.uint16))
    with pytest.raises(DataError, match="no usable image pairs.*implausible temperatures: 3"):
        _prepare(pairs, tmp_path / "c")  # read as centi-Kelvin: about -244 C
    ds = _prepare(pairs, tmp_path / "c", thermal_scale=0.1, thermal_offset=-273.15)
    assert len(ds) == 3 and np.abs(ds[0].thermal - temperature(0)).max() <= 0.05 + 1e-4


def test_eight_bit_thermal_feeds_the_eight_bit_encodings(pairs, tmp_path):
    import cv2

    from harness.plugins import get_host

    for p in (pairs / "thermal").glob("*.png"):
        cv2.imwrite(str(p), np.full((H, W), 77, np.uint8))
    ds = _prepare(pairs, tmp_path / "c8", thermal="8bit")
    assert len(ds) == 12 and not ds.radiometric and ds[0].thermal is None and int(ds[0].ir8[0, 0]) == 77
    assert encode(get_host().encoding("proxy8"), ds[0]).shape == (H, W)
    radiometric = pytest.raises(DataError, match=r"no usable image pairs.*8-bit thermal: 12")
    with radiometric:
        _prepare(pairs, tmp_path / "c16")


def test_rgb_of_another_size_is_registered_by_the_group_homography(pairs, tmp_path):
    import cv2

    coco = read_json(pairs)
    small = cv2.imread(str(pairs / "rgb" / "000.png"))[:, :, ::-1]
    big = cv2.resize(cv2.imread(str(pairs / "rgb" / "000.png")), (2 * W, 2 * H), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(pairs / "rgb" / "000.png"), big)
    cv2.imwrite(str(pairs / "rgb" / "001.png"), big)
    half = [[0.5, 0, 0], [0, 0.5, 0], [0, 0, 1]]
    coco["homographies"] = {"site-a": half}  # image 1 (000.png) is in site-a
    coco["images"][1]["homography"] = half  # image 2 (001.png, site-b) gives its own
    write_json(pairs, coco)
    ds = _prepare(pairs, tmp_path / "c")
    assert len(ds) == 12 and skip_reasons(ds) == {}
    by_id = {ds[i].image_id: ds[i] for i in range(len(ds))}
    for iid in (1, 2):
        s = by_id[iid]
        assert s.rgb.shape == (H, W, 3) and s.meta["H_rgb_to_frame"] is not None
        # the warp brings the 2x RGB back onto the thermal grid (edges of the blobs blur a little)
        assert np.median(np.abs(s.rgb.astype(int) - small.astype(int))) <= 1
    np.testing.assert_allclose(by_id[1].boxes, [[6, 10, 16, 20], [40, 28, 52, 40]])
    assert "H_rgb_to_frame" not in by_id[3].meta  # same-size pairs are not resampled
    assert any("warped into the thermal frame" in n for n in ds.manifest["report"]["notes"])


def test_registration_crops_to_the_common_support_and_moves_the_boxes(pairs, tmp_path):
    import cv2

    rgb = cv2.imread(str(pairs / "rgb" / "000.png"))
    cv2.imwrite(str(pairs / "rgb" / "000.png"), rgb[:, 8:])  # 56x48: the RGB camera missed the left 8 columns
    with edited_json(pairs / "annotations.json") as coco:
        coco["images"][0]["homography"] = [[1, 0, 8], [0, 1, 0], [0, 0, 1]]  # RGB x + 8 = thermal x
    ds = _prepare(pairs, tmp_path / "c")
    s = next(ds[i] for i in range(len(ds)) if ds[i].image_id == 1)
    assert s.rgb.shape == (H, W - 8, 3) and s.thermal.shape == (H, W - 8)
    assert s.meta["crop_origin"] == [8, 0]
    decoded = (centikelvin(temperature(0)).astype(np.float64) * 0.01 - 273.15).astype(np.float32)
    np.testing.assert_array_equal(s.thermal, decoded[:, 8:])  # sliced, never resampled
    np.testing.assert_array_equal(s.rgb, rgb[:, 8:, ::-1])
    np.testing.assert_allclose(s.boxes, [[0, 10, 8, 20], [32, 28, 44, 40]])  # shifted by the crop origin, clipped


# ------------------------------------------------------------------------------------------- bad inputs
def test_missing_thermal_partner_is_a_counted_skip(pairs, tmp_path):
    (pairs / "thermal" / "000.png").unlink()
    coco = read_json(pairs)
    del coco["images"][1]["thermal_file_name"]
    write_json(pairs, coco)
    reasons = _prepare_skipping(pairs, tmp_path / "c", 10, {"missing thermal partner": 2})
    assert "thermal/000.png not found" in reasons["rgb/000.png"]
    assert "has no 'thermal_file_name'" in reasons["rgb/001.png"]


def test_missing_rgb_file_is_a_counted_skip(pairs, tmp_path):
    (pairs / "rgb" / "003.png").unlink()
    _prepare_skipping(pairs, tmp_path / "c", 11, {"missing RGB image": 1})


def test_size_mismatch_without_a_homography_is_a_counted_skip_naming_the_fix(pairs, tmp_path):
    import cv2

    cv2.imwrite(str(pairs / "rgb" / "000.png"), np.zeros((2 * H, 2 * W, 3), np.uint8))
    with edited_json(pairs / "annotations.json") as coco:
        coco["images"][1]["width"] = 640
    reasons = _prepare_skipping(pairs, tmp_path / "c", 10, {"size mismatch": 2})
    assert "RGB rgb/000.png is 128x96, thermal thermal/000.png is 64x48" in reasons["rgb/000.png"]
    assert "homographies['site-a']" in reasons["rgb/000.png"]
    assert "the JSON says 640x48" in reasons["rgb/001.png"]


def _prepare_accepting(root: Path, cache: Path, kind: str, **options):
    """Prepare with ``inputs.accept=[kind]`` (the guard's option that accepts the finding)."""
    from harness.cache import prepare
    from harness.config import load_config

    cfg = load_config(protocol="default", overrides=[f"inputs.accept=[{kind}]"])
    cfg["dataset"] = {"root": str(root), **options}
    return prepare("coco-rgbt", cfg, cache_root=cache, progress=False)


def test_a_category_missing_from_the_file_stops_instead_of_dropping_its_boxes(pairs, tmp_path):
    coco = read_json(pairs)
    for a in coco["annotations"]:
        if a["category_id"] == 2:
            a["category_id"] = 7  # 'window' left out of the categories: its boxes would be dropped
    write_json(pairs, coco)
    with pytest.raises(DataError) as err:
        _prepare(pairs, tmp_path / "c")
    lines = str(err.value).splitlines()
    assert " ".join(x.strip() for x in lines[1:3]) == (
        "dropped-annotations: 12 annotation(s) dropped, 12 kept (annotation with an unknown category id: 12)"
    )
    assert lines[3].startswith("    e.g. annotations.json#annotation=") and lines[5].endswith("(and 9 more)")
    assert all(len(line) <= 100 for line in lines[1:6])
    assert "inputs.accept=[dropped-annotations]" in lines[7]
    ds = _prepare_accepting(pairs, tmp_path / "c", "dropped-annotations")
    assert len(ds) == 12 and skip_reasons(ds) == {"annotation with an unknown category id": 12}
    assert "1 hot_spot, 2 window" in _skipped(ds)[0][1]
    assert ds.manifest["instances"] == 12
    assert [r["kind"] for r in ds.input_risks] == ["dropped-annotations"]


def test_box_outside_the_image_stops_with_a_summary_and_partial_boxes_are_clipped(pairs, tmp_path):
    coco = read_json(pairs)
    for a in coco["annotations"][:5]:
        a["bbox"] = [500.0 + a["id"], 10.0, 10.0, 10.0]
    coco["annotations"][5]["bbox"] = [50.0, 30.0, 30.0, 10.0]  # reaches past x = 64
    write_json(pairs, coco)
    with pytest.raises(DataError) as err:
        _prepare(pairs, tmp_path / "c")
    lines = str(err.value).splitlines()  # counts and three examples, not one reason per box on one line
    assert lines[1] == "  dropped-annotations: 5 annotation(s) dropped, 19 kept (annotation box outside the image: 5)"
    assert lines[2].startswith("    e.g. annotations.json#annotation=1: annotation box outside the image: [501.0,")
    assert lines[4].endswith("(and 2 more)") and all(len(line) <= 100 for line in lines[1:5])
    ds = _prepare_accepting(pairs, tmp_path / "c", "all")
    assert len(ds) == 12 and skip_reasons(ds) == {"annotation box outside the image": 5}
    assert _skipped(ds)[0][0] == "annotations.json#annotation=1"
    assert any("1 box(es) reaching past the image edge were clipped" in n for n in ds.manifest["report"]["notes"])
    clipped = next(ds[i] for i in range(len(ds)) if ds[i].image_id == coco["annotations"][5]["image_id"])
    assert [50, 30, 64, 40] in clipped.boxes.tolist()


def test_duplicate_image_ids_are_a_clear_error(pairs, tmp_path):
    with edited_json(pairs / "annotations.json") as coco:
        coco["images"][1]["id"] = coco["images"][0]["id"]
    with pytest.raises(DataError, match=r"annotations.json: duplicate image id 1 \('rgb/000.png' and 'rgb/001.png'\)"):
        _prepare(pairs, tmp_path / "c")
    assert not list((tmp_path / "c").rglob("manifest.json"))


def test_duplicate_category_ids_are_a_clear_error(pairs, tmp_path):
    with edited_json(pairs / "annotations.json") as coco:
        coco["categories"][1]["id"] = 1
    with pytest.raises(DataError, match=r"duplicate category id 1 \('hot_spot' and 'window'\)"):
        _prepare(pairs, tmp_path / "c")


def test_duplicate_annotation_ids_are_dropped_annotations(pairs, tmp_path):
    with edited_json(pairs / "annotations.json") as coco:
        coco["annotations"][3]["id"] = coco["annotations"][0]["id"]
    with pytest.raises(DataError, match="dropped-annotations: 1 annotation"):
        _prepare(pairs, tmp_path / "c")
    ds = _prepare_accepting(pairs, tmp_path / "c", "dropped-annotations")
    assert skip_reasons(ds) == {"annotation with a duplicate id": 1} and ds.manifest["instances"] == 23


def test_image_without_a_group_or_with_an_escaping_path_is_a_counted_skip(pairs, tmp_path):
    coco = read_json(pairs)
    del coco["images"][0]["group"]
    coco["images"][1]["thermal_file_name"] = "../../../etc/passwd"
    write_json(pairs, coco)
    ds = _prepare(pairs, tmp_path / "c")
    assert len(ds) == 10 and skip_reasons(ds) == {"no group": 1, "path outside the dataset root": 1}


def test_unreadable_and_mostly_missing_thermal_are_counted_skips_a_few_holes_are_kept(pairs, tmp_path):
    import tifffile

    (pairs / "thermal" / "000.png").write_bytes(b"not a png")
    holed = temperature(1)
    holed[3, 3], holed[5, 7] = np.nan, np.inf
    tifffile.imwrite(pairs / "thermal" / "001.tif", holed)
    mostly = temperature(2)
    mostly[: mostly.shape[0] * 3 // 4] = np.nan
    tifffile.imwrite(pairs / "thermal" / "002.tif", mostly)
    with edited_json(pairs / "annotations.json") as coco:
        coco["images"][1]["thermal_file_name"] = "thermal/001.tif"
        coco["images"][2]["thermal_file_name"] = "thermal/002.tif"
    ds = _prepare(pairs, tmp_path / "c")
    assert skip_reasons(ds) == {"thermal unreadable": 1, "non-finite temperatures": 1}
    missing = ds.manifest["report"]["missing_temperatures"]
    assert missing["samples"] == 1 and missing["pixels"] == 2  # the holed frame is kept, its two holes counted


@pytest.mark.parametrize(
    "content, message",
    [
        (None, "annotation file not found; set dataset.annotations"),
        ("", "annotation file is empty"),
        ('{"images": [', "invalid JSON"),
        ('{"images": [], "annotations": []}', "'categories' is missing"),
        ('{"images": [], "categories": []}', "'categories' is empty"),
    ],
)
def test_broken_annotation_file_is_a_clear_error(pairs, tmp_path, content, message):
    write_or_remove(pairs / "annotations.json", content)
    with pytest.raises(DataError, match=message) as exc:
        _prepare(pairs, tmp_path / "c")
    assert "annotations.json" in str(exc.value)


def test_folds_naming_an_unknown_group_are_a_clear_error(pairs, tmp_path):
    with edited_json(pairs / "annotations.json") as coco:
        coco["folds"] = {"x": ["site-z"]}
    with pytest.raises(DataError, match="fold 'x' holds out 'site-z'.*site-a, site-b, site-c"):
        _prepare(pairs, tmp_path / "c")


@pytest.mark.parametrize(
    "options, message",
    [
        ({"thermal": "16bit"}, "option 'thermal' must be one of radiometric, 8bit"),
        ({"thermal_scale": "big"}, "option 'thermal_scale' must be a number"),
        ({"stride": 2}, "does not take option"),
    ],
)
def test_bad_options_are_config_errors(pairs_source, tmp_path, options, message):
    with pytest.raises(ConfigError, match=message):
        _prepare(pairs_source, tmp_path / "c", **options)


def test_a_bad_warp_setting_is_a_config_error(pairs_source, tmp_path):
    from harness.cache import prepare
    from harness.config import load_config

    cfg = load_config(protocol="default", overrides=["sensing.warp.interpolation=bicubic"])
    cfg["dataset"] = {"root": str(pairs_source)}
    with pytest.raises(ConfigError, match="sensing.warp.interpolation must be one of linear"):
        prepare("coco-rgbt", cfg, cache_root=tmp_path / "c", progress=False)


def test_cli_prints_a_clear_error_without_traceback(pairs, tmp_path):
    from click.testing import CliRunner

    from harness.cli import get_cli

    (pairs / "annotations.json").write_text("{oops")
    res = CliRunner().invoke(
        get_cli(), ["prepare", "--dataset", "coco-rgbt", "--root", str(pairs), "--cache", str(tmp_path / "c")]
    )
    assert res.exit_code != 0 and "invalid JSON" in res.output and "Traceback" not in res.output
