"""Registration lives in one package (``harness.sensing.registration``): one landmark fit, one record of its quality,
one implementation of the homography maths, used by the command, the dataset adapters and the generator alike."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from harness.api import PrepareReport
from harness.sensing.registration import (
    HomographyEntry,
    LandmarkFit,
    apply_homography,
    fit_landmarks,
    homography_from_similarity,
    load_homography_entries,
)

#: The quality fields of a landmark fit, wherever it is recorded.
LANDMARK_QUALITY = ["pairs", "inliers", "rms_px"]
ROOT = Path(__file__).resolve().parents[1]
HOME = "harness/sensing/registration/"


def test_a_landmark_fit_is_one_record_with_one_set_of_quality_fields():
    rng = np.random.default_rng(4)
    H_true = homography_from_similarity(3.0, -2.0, 0.8, 0.31, (479.5, 359.5), (159.5, 127.5))
    rgb = rng.uniform([50, 40], [900, 680], size=(20, 2))
    thermal = apply_homography(H_true, rgb) + rng.normal(0, 0.2, (20, 2))
    thermal[:3] += 25.0  # three mis-clicks
    fit = fit_landmarks(rgb, thermal, "ransac", ransac_threshold=1.5)
    assert isinstance(fit, LandmarkFit) and fit.pairs == 20 and not fit.inliers[:3].any() and fit.inliers[3:].all()
    q = fit.quality()
    assert list(q) == LANDMARK_QUALITY
    assert q == {"pairs": 20, "inliers": 17, "rms_px": round(fit.rms_px, 4)} and 0.05 < fit.rms_px < 0.5
    entry = fit.entry((960, 720), (320, 256))
    assert isinstance(entry, HomographyEntry) and entry.method == "landmarks" and entry.quality == q
    assert fit_landmarks(rgb[3:], thermal[3:]).quality()["inliers"] == 17  # least squares keeps every pair


def test_the_register_command_and_the_dataset_record_the_same_fit(tiny_source, tmp_path, cli_runner):  # noqa: F811
    """`harness sensing register --landmarks` and the M3T adapter's own registration fit each group once, through
    the same function, and write the same quality fields."""
    from adapters.datasets.m3t import open_m3t

    out = tmp_path / "homographies.yaml"
    res = cli_runner(
        ["sensing", "register", "--landmarks", str(tiny_source / "registration" / "landmarks.json"), "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    written = load_homography_entries(out)
    source = open_m3t(tiny_source)
    report = PrepareReport()
    assert len(list(source.samples(report))) == len(source) and not report.skipped
    used = source._aligner.ctx.entries  # type: ignore[attr-defined]
    assert sorted(written) == sorted(used) == ["P1-01", "P2-01", "P3-01", "P4-01", "P5-01"]
    for group, entry in written.items():
        assert entry.method == used[group].method == "landmarks"
        assert list(entry.quality) == list(used[group].quality) == LANDMARK_QUALITY
        assert entry.quality["pairs"] == used[group].quality["pairs"] >= 4
        # the dataset fits in the undistorted image's frame, the command in the calibration's: the same pairs
        assert entry.quality["rms_px"] == pytest.approx(used[group].quality["rms_px"], abs=2e-3)
        assert source.registration[group] == {
            "source": "landmarks",
            "pairs": entry.quality["pairs"],
            "rms_px": used[group].quality["rms_px"],
        }


def _python_files() -> list[Path]:
    return sorted(
        p for folder in ("harness", "adapters", "benchmarks", "plugins") for p in (ROOT / folder).rglob("*.py")
    )


def test_the_homography_maths_has_one_implementation_that_every_caller_uses():
    """No second definition of the shared maths, no landmark fit or ``cv2.findHomography`` outside the
    registration package, and no dataset adapter that borrows the M3T plugin's helpers."""
    shared = {
        "apply_homography",
        "project_points",
        "homography_from_landmarks",
        "fit_landmarks",
        "focal_length_px",
        "homography_from_focal_lengths",
        "focal_prior",
        "plane_homography",
        "change_camera",
    }
    defined: dict[str, list[str]] = {}
    outside: list[str] = []
    borrowers: list[str] = []
    for path in _python_files():
        rel = path.relative_to(ROOT).as_posix()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef) and node.name in shared:
                defined.setdefault(node.name, []).append(rel)
            elif isinstance(node, ast.Call) and not rel.startswith(HOME):
                name = getattr(node.func, "attr", None) or getattr(node.func, "id", None)
                if name in ("findHomography", "homography_from_landmarks"):
                    outside.append(f"{rel}:{node.lineno} {name}")
            elif (
                isinstance(node, ast.ImportFrom)
                and node.module == "adapters.datasets.m3t"
                and rel.startswith("adapters/datasets/")
                and not rel.startswith("adapters/datasets/synthetic/")
            ):
                borrowers.append(rel)
    assert {n: where for n, where in defined.items() if len(where) != 1 or not where[0].startswith(HOME)} == {}
    assert outside == []
    assert borrowers == []
    assert sorted(defined) == sorted(shared)  # the scan saw every one of them
