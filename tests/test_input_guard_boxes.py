"""The input guard's ``misplaced-boxes`` finding: boxes that sit on image structure far better read another way (as
centres, or as the previous image's) stop the preparation naming that reading and the numbers; correct boxes pass; an
accepted finding labels the prepared set."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import pytest

from harness.errors import DataError

Coco = dict[str, Any]


def _as_centres(coco: Coco) -> None:
    for a in coco["annotations"]:
        x, y, w, h = a["bbox"]
        a["bbox"] = [x + w / 2, y + h / 2, w, h]


def _ids_shifted(coco: Coco) -> None:
    for a in coco["annotations"]:
        a["image_id"] = a["image_id"] % len(coco["images"]) + 1


def _coco(tmp_path: Path, edit: Callable[[Coco], None] | None = None, n: int = 12) -> Path:
    from coco_rgbt_helpers import make_coco_rgbt, read_json, write_json

    root = make_coco_rgbt(tmp_path / "d", n=n)
    if edit is not None:
        coco = read_json(root)
        edit(coco)
        write_json(root, coco)
    return root


def _prepare(root: Path, tmp_path: Path, *accept: str):
    from coco_rgbt_helpers import prepare_coco_rgbt

    return prepare_coco_rgbt(root, tmp_path / "cache", *accept)


@pytest.mark.parametrize(
    "edit, says",
    [
        (_as_centres, "boxes read as centre x, centre y, w, h sit on image structure better: in-box contrast"),
        (_ids_shifted, "each image's boxes read as the previous image's (image ids shifted by +1) sit on image"),
    ],
    ids=["boxes as centres", "image ids shifted"],
)
def test_misread_boxes_stop_naming_the_reading_that_fits_and_the_option(tmp_path, edit, says):
    root = _coco(tmp_path, edit)
    with pytest.raises(DataError) as err:
        _prepare(root, tmp_path)
    text = " ".join(str(err.value).split())
    assert f"misplaced-boxes: {says}" in text
    assert "(given), higher for 100% of" in text
    assert "--set 'inputs.accept=[misplaced-boxes]'" in text
    ds = _prepare(root, tmp_path, "misplaced-boxes")  # accepted: read from the cache, labelled
    assert ds.from_cache and [r["kind"] for r in ds.input_risks] == ["misplaced-boxes"]
    assert " ".join(ds.input_risks[0]["message"].split()).startswith(says)


def test_correct_boxes_pass(tmp_path):
    assert _prepare(_coco(tmp_path), tmp_path).input_risks == []


def test_a_kind_the_guard_knows(tmp_path):
    from harness.input_guard import KINDS, settings

    assert "misplaced-boxes" in KINDS
    assert settings({"inputs": {"accept": ["misplaced-boxes"]}})[0] == {"misplaced-boxes"}


def test_every_finding_and_the_rule_are_in_the_datasets_guide():
    from harness import box_fit
    from harness.input_guard import KINDS

    guide = " ".join((Path(__file__).resolve().parents[1] / "docs" / "datasets.md").read_text().split())
    assert all(f"| `{kind}` |" in guide for kind in KINDS)
    rule = (
        f"at least {box_fit.FACTOR:g} times and {box_fit.MIN_GAIN:g} above the given one's and higher for at least "
        f"{box_fit.SHARE:.0%} of at least {box_fit.MIN_COMPARED} boxes"
    ).replace("%", " %")
    assert rule in guide and f"at most {box_fit.MAX_SAMPLES} samples" in guide
