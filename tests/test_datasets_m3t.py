"""The M3T adapter on the synthetic raw layout: boxes after the pipeline, grouping, the aligned form, the manifest."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from adapters.datasets.m3t import M3T_CATEGORIES, clip_box_xywh, load_manifest, open_m3t, safe_join, time_from_name
from datasets_helpers import corner_errors, synth_cfg
from harness.api import PrepareReport
from harness.errors import DataError


def _prepare(root: Path, cache: Path, **dataset):
    from harness.cache import prepare

    return prepare("m3t-synth", synth_cfg(root, **dataset), cache_root=cache, progress=False)


# ------------------------------------------------------------------------------------------------ pure helpers
def test_time_from_dji_file_name():
    assert time_from_name("DJI_20240512103015_0001_W.JPG").isoformat() == "2024-05-12T10:30:15"
    assert time_from_name("IMG_0001.JPG") is None


def test_clip_box_xywh():
    assert clip_box_xywh([10, 10, 5, 5], 100, 80) == ([10, 10, 15, 15], False)
    assert clip_box_xywh([-5, 70, 20, 20], 100, 80) == ([0, 70, 15, 80], True)
    assert clip_box_xywh([120, 10, 5, 5], 100, 80) == (None, True)


def test_safe_join_refuses_paths_leaving_the_root(tmp_path):
    (tmp_path / "a").mkdir()
    assert safe_join(tmp_path, "a/b.json", "x") == tmp_path / "a" / "b.json"
    assert safe_join(tmp_path, "a/../a/./b.json", "x") == tmp_path / "a" / "b.json"
    for bad in ("../outside", "/etc/passwd", "a/../../x", "a/../../" + tmp_path.name + "-evil/x"):
        with pytest.raises(DataError, match="leads outside the dataset root"):
            safe_join(tmp_path, bad, "manifest key 'images'")
    # a link the user placed inside the dataset (images on another disk) is followed
    os.symlink(tmp_path / "a", tmp_path / "link")
    assert safe_join(tmp_path, "link/b.json", "y") == tmp_path / "link" / "b.json"


# ------------------------------------------------------------------------------------------------ the pipeline
def test_boxes_after_the_pipeline_match_the_generators_ground_truth(tiny, tmp_path):
    """Landmarks -> homography per group -> undistort, warp, crop, boxes through H: mean corner error < 1 px."""
    ds = _prepare(tiny, tmp_path / "cache")
    gt = json.loads((tiny / "ground_truth" / "instances_thermal.json").read_text())
    assert len(ds) == len(gt["images"])
    err, unmatched = corner_errors(ds, tiny)
    assert len(err) >= 0.95 * len(gt["annotations"])
    assert unmatched <= 0.05 * len(err)  # slivers of objects just outside the frame
    assert err.mean() < 1.0, err.mean()
    assert np.median(err) < 0.8
    # every sample is in the thermal frame: same size as the thermal sensor when RGB covers it all
    s = ds[0]
    assert s.thermal.shape == (128, 160) and s.rgb.shape == (128, 160, 3)
    assert s.meta["inspection_group"] == "P1-01" and s.group == "P1"


def test_true_homographies_give_smaller_box_errors(tiny, tmp_path):
    shutil.copy(tiny / "ground_truth" / "homographies.yaml", tiny / "registration" / "homographies.yaml")
    ds = _prepare(tiny, tmp_path / "cache")
    assert "source dataset file" in " ".join(ds.manifest["report"]["notes"])
    err, _ = corner_errors(ds, tiny)
    assert err.mean() < 0.7


def test_landmarks_clicked_on_the_raw_images_are_undistorted_first(tiny, tmp_path):
    from adapters.datasets.synthetic import distort_points
    from harness.sensing.calibration import CameraModel

    cam = CameraModel.load(tiny / "calibration" / "wide_camera.yaml")
    path = tiny / "registration" / "landmarks.json"
    data = json.loads(path.read_text())
    for item in data["landmarks"]:
        item["rgb"] = distort_points(np.array([item["rgb"]]), cam.K, cam.dist)[0].tolist()
    path.write_text(json.dumps(data))
    (tiny / "m3t.yaml").write_text("landmarks_rgb: raw\n")
    err, _ = corner_errors(_prepare(tiny, tmp_path / "raw"), tiny)
    assert err.mean() < 1.0
    (tiny / "m3t.yaml").write_text("landmarks_rgb: undistorted\n")  # the wrong frame: distortion left in
    wrong, _ = corner_errors(_prepare(tiny, tmp_path / "wrong"), tiny)
    assert wrong.mean() > err.mean() + 0.1


def test_prepared_thermal_is_the_decoded_rjpeg_unresampled(tiny, tmp_path):
    from harness.sensing.radiometry import read_rjpeg

    ds = _prepare(tiny, tmp_path / "cache")
    s = ds[3]
    rj = read_rjpeg(tiny / s.meta["thermal_file"])
    x0, y0 = s.meta["crop_origin"]
    h, w = s.thermal.shape
    assert np.array_equal(s.thermal, rj.temperature_c[y0 : y0 + h, x0 : x0 + w])


def test_fitted_homographies_are_saved_with_the_prepared_data(tiny, tmp_path):
    from harness.sensing.registration import corner_error, load_homographies

    ds = _prepare(tiny, tmp_path / "cache")
    fitted = load_homographies(ds.folder / "homographies.yaml")
    true = load_homographies(tiny / "ground_truth" / "homographies.yaml")
    assert set(fitted) == set(true)
    for g in true:
        assert corner_error(fitted[g], true[g], (160, 128)).mean() < 2.0  # extrapolated to the frame's corners


def test_registration_error_command_on_the_synthetic_landmarks(tiny, tmp_path, cli_runner):
    """`harness sensing registration-error` against the true homography measures the click noise; the
    homographies fitted while preparing score about the same on those landmarks."""
    ds = _prepare(tiny, tmp_path / "cache")

    def registration_error(homographies: Path, name: str) -> dict:
        landmarks = str(tiny / "registration" / "landmarks.json")
        out = tmp_path / f"{name}.json"
        args = ["--landmarks", landmarks, "--homographies", str(homographies), "--out", str(out)]
        res = cli_runner(["sensing", "registration-error", *args])
        assert res.exit_code == 0, res.output
        return json.loads(out.read_text())

    true = registration_error(tiny / "ground_truth" / "homographies.yaml", "true")
    fitted = registration_error(ds.folder / "homographies.yaml", "fitted")
    assert true["n"] == fitted["n"] > 50
    assert 0.3 < true["mean"] < 1.0  # 0.8 RGB px and 0.35 thermal px click noise per axis
    assert fitted["mean"] <= true["mean"] + 0.05  # least squares fits the clicks it was fitted on


def test_centikelvin_thermal_files_are_read_the_same_way(tmp_path):
    from adapters.datasets.synthetic import generate
    from harness.sensing.radiometry import read_thermal

    s = generate(tmp_path / "ck", profile="tiny", seed=0, thermal_format="centikelvin", progress=False)
    tfile = next((s.root / "images" / "P1").glob("*_T.png"))
    temp, info = read_thermal(tfile)
    assert info["unit"] == "centikelvin" and temp.shape == (128, 160)
    ds = _prepare(s.root, tmp_path / "cache")
    assert len(ds) == 8 and ds.radiometric
    err, _ = corner_errors(ds, s.root)
    assert err.mean() < 1.0


def test_inspection_groups_come_from_capture_times(tiny):
    src = open_m3t(tiny, name="m3t-synth")
    sessions = json.loads((tiny / "ground_truth" / "sessions.json").read_text())
    assert src.inspection_groups() == sorted(sessions)
    assert src.groups() == ["P1", "P2", "P3", "P4", "P5"]


def test_capture_times_from_exif_when_file_names_carry_none(tiny):
    coco = json.loads((tiny / "annotations" / "instances_rgb.json").read_text())
    for img in coco["images"]:
        old = tiny / "images" / img["file_name"]
        new_name = img["file_name"].replace("DJI_", "IMG_")
        old.rename(tiny / "images" / new_name)
        t_old = old.with_name(old.name.replace("_W.JPG", "_T.JPG"))
        t_old.rename(t_old.with_name(t_old.name.replace("DJI_", "IMG_")))
        img["file_name"] = new_name
        del img["date_captured"]
    (tiny / "annotations" / "instances_rgb.json").write_text(json.dumps(coco))
    src = open_m3t(tiny)
    sessions = json.loads((tiny / "ground_truth" / "sessions.json").read_text())
    assert src.inspection_groups() == sorted(sessions)
    assert all(r.captured is not None for r in src.records)


def test_a_captures_file_overrides_groups(tiny):
    coco = json.loads((tiny / "annotations" / "instances_rgb.json").read_text())
    rows = ["file,group"] + [f"{img['file_name']},site-A" for img in coco["images"][:2]]
    (tiny / "captures.csv").write_text("\n".join(rows) + "\n")
    src = open_m3t(tiny)
    assert "site-A" in src.inspection_groups()


def test_dataset_folds_are_the_seeds_project_groups(tiny):
    folds = {f.name: (f.train_groups, f.val_groups) for f in open_m3t(tiny).folds()}
    assert folds["P4+P5"] == (("P1", "P2", "P3"), ("P4", "P5"))
    assert folds["P1"] == (("P2", "P3", "P4", "P5"), ("P1",))


def test_displacement_delamination_response_falls_and_seepage_does_not(tiny_source, tmp_path):
    """The seed's displacement study on the synthetic set: the compact delamination patch loses its C2 response
    when thermal and boxes are misregistered by a few pixels; the diffuse water seepage does not."""
    from harness.sensing.analyses import displacement_study

    ds = _prepare(tiny_source, tmp_path / "cache")
    r = displacement_study(iter(ds), ds.categories, [2, 5, 10])
    delam, seep = r["classes"]["delamination"], r["classes"]["water_seepage"]
    assert delam["boxes"] >= 5 and seep["boxes"] >= 3
    assert delam["R"][3] < 97  # 10 px, in % of the aligned response (the ranges: test_synthetic_physics.py)
    assert delam["R"][1] > delam["R"][2] > delam["R"][3]
    assert 95 <= min(seep["R"][1:]) and max(seep["R"][1:]) <= 110


# ------------------------------------------------------------------------------------------------ aligned form
def _export_aligned(prepared, out: Path) -> None:
    """Write prepared samples in the aligned M3T layout (RGB PNG, centi-Kelvin PNG, COCO in the thermal frame)."""
    import cv2

    from harness.sensing.radiometry import write_thermal

    images, anns = [], []
    for s in prepared:
        stem = Path(s.meta["file_name"]).stem.replace("_W", "")
        project = s.group
        (out / "aligned" / "rgb" / project).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out / "aligned" / "rgb" / project / f"{stem}.png"), np.ascontiguousarray(s.rgb[:, :, ::-1]))
        write_thermal(out / "aligned" / "thermal" / project / f"{stem}.png", s.thermal)
        images.append({"id": s.image_id, "file_name": f"{project}/{stem}.png", "width": s.width, "height": s.height})
        for b, lab in zip(np.asarray(s.boxes), s.labels):
            anns.append(
                {
                    "id": len(anns) + 1,
                    "image_id": s.image_id,
                    "category_id": int(lab) + 1,
                    "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])],
                }
            )
    cats = [{"id": i + 1, "name": n} for i, n in enumerate(M3T_CATEGORIES)]
    (out / "annotations").mkdir(parents=True)
    (out / "annotations" / "instances_thermal.json").write_text(
        json.dumps({"images": images, "annotations": anns, "categories": cats})
    )


def test_aligned_form_reads_back_what_was_prepared(tiny, tmp_path):
    ds = _prepare(tiny, tmp_path / "cache")
    out = tmp_path / "aligned"
    _export_aligned(ds, out)
    src = open_m3t(out)
    assert src.manifest.format == "aligned"
    report = PrepareReport()
    samples = list(src.samples(report))
    assert not report.skipped
    by_id = {s.image_id: s for s in samples}
    for s in ds:
        a = by_id[s.image_id]
        assert np.array_equal(a.rgb, s.rgb)
        assert np.abs(a.thermal - s.thermal).max() <= 0.005 + 1e-6  # centi-Kelvin storage
        assert np.allclose(a.boxes, s.boxes, atol=1e-4) and np.array_equal(a.labels, s.labels)
        assert a.group == s.group


def test_aligned_form_skips_pairs_whose_sizes_disagree(tiny, tmp_path):
    import cv2

    ds = _prepare(tiny, tmp_path / "cache")
    out = tmp_path / "aligned"
    _export_aligned(ds, out)
    first = sorted((out / "aligned" / "rgb").rglob("*.png"))[0]
    cv2.imwrite(str(first), np.zeros((50, 60, 3), np.uint8))
    report = PrepareReport()
    samples = list(open_m3t(out).samples(report))
    assert len(samples) == len(ds) - 1
    assert report.summary()["skip_reasons"] == {"RGB size mismatch": 1}


# ------------------------------------------------------------------------------------------------ manifest
def test_manifest_maps_folder_names_and_categories(tiny):
    (tiny / "images" / "P1").rename(tiny / "images" / "Site_Alpha")
    coco_path = tiny / "annotations" / "instances_rgb.json"
    coco = json.loads(coco_path.read_text())
    for img in coco["images"]:
        img["file_name"] = img["file_name"].replace("P1/", "Site_Alpha/")
    coco["categories"][3]["name"] = "surface_crack"
    (tiny / "labels").mkdir()
    (tiny / "labels" / "rgb.json").write_text(json.dumps(coco))
    (tiny / "m3t.yaml").write_text(
        "format: raw\nannotations: labels/rgb.json\nthermal_size: [160, 128]\n"
        "projects: {P1: Site_Alpha, P2: P2, P3: P3, P4: P4, P5: P5}\n"
        "categories: {surface_crack: crack}\n"
    )
    src = open_m3t(tiny)
    assert src.groups() == ["P1", "P2", "P3", "P4", "P5"]
    report = PrepareReport()
    samples = list(src.samples(report))
    assert len(samples) == 8 and not report.skipped
    assert any((s.labels == M3T_CATEGORIES.index("crack")).any() for s in samples)


def test_manifest_unknown_key_and_bad_values_are_errors(tiny):
    for text, match in (
        ("format: raw\nimage_dir: images\n", "unknown manifest key.*'image_dir'"),
        ("format: stacked\n", "'format' expects 'raw' or 'aligned'"),
        ("thermal_size: 640\n", "thermal_size"),
        ("categories: {cracks: fissure}\n", "neither one of"),
    ):
        (tiny / "m3t.yaml").write_text(text)
        with pytest.raises(DataError, match=match):
            load_manifest(tiny)


def test_no_root_names_the_setting_and_the_synthetic_alternative(monkeypatch):
    monkeypatch.delenv("HARNESS_M3T_ROOT", raising=False)
    with pytest.raises(DataError, match="dataset.root.*HARNESS_M3T_ROOT.*m3t-synth"):
        open_m3t(None)


def test_registration_error_with_the_truth_beside_it(tiny, tmp_path, cli_runner):
    """`--truth`: the landmarks' error under the true homographies and the fitted ones' distance from them."""
    lm = tiny / "registration" / "landmarks.json"
    truth = tiny / "ground_truth" / "homographies.yaml"
    res = cli_runner(
        [
            "sensing",
            "registration-error",
            "--landmarks",
            str(lm),
            "--truth",
            str(truth),
            "--out",
            str(tmp_path / "r.json"),
        ]
    )
    assert res.exit_code == 0, res.output
    assert "landmarks, true homography" in res.output and "fitted vs true homography" in res.output
    r = json.loads((tmp_path / "r.json").read_text())["truth"]
    assert r["landmarks_on_true"]["n"] == json.loads((tmp_path / "r.json").read_text())["n"] > 50
    assert 0.3 < r["landmarks_on_true"]["mean"] < 1.0  # the tiny profile's precise clicks
    assert 0 < r["fitted_vs_true"]["mean"] < 2.0 and r["fitted_vs_true"]["n"] == 81 * 5  # 9x9 grid, 5 groups
    # the truth given as the evaluated homographies: the fitted-vs-true distance is zero
    res = cli_runner(
        [
            "sensing",
            "registration-error",
            "--landmarks",
            str(lm),
            "--homographies",
            str(truth),
            "--truth",
            str(truth),
            "--out",
            str(tmp_path / "t.json"),
        ]
    )
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "t.json").read_text())["truth"]["fitted_vs_true"]["mean"] < 1e-6
    # a synthetic set's own landmarks: its ground truth is found beside them
    res = cli_runner(["sensing", "registration-error", "--landmarks", str(lm)])
    assert res.exit_code == 0 and "landmarks, true homography" in res.output, res.output
    (tmp_path / "elsewhere").mkdir()
    shutil.copy(lm, tmp_path / "elsewhere" / "landmarks.json")
    res = cli_runner(["sensing", "registration-error", "--landmarks", str(tmp_path / "elsewhere" / "landmarks.json")])
    assert res.exit_code == 0 and "true homography" not in res.output, res.output
