"""The synthetic generator's physics lands the sensor-level tables near the M3T paper's, on the `small` profile.

Frames of `small` (thermal 320x256) are rendered in memory, thermal side only, six per project; the analyses
run on the true thermal-frame boxes. Paper (M3T): delamination R(2/5/10/15 px) 99.6 / 97.2 / 88.4 / 77.0 %,
water seepage 100.2 / 100.6 / 101.5 / 103.5 %, registration error median 3.38 px (mean 3.87, P95 7.43).
"""

from __future__ import annotations

import numpy as np
import pytest

from adapters.datasets import synthetic as S
from adapters.datasets.m3t import M3T_CATEGORIES
from adapters.datasets.synthetic.generation import _session

FRAMES_PER_PROJECT = 12


@pytest.fixture(scope="module")
def small_frames() -> list[tuple[str, S.Session, S.Frame]]:
    prof = S.PROFILES["small"]
    rig = S.Rig.for_profile(prof)
    out = []
    for p, project in enumerate(S.PROJECTS):
        session, _ = _session(rig, 0, project, 0)
        canvas = S.canvas_for_session(rig, session)
        for k in range(FRAMES_PER_PROJECT):
            rng = np.random.default_rng(np.random.SeedSequence((0, p, k)))
            frame = S.render_frame(rig, session, canvas, None, S.LOOKS[project], rng, 0.5)
            out.append((project, session, frame))
    return out


def _retained(frames: list[tuple[str, S.Session, S.Frame]], category: str) -> tuple[int, np.ndarray]:
    """(boxes, R_c(d) in % for d = 2, 5, 10, 15 px), the displacement study's definition."""
    from harness.sensing.analyses import box_amplitudes

    tw, th = S.PROFILES["small"].thermal_size
    rows = []
    for _, _, frame in frames:
        boxes = [np.clip(o.box, 0, [tw, th, tw, th]) for o in frame.objects if o.category == category]
        boxes = [b for b in boxes if (b[2] - b[0]) >= 2 and (b[3] - b[1]) >= 2]
        if boxes:
            rows.append(box_amplitudes(frame.temperature, np.array(boxes), (2, 5, 10, 15)))
    a = np.mean(np.concatenate(rows), axis=0)
    return sum(len(r) for r in rows), 100.0 * a[1:] / a[0]


def test_delamination_loses_c2_like_the_papers_compact_patches(small_frames):
    n, r = _retained(small_frames, "delamination")
    assert n >= 20
    assert 93 <= r[1] <= 100, r  # R(5 px)
    assert 70 <= r[3] <= 85, r  # R(15 px)
    assert r[0] > r[1] > r[2] > r[3]


def test_water_seepage_keeps_its_c2_at_every_shift(small_frames):
    n, r = _retained(small_frames, "water_seepage")
    assert n >= 8
    assert np.all((95 <= r) & (r <= 110)), r


def test_vents_have_a_thermal_signature_and_a_visible_grille(small_frames):
    """A vent is warmer than the wall around it in the thermal image."""
    tw, th = S.PROFILES["small"].thermal_size
    deltas = []
    for _, _, frame in small_frames:
        t = frame.true_temperature
        for o in frame.objects:
            if o.category != "vent":
                continue
            x0, y0, x1, y1 = (int(round(v)) for v in o.box)
            if x0 < 3 or y0 < 3 or x1 > tw - 3 or y1 > th - 3:
                continue
            inner = t[y0:y1, x0:x1]
            ring = np.concatenate(
                [
                    t[y0 - 3 : y0, x0:x1].ravel(),
                    t[y1 : y1 + 3, x0:x1].ravel(),
                    t[y0:y1, x0 - 3 : x0].ravel(),
                    t[y0:y1, x1 : x1 + 3].ravel(),
                ]
            )
            deltas.append(float(inner.mean() - np.median(ring)))
    assert len(deltas) >= 8 and np.median(deltas) > 1.0, deltas


def test_registration_error_of_human_clicks_is_a_few_thermal_pixels(small_frames):
    """Landmarks picked on `small` frames: leave-one-out registration error near the paper's median, and the
    error under the true homography (the clicking alone) of the same size."""
    from harness.sensing.registration import Landmarks, leave_one_out_errors, registration_error

    prof = S.PROFILES["small"]
    rig = S.Rig.for_profile(prof)
    rgb, thermal, scene, group = [], [], [], []
    truth = {}
    for project, session, frame in small_frames:
        rng = np.random.default_rng(np.random.SeedSequence((1, len(scene))))
        for lm in S.pick_landmarks(frame, session, rig, rng, limit=12)[:5]:
            rgb.append(lm["rgb"])
            thermal.append(lm["thermal"])
            scene.append(f"{project}-{len(scene)}")
            group.append(session.name)
        truth[session.name] = session.homography
    lm = Landmarks(np.array(rgb), np.array(thermal), scene, group)
    loo = leave_one_out_errors(lm)
    true = registration_error(lm, truth)
    assert len(loo) >= 100
    assert 2.5 <= float(np.median(loo)) <= 4.5, np.median(loo)
    assert 2.5 <= true["median"] <= 4.5, true["median"]
    assert np.array_equal(lm.thermal, np.round(lm.thermal))  # clicks snap to whole thermal pixels


def test_precise_clicks_stay_for_the_test_profile():
    assert S.PROFILES["tiny"].clicks == "precise" and S.PROFILES["small"].clicks == "human"
    rig = S.Rig.for_profile(S.PROFILES["small"])
    pts = np.array([[100.0, 80.0]] * 400)
    rgb, th = S.click_landmarks(pts, pts, rig, np.random.default_rng(0), "precise")
    assert np.abs(th - pts).mean() < 0.5
    with pytest.raises(ValueError, match="unknown click model"):
        S.click_landmarks(pts, pts, rig, np.random.default_rng(0), "sloppy")


def test_categories_are_the_m3t_order():
    m3t_order = "window ac_unit vent crack paint_peeling efflorescence delamination water_seepage"
    assert M3T_CATEGORIES == tuple(m3t_order.split())


def test_no_import_circle_between_the_generator_and_the_commands():
    """The generator imports no command module, and `harness/` imports nothing from `adapters/`."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]

    def imports(path: Path) -> set[str]:
        out = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                out.add(node.module)
            elif isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
        return out

    gen = set().union(*(imports(p) for p in (root / "adapters" / "datasets" / "synthetic").glob("*.py")))
    assert "adapters.datasets.synthetic.generation" in gen  # the package's modules were read
    assert not any(m.startswith("harness.commands") for m in gen), gen
    offenders = {
        str(p.relative_to(root)): sorted(m for m in imports(p) if m.split(".")[0] == "adapters")
        for p in (root / "harness").rglob("*.py")
    }
    assert not {k: v for k, v in offenders.items() if v}


def test_a_new_generator_version_regenerates_and_changes_the_cache_key(tmp_path, monkeypatch):
    import json

    from harness.errors import DataError

    monkeypatch.setenv(S.ENV_DATA, str(tmp_path / "data"))
    first = S.open_synthetic(profile="tiny", seed=0).fingerprint()
    marker = S.default_root("tiny", 0) / S.MARKER
    info = json.loads(marker.read_text())
    assert info["generator_version"] == S.GENERATOR_VERSION
    marker.write_text(json.dumps({**info, "generator_version": S.GENERATOR_VERSION - 1}))
    second = S.open_synthetic(profile="tiny", seed=0).fingerprint()  # the default folder is regenerated
    assert json.loads(marker.read_text())["generator_version"] == S.GENERATOR_VERSION
    assert second != first
    marker.write_text(json.dumps({**info, "generator_version": S.GENERATOR_VERSION - 1}))
    with pytest.raises(DataError, match="regenerate it with `harness synth"):
        S.open_synthetic(S.default_root("tiny", 0), profile="tiny")  # a folder the user named is not replaced
