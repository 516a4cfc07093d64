"""RGB -> thermal registration: landmarks, similarity parameters, automatic ECC, groups, files, errors."""

from __future__ import annotations

import json
from datetime import datetime

import numpy as np
import pytest

from harness.errors import DataError
from harness.sensing import registration as reg
from harness.sensing.registration import (
    Landmarks,
    apply_homography,
    corner_error,
    estimate_homography_auto,
    group_by_capture_time,
    homography_from_focal_lengths,
    homography_from_landmarks,
    homography_from_similarity,
    image_center,
    load_homographies,
    read_landmarks,
    registration_error,
    save_homographies,
)
from sensing_scenes import SCENE_RGB, SCENE_TH, focal_prior, render_pair, scene_truth

RGB_SIZE, TH_SIZE = (4000, 3000), (640, 512)


def _true_h() -> np.ndarray:
    H = homography_from_similarity(12.0, -7.0, 1.2, 0.2734, image_center(RGB_SIZE), image_center(TH_SIZE))
    H[2, :2] = [3e-7, -2e-7]  # a little perspective
    return H / H[2, 2]


def _landmarks(n=20, seed=0, noise=0.0, H=None):
    rng = np.random.default_rng(seed)
    H = _true_h() if H is None else H
    rgb = rng.uniform([1000, 800], [3000, 2200], size=(n, 2))
    th = apply_homography(H, rgb) + rng.normal(0, noise, (n, 2)) if noise else apply_homography(H, rgb)
    return rgb, th


# ---------------------------------------------------------------------------------------------- landmarks
def test_landmarks_least_squares_recovers_the_homography():
    rgb, th = _landmarks()
    H = homography_from_landmarks(rgb, th, "lsq")
    test_rgb, test_th = _landmarks(50, seed=9)
    assert reg.reprojection_errors(H, test_rgb, test_th).max() < 0.1
    assert corner_error(H, _true_h(), TH_SIZE).max() < 0.1


def test_landmarks_ransac_ignores_outliers_that_break_least_squares():
    rgb, th = _landmarks(30, seed=1)
    th_bad = th.copy()
    th_bad[:6] += np.array([[40, -25], [-30, 60], [80, 5], [-50, -50], [25, 90], [70, -40]])
    fit = reg.fit_landmarks(rgb, th_bad, "ransac", ransac_threshold=2.0)
    H, inliers = fit.H, fit.inliers
    assert not inliers[:6].any() and inliers[6:].all()
    test_rgb, test_th = _landmarks(50, seed=9)
    assert reg.reprojection_errors(H, test_rgb, test_th).max() < 0.1
    H_lsq = homography_from_landmarks(rgb, th_bad, "lsq")
    assert reg.reprojection_errors(H_lsq, test_rgb, test_th).mean() > 1.0  # what RANSAC protects against


def test_landmark_errors_are_clear():
    rgb, th = _landmarks(3)
    with pytest.raises(DataError, match="at least 4"):
        homography_from_landmarks(rgb, th)
    with pytest.raises(DataError, match="collinear"):
        line = np.stack([np.arange(6.0), np.arange(6.0)], axis=1)
        homography_from_landmarks(line, line * 0.3)
    with pytest.raises(DataError, match="unknown landmark method"):
        homography_from_landmarks(*_landmarks(5), method="magic")


# ---------------------------------------------------------------------------------------------- similarity, optics
def test_similarity_homography_by_hand():
    H = homography_from_similarity(5.0, -3.0, 90.0, 0.5, rgb_center=(100.0, 50.0), thermal_center=(20.0, 10.0))
    # x - c_rgb = (10, 0); R(90) [1, 0] = (0, -1) on screen (counter-clockwise); * 0.5 -> (0, -5)
    np.testing.assert_allclose(apply_homography(H, np.array([[110.0, 50.0]])), [[20 + 0 + 5, 10 - 5 - 3]], atol=1e-9)
    np.testing.assert_allclose(apply_homography(H, np.array([[100.0, 50.0]])), [[25.0, 7.0]], atol=1e-9)
    params = reg.similarity_from_homography(H, (100.0, 50.0), (20.0, 10.0))
    assert params == pytest.approx({"tx": 5.0, "ty": -3.0, "theta_deg": 90.0, "scale": 0.5})
    with pytest.raises(DataError, match="positive"):
        homography_from_similarity(0, 0, 0, 0.0)


def test_focal_length_prior_for_the_m3t():
    f_th = reg.focal_length_px(focal_mm=9.1, pixel_pitch_mm=0.012)
    assert f_th == pytest.approx(758.33, abs=0.01)
    assert reg.focal_length_px(focal_35mm=40, image_size=TH_SIZE) == pytest.approx(757.8, abs=1.0)
    f_rgb = reg.focal_length_px(focal_35mm=24, image_size=RGB_SIZE)
    H = homography_from_focal_lengths(f_rgb, f_th, RGB_SIZE, TH_SIZE)
    np.testing.assert_allclose(apply_homography(H, np.array([image_center(RGB_SIZE)])), [image_center(TH_SIZE)])
    assert H[0, 0] == pytest.approx(f_th / f_rgb)
    with pytest.raises(DataError, match="needs"):
        reg.focal_length_px(focal_mm=9.1)


# ---------------------------------------------------------------------------------------------- automatic


@pytest.mark.parametrize("seed", [1, 2])
def test_automatic_registration_recovers_a_known_misalignment(seed):
    H_true = scene_truth()
    rgb, thermal = render_pair(seed, H_true, SCENE_RGB, SCENE_TH)
    start = corner_error(focal_prior(), H_true, SCENE_TH)
    assert np.median(start) > 3.0  # the prior is off by several pixels (1.5 deg, 2 % scale, (3, -2) px)
    res = estimate_homography_auto(rgb, thermal, init=focal_prior())
    assert res.ok, res.reason
    assert np.median(corner_error(res.H, H_true, SCENE_TH)) < 1.0
    assert res.correlation > res.initial_correlation


def test_automatic_registration_rejects_a_scrambled_pair():
    H_true = scene_truth()
    rgb, _ = render_pair(1, H_true, SCENE_RGB, SCENE_TH)
    _, other = render_pair(77, H_true, SCENE_RGB, SCENE_TH)  # the thermal frame of another facade
    res = estimate_homography_auto(rgb, other, init=focal_prior())
    assert not res.ok and "correlation" in res.reason
    np.testing.assert_allclose(res.H, reg.normalize(focal_prior()))  # nothing is made up: H stays the prior
    rng = np.random.default_rng(0)
    _, thermal = render_pair(1, H_true, SCENE_RGB, SCENE_TH)
    blocks = thermal.reshape(4, 32, 4, 40).transpose(0, 2, 1, 3).reshape(16, 32, 40)[rng.permutation(16)]
    shuffled = np.ascontiguousarray(blocks.reshape(4, 4, 32, 40).transpose(0, 2, 1, 3).reshape(128, 160))
    assert not estimate_homography_auto(rgb, shuffled, init=focal_prior()).ok


def test_structure_images_are_bounded_and_modality_agnostic():
    rgb, thermal = render_pair(3, scene_truth(), SCENE_RGB, SCENE_TH)
    for img in (rgb, thermal, (thermal * 10).astype(np.uint8)):
        s = reg.structure_image(img)
        assert s.dtype == np.float32 and s.min() >= 0 and s.max() < 1


# ---------------------------------------------------------------------------------------------- groups and files
def test_groups_from_capture_time():
    times = {
        "a": "2022:07:23 15:12:19",
        "b": "2022:07:23 15:13:38",
        "c": datetime(2022, 7, 23, 15, 40, 0),
        "d": "2022:07:23 15:41:00",
        "e": "2022:07:24 09:00:00",
    }
    assert group_by_capture_time(times, gap_s=300) == {"a": "G01", "b": "G01", "c": "G02", "d": "G02", "e": "G03"}
    assert set(group_by_capture_time(times, gap_s=86400).values()) == {"G01"}
    with pytest.raises(DataError, match="no capture time for 1 capture"):
        group_by_capture_time({"a": "2022:07:23 15:12:19", "x": None})


def test_capture_time_from_exif(tmp_path):
    from harness.sensing.radiometry import write_rjpeg

    path = write_rjpeg(
        tmp_path / "t.jpg", np.full((8, 8), 25.0, np.float32), exif={"DateTimeOriginal": "2023:03:04 05:06:07"}
    )
    assert reg.capture_time(path) == datetime(2023, 3, 4, 5, 6, 7)


def test_homographies_file_round_trip_and_hand_edits(tmp_path):
    path = tmp_path / "H.yaml"
    H1 = _true_h()
    entry = reg.entry_from_similarity({"tx": 1.0, "ty": 2.0, "theta_deg": 0.5, "scale": 0.27}, RGB_SIZE, TH_SIZE)
    save_homographies(path, {"P1": H1, "P2": entry})
    text = path.read_text()
    assert "similarity" in text and "thermal pixel ~ H @" in text
    loaded = load_homographies(path)
    np.testing.assert_allclose(loaded["P1"], H1, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(loaded["P2"], entry.H)
    # a person changes the similarity by hand: the loaded H follows
    path.write_text(text.replace("tx: 1.0", "tx: 4.0"))
    moved = load_homographies(path)["P2"]
    np.testing.assert_allclose(apply_homography(moved, [[0, 0]]) - apply_homography(entry.H, [[0, 0]]), [[3.0, 0.0]])
    path.write_text("schema: 1\ngroups:\n  P3: {H: [[1, 0], [0, 1]]}\n")
    with pytest.raises(DataError, match=r"H.yaml: group 'P3': H has shape"):
        load_homographies(path)
    path.write_text("schema: 1\ngroups:\n  P3: {method: auto}\n")
    with pytest.raises(DataError, match="needs 'H' or 'similarity'"):
        load_homographies(path)


# ---------------------------------------------------------------------------------------------- landmarks files, error
def _write_csv(path, rows):
    path.write_text(
        "scene,group,rgb_x,rgb_y,thermal_x,thermal_y\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n"
    )


def test_landmarks_files_csv_and_json(tmp_path):
    rgb, th = _landmarks(6)
    rows = [("s1" if i < 3 else "s2", "P1", *rgb[i], *th[i]) for i in range(6)]
    _write_csv(tmp_path / "lm.csv", rows)
    lm = read_landmarks(tmp_path / "lm.csv")
    assert len(lm) == 6 and lm.scene[:4] == ["s1", "s1", "s1", "s2"] and lm.groups() == ["P1"]
    np.testing.assert_allclose(lm.rgb, rgb)
    reg.write_landmarks(tmp_path / "lm.json", lm)
    again = read_landmarks(tmp_path / "lm.json")
    np.testing.assert_allclose(again.thermal, lm.thermal)
    (tmp_path / "bad.csv").write_text("scene,rgb_x,rgb_y,thermal_x\ns,1,2,3\n")
    with pytest.raises(DataError, match=r"bad.csv: CSV header lacks \['thermal_y'\]"):
        read_landmarks(tmp_path / "bad.csv")
    (tmp_path / "bad2.csv").write_text("scene,rgb_x,rgb_y,thermal_x,thermal_y\ns,1,2,3,x\n")
    with pytest.raises(DataError, match="bad2.csv: line 2"):
        read_landmarks(tmp_path / "bad2.csv")
    (tmp_path / "bad.json").write_text(json.dumps({"landmarks": [{"scene": "s", "rgb": [1]}]}))
    with pytest.raises(DataError, match="bad.json: landmark 0"):
        read_landmarks(tmp_path / "bad.json")


def test_registration_error_statistics_by_hand():
    H = np.eye(3)
    rgb = np.array([[0, 0], [10, 0], [0, 10], [10, 10]], dtype=float)
    th = rgb + np.array([[3, 4], [0, 1], [0, 2], [6, 8]])  # errors 5, 1, 2, 10
    lm = Landmarks(rgb, th, ["a", "a", "b", "b"], ["P1"] * 4)
    res = registration_error(lm, H)
    assert res["n"] == 4 and res["mean"] == pytest.approx(4.5) and res["median"] == pytest.approx(3.5)
    assert res["p95"] == pytest.approx(5 + 0.85 * 5)  # sorted 1, 2, 5, 10; rank 2.85
    assert res["per_scene"]["a"]["mean"] == pytest.approx(3.0) and res["per_scene"]["b"]["mean"] == pytest.approx(6.0)
    inside = registration_error(lm, {"P1": H}, support={"P1": (0, 0, 13, 13)})
    assert inside["n"] == 3 and inside["outside_support"] == 1  # (16, 18) lies outside the crop
    with pytest.raises(DataError, match="no homography for group 'P1'"):
        registration_error(lm, {"P2": H})


def test_leave_one_out_is_honest_about_noise():
    rgb, th = _landmarks(12, seed=4, noise=0.5)
    lm = Landmarks(rgb, th, ["s"] * 12, ["P1"] * 12)
    loo = reg.leave_one_out_errors(lm)
    fit = reg.reprojection_errors(homography_from_landmarks(rgb, th), rgb, th)
    assert np.isfinite(loo).all() and loo.mean() > fit.mean()  # held-out points are not flattered


def test_registration_error_command(tmp_path, cli_runner):
    rgb, th = _landmarks(16, seed=2, noise=0.3)
    rows = [(f"s{i % 3}", "P1" if i < 8 else "P2", *rgb[i], *th[i]) for i in range(16)]
    _write_csv(tmp_path / "lm.csv", rows)
    save_homographies(
        tmp_path / "H.yaml",
        {"P1": _true_h(), "P2": reg.HomographyEntry(_true_h(), "landmarks", None, RGB_SIZE, TH_SIZE)},
    )
    out = tmp_path / "err.json"
    res = cli_runner(
        [
            "sensing",
            "registration-error",
            "--landmarks",
            str(tmp_path / "lm.csv"),
            "--homographies",
            str(tmp_path / "H.yaml"),
            "--dataset",
            "m3t",
            "--store",
            str(tmp_path / "store"),
            "--out",
            str(out),
        ]
    )
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert data["n"] == 16 and 0.1 < data["mean"] < 1.0 and set(data["per_scene"]) == {"s0", "s1", "s2"}
    assert (tmp_path / "store" / "m3t" / "_sensing" / "registration_error.json").exists()
    lines = res.output.splitlines()
    assert any("mean (px)" in ln and "P95 (px)" in ln for ln in lines)
    header = next(ln for ln in lines if ln.startswith("scene"))
    rows_out = [ln for ln in lines if ln.startswith("s0") or ln.startswith("s1")]
    assert all(len(r) == len(header) for r in rows_out)  # columns line up
    loo = cli_runner(
        ["sensing", "registration-error", "--landmarks", str(tmp_path / "lm.csv"), "--out", str(tmp_path / "loo.json")]
    )
    assert loo.exit_code == 0 and "leave-one-out" in loo.output


def test_register_command_from_landmarks_similarity_and_images(tmp_path, cli_runner):
    import cv2

    rgb, th = _landmarks(10, seed=5)
    _write_csv(tmp_path / "lm.csv", [("s", "P1", *rgb[i], *th[i]) for i in range(10)])
    out = tmp_path / "H.yaml"

    def register(*how: str):
        res = cli_runner(["sensing", "register", *how, "--out", str(out)])
        assert res.exit_code == 0, res.output
        return res

    sizes = ["--rgb-size", "4000x3000", "--thermal-size", "640x512"]
    register("--landmarks", str(tmp_path / "lm.csv"), *sizes)
    register("--similarity", "P2=1,2,0.5,0.27", *sizes)
    H_true = scene_truth()
    scene_rgb, scene_th = render_pair(2, H_true, SCENE_RGB, SCENE_TH)
    cv2.imwrite(str(tmp_path / "rgb.png"), scene_rgb[:, :, ::-1])
    from harness.sensing.radiometry import write_thermal

    write_thermal(tmp_path / "th.tif", scene_th, unit="celsius")
    save_homographies(tmp_path / "init.yaml", {"P3": focal_prior()})
    images = f"P3={tmp_path / 'rgb.png'},{tmp_path / 'th.tif'}"
    res = register("--auto", images, "--start-homographies", str(tmp_path / "init.yaml"))
    Hs = load_homographies(out)
    assert set(Hs) == {"P1", "P2", "P3"}
    np.testing.assert_allclose(apply_homography(Hs["P1"], rgb), th, atol=0.05)
    assert np.median(corner_error(Hs["P3"], H_true, SCENE_TH)) < 1.0
    assert "ok" in res.output


def test_sensing_context_registers_unknown_groups_automatically_or_refuses():
    from harness.config import load_config
    from harness.sensing.pipeline import SensingContext

    H_true = scene_truth()
    rgb, thermal = render_pair(2, H_true, SCENE_RGB, SCENE_TH)
    ctx = SensingContext.from_config(load_config())
    ir8 = np.zeros(thermal.shape, np.uint8)
    pair = ctx.align_capture(rgb, thermal, ir8, np.array([[10, 10, 40, 30]]), np.array([0]), "G01", prior=focal_prior())
    assert np.median(corner_error(ctx.entries["G01"].H, H_true, SCENE_TH)) < 1.0 and ctx.auto_results["G01"].ok
    np.testing.assert_array_equal(
        pair.thermal, thermal[pair.origin[1] :, pair.origin[0] :][: pair.size[1], : pair.size[0]]
    )
    _, other = render_pair(77, H_true, SCENE_RGB, SCENE_TH)
    with pytest.raises(DataError, match="group 'G02': automatic registration rejected"):
        ctx.align_capture(rgb, other, ir8, np.zeros((0, 4)), np.zeros(0), "G02", prior=focal_prior())
