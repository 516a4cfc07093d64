"""Bad input never produces a traceback: each case is a counted skip (the rest is prepared) or a clear
``DataError`` naming the file and what to do."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from datasets_helpers import edited_json, skip_reasons, synth_cfg, write_or_remove
from harness.errors import DataError


def _prepare(root: Path, cache: Path, accept: tuple[str, ...] = ()):
    from harness.cache import prepare

    cfg = synth_cfg(root)
    cfg.setdefault("inputs", {})["accept"] = list(accept)
    return prepare("m3t", cfg, cache_root=cache, progress=False)


def _coco(root: Path) -> dict:
    return json.loads((root / "annotations" / "instances_rgb.json").read_text())


def _first_pair(root: Path) -> tuple[Path, Path]:
    rgb = root / "images" / _coco(root)["images"][0]["file_name"]
    return rgb, rgb.with_name(rgb.name.replace("_W.JPG", "_T.JPG"))


# ------------------------------------------------------------------------------------------------ counted skips
def test_missing_thermal_partner_is_a_counted_skip(tiny, tmp_path):
    _, thermal = _first_pair(tiny)
    thermal.unlink()
    ds = _prepare(tiny, tmp_path / "c")
    assert len(ds) == 7 and skip_reasons(ds) == {"missing thermal partner": 1}
    listed = ds.manifest["report"]["skipped_files"]
    assert listed[0][0].endswith("_W.JPG") and "no P1/" in listed[0][1]


def test_unreadable_rgb_is_a_counted_skip(tiny, tmp_path):
    rgb, _ = _first_pair(tiny)
    rgb.write_bytes(b"this is not a JPEG")
    ds = _prepare(tiny, tmp_path / "c")
    assert len(ds) == 7 and skip_reasons(ds) == {"RGB unreadable": 1}


def test_unreadable_thermal_is_a_counted_skip(tiny, tmp_path):
    _, thermal = _first_pair(tiny)
    data = thermal.read_bytes()
    thermal.write_bytes(data[: len(data) // 3])  # cut short inside the radiometric payload
    ds = _prepare(tiny, tmp_path / "c")
    assert len(ds) == 7 and skip_reasons(ds) == {"thermal unreadable": 1}


def test_plain_jpeg_instead_of_rjpeg_is_a_counted_skip(tiny, tmp_path):
    rgb, thermal = _first_pair(tiny)
    thermal.write_bytes(rgb.read_bytes())  # a JPEG without APP3 payload
    ds = _prepare(tiny, tmp_path / "c")
    assert skip_reasons(ds) == {"thermal unreadable": 1}
    assert "no radiometric payload" in ds.manifest["report"]["skipped_files"][0][1]


def test_thermal_size_mismatch_is_a_counted_skip(tiny, tmp_path):
    from harness.sensing.radiometry import write_rjpeg

    _, thermal = _first_pair(tiny)
    write_rjpeg(thermal, np.full((64, 80), 20.0, np.float32))
    ds = _prepare(tiny, tmp_path / "c")
    assert len(ds) == 7 and skip_reasons(ds) == {"thermal size mismatch": 1}
    assert "80x64, expected 160x128" in ds.manifest["report"]["skipped_files"][0][1]


def test_a_few_missing_temperatures_are_kept_and_counted_mostly_missing_is_a_counted_skip(tiny, tmp_path):
    _, thermal = _first_pair(tiny)
    temp = np.full((128, 160), 21.5, np.float32)
    temp[10:12, 20:30] = np.nan
    thermal.unlink()
    np.save(thermal.with_suffix(".npy"), temp)
    ds = _prepare(tiny, tmp_path / "c")
    assert len(ds) == 8 and not skip_reasons(ds)
    missing = ds.manifest["report"]["missing_temperatures"]
    assert missing["samples"] == 1 and missing["pixels"] >= 20  # undistortion may widen the holes

    temp[:100] = np.nan
    np.save(thermal.with_suffix(".npy"), temp)
    ds = _prepare(tiny, tmp_path / "d")
    assert len(ds) == 7 and skip_reasons(ds) == {"non-finite temperatures": 1}


def test_rgb_size_differing_from_the_annotation_file_is_a_counted_skip(tiny, tmp_path):
    with edited_json(tiny / "annotations" / "instances_rgb.json") as coco:
        coco["images"][0]["width"] = 4000
    ds = _prepare(tiny, tmp_path / "c")
    assert skip_reasons(ds) == {"RGB size mismatch": 1}


def test_box_outside_the_image_is_counted_and_stops_unless_accepted_partial_boxes_are_clipped(tiny, tmp_path):
    with edited_json(tiny / "annotations" / "instances_rgb.json") as coco:
        coco["annotations"][0]["bbox"] = [5000.0, 10.0, 20.0, 20.0]
        coco["annotations"][1]["bbox"] = [-30.0, 10.0, 40.0, 20.0]
    with pytest.raises(DataError, match=r"dropped-annotations: 1 annotation\(s\) dropped"):
        _prepare(tiny, tmp_path / "c")  # a dropped box would be an unlabelled object: the guard stops
    ds = _prepare(tiny, tmp_path / "c", accept=("dropped-annotations",))
    assert len(ds) == 8 and skip_reasons(ds) == {"annotation box outside the image": 1}
    assert any("clipped" in n for n in ds.manifest["report"]["notes"])


def test_malformed_annotations_are_counted_and_stop_unless_accepted(tiny, tmp_path):
    with edited_json(tiny / "annotations" / "instances_rgb.json") as coco:
        coco["annotations"][0]["category_id"] = 99
        coco["annotations"][1]["image_id"] = 12345
        coco["annotations"][2]["bbox"] = [1, 2, 0, 5]
        coco["annotations"][3]["bbox"] = "wide"
    with pytest.raises(DataError, match=r"dropped-annotations: 4 annotation\(s\) dropped"):
        _prepare(tiny, tmp_path / "c")
    ds = _prepare(tiny, tmp_path / "c", accept=("dropped-annotations",))
    assert skip_reasons(ds) == {
        "annotation with an unknown category id": 1,
        "annotation for an unknown image id": 1,
        "annotation box malformed": 2,
    }


def test_image_path_escaping_the_root_is_a_counted_skip(tiny, tmp_path):
    with edited_json(tiny / "annotations" / "instances_rgb.json") as coco:
        coco["images"][0]["file_name"] = "../../../../etc/passwd"
    ds = _prepare(tiny, tmp_path / "c")
    assert len(ds) == 7 and skip_reasons(ds) == {"path outside the dataset root": 1}


# ------------------------------------------------------------------------------------------------ clear errors
@pytest.mark.parametrize(
    "content, message",
    [
        (None, "annotation file not found"),
        ("", "annotation file is empty"),
        ("  \n", "annotation file is empty"),
        ('{"images": [', "invalid JSON at line 1"),
        ("[1, 2]", "expected a COCO JSON object"),
        ('{"annotations": []}', "'images' is missing"),
    ],
)
def test_broken_annotation_file_is_a_clear_error(tiny, tmp_path, content, message):
    write_or_remove(tiny / "annotations" / "instances_rgb.json", content)
    with pytest.raises(DataError, match=message) as exc:
        _prepare(tiny, tmp_path / "c")
    assert "instances_rgb.json" in str(exc.value)
    assert not (tmp_path / "c" / "m3t").exists() or not any((tmp_path / "c" / "m3t").iterdir())


def test_unknown_category_is_a_clear_error_that_says_how_to_map_it(tiny, tmp_path):
    with edited_json(tiny / "annotations" / "instances_rgb.json") as coco:
        coco["categories"][4]["name"] = "peeling_paint"
    with pytest.raises(DataError, match="unknown category name.*'peeling_paint'.*manifest key 'categories'"):
        _prepare(tiny, tmp_path / "c")
    (tiny / "m3t.yaml").write_text("categories: {peeling_paint: paint_peeling}\n")
    assert len(_prepare(tiny, tmp_path / "c")) == 8


def test_duplicate_image_ids_are_a_clear_error(tiny, tmp_path):
    with edited_json(tiny / "annotations" / "instances_rgb.json") as coco:
        coco["images"][1]["id"] = coco["images"][0]["id"]
    with pytest.raises(DataError, match=r"duplicate image id \d+ \('P1/DJI_.*' and 'P1/DJI_.*'\)"):
        _prepare(tiny, tmp_path / "c")


@pytest.mark.parametrize(
    "line",
    [
        "images: ../../elsewhere",
        "annotations: /etc/hosts",
        "landmarks: registration/../../x.json",
        "projects: {P1: ../../P1}",
    ],
)
def test_manifest_path_escaping_the_root_is_a_clear_error(tiny, tmp_path, line):
    (tiny / "m3t.yaml").write_text(line + "\n")
    with pytest.raises(DataError, match="leads outside the dataset root"):
        _prepare(tiny, tmp_path / "c")


def test_no_usable_pair_is_a_clear_error_and_nothing_is_cached(tiny, tmp_path):
    for p in (tiny / "images").rglob("*_T.JPG"):
        p.unlink()
    with pytest.raises(DataError, match="no usable image pairs.*8 skipped.*missing thermal partner: 8"):
        _prepare(tiny, tmp_path / "c")
    assert not list((tmp_path / "c").rglob("manifest.json"))


def test_cli_prints_a_clear_error_without_traceback(tiny, tmp_path, cli_runner):
    (tiny / "annotations" / "instances_rgb.json").write_text("{oops")
    from click.testing import CliRunner

    from harness.cli import get_cli

    res = CliRunner().invoke(
        get_cli(), ["prepare", "--dataset", "m3t", "--root", str(tiny), "--cache", str(tmp_path / "c")]
    )
    assert res.exit_code == 2
    assert "error:" in res.output and "invalid JSON" in res.output and "Traceback" not in res.output
