"""The synthetic M3T-like generator: geometry maths, determinism, layout, and the categories' signatures."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from adapters.datasets import synthetic as S
from adapters.datasets.m3t import M3T_CATEGORIES
from adapters.datasets.synthetic.generation import _sawtooth
from adapters.datasets.synthetic.painting import _overlaps
from harness.sensing.registration import apply_homography, plane_homography


# ------------------------------------------------------------------------------------------------ geometry
def test_camera_matrix_uses_35mm_equivalent_focal_length():
    k = S.camera_matrix((960, 720), 24.0)
    assert k[0, 0] == pytest.approx(24.0 * 1200.0 / 43.27)  # diagonal 1200 px
    assert (k[0, 2], k[1, 2]) == (479.5, 359.5)  # OpenCV pixel centres


def test_m3t_optics_put_thermal_footprint_in_the_central_part_of_rgb():
    rig = S.Rig.for_profile(S.PROFILES["full"])
    scale = rig.k_thermal[0, 0] / rig.k_rgb[0, 0]  # thermal px per RGB px
    # 40 mm vs 24 mm equivalent at 640x512 vs 2000x1500: 640 thermal px span ~1170 RGB px (58 %)
    assert 640 / scale / 2000 == pytest.approx(0.585, abs=0.01)


def test_plane_homography_without_rotation_or_baseline_is_the_focal_ratio():
    kw = S.camera_matrix((400, 300), 24.0)
    kt = S.camera_matrix((160, 128), 40.0)
    h = plane_homography(kw, kt, np.eye(3), np.zeros(3), np.array([0, 0, 1.0]), 10.0)
    s = kt[0, 0] / kw[0, 0]
    assert np.allclose(h[:2, :2], np.eye(2) * s)
    # the RGB principal point lands on the thermal principal point
    assert np.allclose(apply_homography(h, [[kw[0, 2], kw[1, 2]]]), [[kt[0, 2], kt[1, 2]]])


def test_baseline_parallax_falls_with_distance():
    kw = S.camera_matrix((400, 300), 24.0)
    kt = S.camera_matrix((160, 128), 40.0)
    t = np.array([0.03, 0.0, 0.0])
    n = np.array([0, 0, 1.0])
    shift = [
        plane_homography(kw, kt, np.eye(3), t, n, d)[0, 2] - plane_homography(kw, kt, np.eye(3), 0 * t, n, d)[0, 2]
        for d in (5.0, 10.0)
    ]
    # f_T * B / Z: halves when the distance doubles
    assert shift[0] == pytest.approx(kt[0, 0] * 0.03 / 5.0)
    assert shift[1] == pytest.approx(shift[0] / 2)


def test_distortion_round_trip_and_barrel_direction():
    k = S.camera_matrix((960, 720), 24.0)
    dist = (-0.105, 0.045, 0, 0, 0)
    pts = np.array([[0.0, 0.0], [959.0, 719.0], [479.5, 359.5], [100.0, 600.0]])
    ideal = S.undistort_points_dense(pts, k, dist)
    assert np.abs(S.distort_points(ideal, k, dist) - pts).max() < 1e-6
    # barrel: a distorted corner comes from further out
    assert ideal[0, 0] < 0 and ideal[0, 1] < 0
    assert np.allclose(ideal[2], pts[2])


def test_opencv_agrees_with_the_generators_distortion_model():
    import cv2

    k = S.camera_matrix((960, 720), 24.0)
    dist = np.array([-0.105, 0.045, 0, 0, 0])
    pts = np.array([[3.0, 5.0], [950.0, 700.0], [600.0, 100.0]])
    ours = S.undistort_points_dense(pts, k, dist)
    theirs = cv2.undistortPoints(pts.reshape(-1, 1, 2), k, dist, P=k).reshape(-1, 2)
    assert np.abs(ours - theirs).max() < 1e-3


def test_canvas_extent_box_is_exact_on_the_canvas_grid():
    c = S.Canvas(k=2, mx=10, my=5, thermal_size=(40, 30))
    assert (c.width, c.height) == (120, 80)
    rows, cols = np.nonzero(np.ones((3, 4), bool))
    box = c.extent_box(rows + 10, cols + 20)  # canvas rows 10..12, cols 20..23
    assert box.tolist() == [0.0, 0.0, 2.0, 1.5]
    assert c.u(20) == pytest.approx(0.25)  # centre of the first canvas column inside the frame


def test_sawtooth_drift_stays_in_range_and_resets():
    vals = [_sawtooth(i, 5, 0, -0.8, 2.2) for i in range(10)]
    assert min(vals) == pytest.approx(-0.8) and max(vals) == pytest.approx(2.2)
    assert vals[4] > vals[5]  # shutter recalibration resets the ramp


def test_full_profile_has_the_seeds_fold_sizes():
    n = dict(zip(S.PROJECTS, S.PROFILES["full"].images))
    total = sum(n.values())
    assert total == 674
    held = {"P1": n["P1"], "P2": n["P2"], "P3": n["P3"], "P4+P5": n["P4"] + n["P5"]}
    assert {f: (total - v, v) for f, v in held.items()} == {
        "P1": (418, 256),
        "P2": (587, 87),
        "P3": (473, 201),
        "P4+P5": (544, 130),
    }


def test_a_stain_wider_than_a_window_is_placed_and_damp_stays_clear_of_every_sill():
    """The full profile's narrow P5 windows (0.9 m) and wide stains (up to 1.5 m) once stopped the generator
    (numpy refused uniform(low > high) for the try under the sill). Every stain now gets a place, and, as the
    documented v2 model says, clear of every window sill."""
    import dataclasses

    canvas = S.Canvas(2, 20, 20, (640, 512))
    ppm = 80.0
    layers = S.Layers(
        canvas,
        np.zeros((canvas.height, canvas.width, 3), np.float32),
        np.zeros((canvas.height, canvas.width), np.float32),
        np.full((canvas.height, canvas.width), np.nan, np.float32),
        ppm,
    )
    window = S.SceneObject("window", np.array([300.0, 100.0, 300.0 + 0.6 * ppm, 100.0 + 1.2 * ppm]))
    sill = S.sill_box(window.box, ppm)
    look = dataclasses.replace(S.LOOKS["P5"], rates={c: 0.0 for c in S.BASE_RATES} | {"water_seepage": 3.0})
    placed = []
    for seed in range(20):
        placed += S.place_objects(layers, look, [window], np.random.default_rng(seed))
    assert len(placed) >= 20 and all(o.category == "water_seepage" for o in placed)
    assert max(o.box[2] - o.box[0] for o in placed) > window.box[2] - window.box[0]  # wider than the window
    assert not any(_overlaps(o.box, [sill], 0.05 * ppm) for o in placed)


def test_unknown_profile_is_a_clear_error():
    from harness.errors import DataError

    with pytest.raises(DataError, match="unknown synthetic profile 'huge'.*tiny, small, full"):
        S.get_profile("huge")


# ------------------------------------------------------------------------------------------------ generated data
def _digest(root: Path) -> str:
    h = hashlib.sha1()
    for p in sorted(root.rglob("*")):
        if p.is_file() and p.name != "synth.json":
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


@pytest.mark.slow
def test_generation_is_deterministic_in_the_seed(tiny_source, tmp_path):
    """Same seed, same bytes, whether rendered in this process (the fixture) or by two worker processes."""
    again = S.generate(tmp_path / "again", profile="tiny", seed=0, progress=False, workers=2)
    other = S.generate(tmp_path / "other", profile="tiny", seed=1, progress=False)
    assert _digest(again.root) == _digest(tiny_source)
    assert _digest(other.root) != _digest(tiny_source)


def test_generated_folder_has_the_raw_m3t_layout(tiny_source):
    root = tiny_source
    coco = json.loads((root / "annotations" / "instances_rgb.json").read_text())
    assert [c["name"] for c in coco["categories"]] == list(M3T_CATEGORIES)
    assert [c["id"] for c in coco["categories"]] == list(range(1, 9))
    assert len(coco["images"]) == S.PROFILES["tiny"].total
    for img in coco["images"]:
        rgb = root / "images" / img["file_name"]
        assert rgb.name.endswith("_W.JPG") and rgb.exists()
        assert (rgb.parent / rgb.name.replace("_W.JPG", "_T.JPG")).exists()
        assert img["file_name"].split("/")[0] in S.PROJECTS
    for name in (
        "calibration/wide_camera.yaml",
        "registration/landmarks.json",
        "m3t.yaml",
        "ground_truth/homographies.yaml",
        "ground_truth/instances_thermal.json",
        "ground_truth/frames.json",
    ):
        assert (root / name).exists(), name


def test_thermal_capture_is_a_real_layout_rjpeg_with_capture_time(tiny_source):
    from harness.sensing import jpeg
    from harness.sensing.radiometry import read_rjpeg

    frames = json.loads((tiny_source / "ground_truth" / "frames.json").read_text())
    f = frames[0]
    rj = read_rjpeg(tiny_source / "images" / f["thermal_file"])
    assert rj.shape == (128, 160)
    assert rj.exif["Model"] == "M3T"
    assert jpeg.parse_exif_datetime(rj.exif["DateTimeOriginal"]).isoformat(sep=" ") == f["captured"]
    rgb_exif = jpeg.read_exif(tiny_source / "images" / f["file_name"])
    assert rgb_exif["Make"] == "DJI" and rgb_exif["DateTimeOriginal"].replace(":", "-", 2) == f["captured"]


def test_landmarks_are_noisy_clicks_of_the_true_homography(tiny_source):
    from harness.sensing.registration import load_homographies, read_landmarks, registration_error

    lm = read_landmarks(tiny_source / "registration" / "landmarks.json")
    true_h = load_homographies(tiny_source / "ground_truth" / "homographies.yaml")
    assert set(lm.group) == set(true_h)
    err = registration_error(lm, true_h)
    # click noise 0.8 RGB px (x0.57 in thermal px) and 0.35 thermal px per axis: ~0.7 px mean distance
    assert 0.3 < err["mean"] < 1.0
    assert err["max"] < 3.0


def _box_contrast(img: np.ndarray, box: list[float], ring: int = 3) -> tuple[float, float]:
    """(mean inside the box - mean of a ring around it, std of the ring)."""
    x0, y0, x1, y1 = (int(round(v)) for v in box)
    h, w = img.shape[:2]
    inner = img[max(y0, 0) : min(y1, h), max(x0, 0) : min(x1, w)]
    outer = img[max(y0 - ring, 0) : min(y1 + ring, h), max(x0 - ring, 0) : min(x1 + ring, w)].astype(np.float64)
    n_out = outer.size - inner.size
    ring_mean = (outer.sum() - inner.sum()) / max(n_out, 1)
    return float(inner.mean() - ring_mean), float(outer.std())


def test_category_signatures_in_the_true_temperature(tiny_source):
    """AC units and vents are warm, delamination a compact +-0.5..3 C patch, water seepage diffuse, paint peeling
    and efflorescence weak: measured on the true temperature maps inside the true boxes."""
    from harness.sensing.radiometry import read_thermal

    frames = json.loads((tiny_source / "ground_truth" / "frames.json").read_text())
    deltas: dict[str, list[float]] = {c: [] for c in M3T_CATEGORIES}
    for f in frames:
        stem = Path(f["file_name"]).name.replace("_W.JPG", "")
        project = f["file_name"].split("/")[0]
        temp, _ = read_thermal(tiny_source / "ground_truth" / "temperature" / project / f"{stem}.png")
        for o in f["objects"]:
            box = o["thermal_box"]
            if box[0] < 0 or box[1] < 0 or box[2] > 160 or box[3] > 128 or o["category"] == "window":
                continue
            deltas[o["category"]].append(_box_contrast(temp, box)[0])
        for o in f["objects"]:
            if o["category"] in ("delamination", "water_seepage", "paint_peeling", "efflorescence", "crack"):
                assert "delta_c" in o
                if o["category"] == "delamination":
                    assert 0.5 <= abs(o["delta_c"]) <= 3.0
                if o["category"] == "water_seepage":
                    assert -2.0 <= o["delta_c"] <= -0.5
                if o["category"] in ("paint_peeling", "efflorescence"):
                    assert abs(o["delta_c"]) <= 0.3
    assert all(d > 1.0 for d in deltas["ac_unit"] + deltas["vent"]), deltas
    # water seepage is diffuse: its cooling reaches well past the stain, so the ring around the box is about as cold
    assert deltas["water_seepage"] and all(abs(d) < 0.4 for d in deltas["water_seepage"]), deltas["water_seepage"]
    assert deltas["delamination"] and max(abs(d) for d in deltas["delamination"]) > 0.3


def test_delamination_is_nearly_invisible_in_rgb_and_cracks_are_visible(tiny_source):
    import cv2

    from harness.sensing.registration import load_homographies

    frames = json.loads((tiny_source / "ground_truth" / "frames.json").read_text())
    coco = json.loads((tiny_source / "annotations" / "instances_rgb.json").read_text())
    boxes = {a["id"]: a["bbox"] for a in coco["annotations"]}
    assert load_homographies(tiny_source / "ground_truth" / "homographies.yaml")
    contrast: dict[str, list[float]] = {"delamination": [], "crack": []}
    for f in frames:
        gray = cv2.imread(str(tiny_source / "images" / f["file_name"]), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        for o in f["objects"]:
            if o["category"] in contrast and o["id"] in boxes:
                x, y, w, h = boxes[o["id"]]
                x0, y0, x1, y1 = int(x), int(y), int(math.ceil(x + w)), int(math.ceil(y + h))
                patch = gray[y0:y1, x0:x1]
                # cracks: the darkest pixels stand well below the median; delamination: nearly uniform
                contrast[o["category"]].append(float(np.median(patch) - np.percentile(patch, 2)))
    assert contrast["crack"] and np.median(contrast["crack"]) > 15
    assert contrast["delamination"] and np.median(contrast["delamination"]) < np.median(contrast["crack"]) / 2
