"""The input guard's ``mismatched-pairs`` finding: RGB frames paired with another image's thermal frame (every
``thermal_file_name`` shifted by one) stop the preparation with the numbers; correct pairs pass; an accepted finding
labels the prepared set."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from harness.errors import DataError


def _coco(tmp_path: Path, shift: int = 0, n: int = 12) -> Path:
    from coco_rgbt_helpers import make_coco_rgbt, read_json, write_json

    root = make_coco_rgbt(tmp_path / "d", n=n)
    if shift:
        coco = read_json(root)
        names = [im["thermal_file_name"] for im in coco["images"]]
        for im, name in zip(coco["images"], names[shift:] + names[:shift]):
            im["thermal_file_name"] = name
        write_json(root, coco)
    return root


def _prepare(root: Path, tmp_path: Path, *accept: str):
    from coco_rgbt_helpers import prepare_coco_rgbt

    return prepare_coco_rgbt(root, tmp_path / "cache", *accept)


def test_thermal_files_shifted_by_one_image_stop_with_the_agreements_and_the_option(tmp_path):
    root = _coco(tmp_path, shift=1)
    with pytest.raises(DataError) as err:
        _prepare(root, tmp_path)
    text = str(err.value)
    assert "mismatched-pairs: 12 of 12 compared RGB frames agree better with another image's thermal frame" in text
    assert "median: own pairs 0." in text and "other pairings 0." in text
    assert "e.g. rgb/001.png: r 0." in text and "with thermal/001.png" in text  # its true partner, given to image 0
    assert "--set 'inputs.accept=[mismatched-pairs]'" in text
    ds = _prepare(root, tmp_path, "mismatched-pairs")  # accepted: read from the cache, labelled
    assert ds.from_cache and [r["kind"] for r in ds.input_risks] == ["mismatched-pairs"]
    assert ds.input_risks[0]["message"].startswith("12 of 12 compared RGB frames")


def test_correct_pairs_pass(tmp_path):
    assert _prepare(_coco(tmp_path), tmp_path).input_risks == []


def test_fewer_than_four_samples_of_a_size_are_not_compared(tmp_path):
    from harness.input_guard import pair_summary

    ds = _prepare(_coco(tmp_path, shift=1, n=3), tmp_path)  # shifted, but too few to tell: no finding
    assert ds.input_risks == [] and pair_summary(ds)["compared"] == 0


def _frames(k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A scene of its own (a bright square at a place of ``k``): its RGB frame and its temperatures."""
    t = 20.0 + 0.1 * rng.standard_normal((48, 64))
    t[8 + 3 * k : 20 + 3 * k, 4 + 5 * k : 16 + 5 * k] += 8.0
    rgb = np.repeat(np.clip((t - 15) * 20, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
    return rgb, t.astype(np.float32)


def test_a_sharper_thermal_frame_that_agrees_with_every_rgb_frame_beats_no_one():
    from harness.input_guard import pair_statistics

    r = np.full((6, 6), 0.3)
    np.fill_diagonal(r, 0.5)
    r[:, 2] = 0.8  # thermal frame 2 agrees with every RGB frame better than they agree with their own
    stats = pair_statistics(r)
    assert stats["compared"] == 6 and stats["beaten"] == []
    r[1, 0], r[0, 0] = 0.9, 0.2  # RGB 1 with thermal 0 beats both given pairs (0.5 and 0.2) by 0.4
    assert [b[:2] for b in pair_statistics(r)["beaten"]] == [(1, 0)]


def test_missing_temperatures_are_left_out_not_read_as_zero():
    from harness.input_guard import pair_agreement

    rng = np.random.default_rng(1)
    rgbs, temps = zip(*(_frames(k, rng) for k in range(4)))
    holed = [t.copy() for t in temps]
    holed[0][30:, 40:] = np.nan  # a corner without temperatures, away from the square
    r, r_holed = pair_agreement(rgbs, temps), pair_agreement(rgbs, holed)
    assert np.isfinite(r_holed).all()
    assert abs(r_holed[0, 0] - r[0, 0]) < 0.05  # the rest of the frame agrees as before
    zeroed = [np.nan_to_num(t, nan=0.0) for t in holed]  # read as 0 C: a strong false edge
    assert pair_agreement(rgbs, zeroed)[0, 0] < r[0, 0] - 0.2
    big = [np.repeat(np.repeat(t, 10, 0), 10, 1) for t in holed]  # 480x640: compared at 64 px, the hole's cells
    big_rgbs = [np.repeat(np.repeat(c, 10, 0), 10, 1) for c in rgbs]  # missing, not averaged with zeros
    assert abs(pair_agreement(big_rgbs, big)[0, 0] - r[0, 0]) < 0.1
    holed[1][:] = np.nan
    assert np.isnan(pair_agreement(rgbs, holed)[:, 1]).all()  # no valid temperature: no agreement, not zero


def test_scenes_of_their_own_are_told_apart_from_a_shift():
    from harness.input_guard import MAX_BEATEN, pair_agreement, pair_statistics

    rng = np.random.default_rng(2)
    rgbs, temps = zip(*(_frames(k, rng) for k in range(6)))
    given = pair_statistics(pair_agreement(rgbs, temps))
    shifted = pair_statistics(pair_agreement(rgbs, temps[1:] + temps[:1]))
    assert given["beaten"] == [] and np.median(given["own"]) > 0.8
    assert len(shifted["beaten"]) > MAX_BEATEN * shifted["compared"]
    assert {(i, j) for i, j, _, _ in shifted["beaten"]} == {(i, (i - 1) % 6) for i in range(6)}


def test_the_guide_states_the_rule_the_guard_applies():
    from harness import input_guard as g

    doc = (Path(__file__).resolve().parent.parent / "docs" / "datasets.md").read_text()
    row = next(line for line in doc.splitlines() if line.startswith("| `mismatched-pairs` |"))
    for said in (
        f"more than {g.MAX_BEATEN:.0%}".replace("%", " %"),
        f"at most {g.PAIR_SAMPLES} of each frame size, in runs of {g.PAIR_RUN} consecutive",
        f"at {g.PAIR_GRID} px, by {g.BEATEN_BY} or more, and at least {g.BEATEN_AT}",
        f"Fewer than {g.MIN_PAIRS} samples of a size are not compared",
    ):
        assert said in row, said
