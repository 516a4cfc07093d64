"""The mutation suite of the ``coco-rgbt`` annotation boundary: every misreading of a known-good COCO JSON is refused
or labelled, never prepared silently.

A known-good ``coco-rgbt`` folder (12 aligned pairs, two boxes each, see ``coco_rgbt_helpers``) goes through
``harness prepare`` as a user runs it. Each operator of ``OPERATORS`` makes one mistake a writer of COCO files makes
(boxes as corners, normalised boxes, the RGB image's size as ``width``/``height``, category ids off by one, ...); for
every operator the command must stop with exit status 2 and a message naming the file and what was seen, or prepare
with the finding recorded as an input risk. The unmutated folder must prepare with no risk. A new kind of mistake goes
in as one more operator.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import pytest

from coco_rgbt_helpers import H, W, make_coco_rgbt, read_json, write_json

Coco = dict[str, Any]


@dataclass(frozen=True)
class Operator:
    """One mistake: ``edit`` changes the JSON document (and may change the folder's files); ``says``: what the
    refusal (or the label) must say; ``unseen``: why the mistake cannot be told from the files yet (an expected
    failure, listed in the suite's result)."""

    name: str
    edit: Callable[[Path, Coco], None]
    says: str
    unseen: str = ""


def _boxes(fn: Callable[[list[float]], list[float]]) -> Callable[[Path, Coco], None]:
    def edit(root: Path, coco: Coco) -> None:
        for a in coco["annotations"]:
            a["bbox"] = fn(a["bbox"])

    return edit


def _categories(shift: int) -> Callable[[Path, Coco], None]:
    def edit(root: Path, coco: Coco) -> None:
        for a in coco["annotations"]:
            a["category_id"] += shift

    return edit


def _rgb_size_as_width(root: Path, coco: Coco) -> None:
    """The RGB images at twice the thermal frame's size (registered by a group homography), and ``width``/``height``
    of the RGB image, the COCO habit."""
    import cv2

    for im in coco["images"]:
        rgb = cv2.imread(str(root / im["file_name"]))
        cv2.imwrite(str(root / im["file_name"]), cv2.resize(rgb, (2 * W, 2 * H)))
        im["width"], im["height"] = 2 * W, 2 * H
    half = [[0.5, 0, 0], [0, 0.5, 0], [0, 0, 1]]
    coco["homographies"] = {g: half for g in {im["group"] for im in coco["images"]}}


def _missing_category(root: Path, coco: Coco) -> None:
    coco["categories"] = coco["categories"][:1]


def _twice(root: Path, coco: Coco) -> None:
    n = len(coco["annotations"])
    coco["annotations"] += [{**a, "id": a["id"] + n} for a in coco["annotations"]]


def _image_ids_nowhere(root: Path, coco: Coco) -> None:
    for a in coco["annotations"]:
        a["image_id"] += 100


def _image_ids_shifted(root: Path, coco: Coco) -> None:
    for a in coco["annotations"]:
        a["image_id"] = a["image_id"] % len(coco["images"]) + 1


def _thermal_shifted(root: Path, coco: Coco) -> None:
    names = [im["thermal_file_name"] for im in coco["images"]]
    for im, name in zip(coco["images"], names[1:] + names[:1]):
        im["thermal_file_name"] = name


def _empty(root: Path, coco: Coco) -> None:
    coco["annotations"] = []


def _few_images_labelled(root: Path, coco: Coco) -> None:
    coco["annotations"] = [a for a in coco["annotations"] if a["image_id"] <= 3]


def _swapped_size(root: Path, coco: Coco) -> None:
    for im in coco["images"]:
        im["width"], im["height"] = im["height"], im["width"]


def _no_groups(root: Path, coco: Coco) -> None:
    for im in coco["images"]:
        im.pop("group")


def _bbox_strings(root: Path, coco: Coco) -> None:
    for a in coco["annotations"]:
        a["bbox"] = " ".join(str(v) for v in a["bbox"])


def _category_names_twice(root: Path, coco: Coco) -> None:
    coco["categories"][1]["name"] = coco["categories"][0]["name"]


def _categories_zero_based(root: Path, coco: Coco) -> None:
    coco["categories"] = [{**c, "id": c["id"] - 1} for c in coco["categories"]]


OPERATORS = (
    Operator("boxes x1, y1, x2, y2", _boxes(lambda b: [b[0], b[1], b[0] + b[2], b[1] + b[3]]), "x1, y1, x2, y2"),
    Operator(
        "boxes cx, cy, w, h",
        _boxes(lambda b: [b[0] + b[2] / 2, b[1] + b[3] / 2, b[2], b[3]]),
        "misplaced-boxes: boxes read as centre x, centre y, w, h",
    ),
    Operator("boxes normalised", _boxes(lambda b: [b[0] / W, b[1] / H, b[2] / W, b[3] / H]), "normalised-boxes"),
    Operator("boxes y first", _boxes(lambda b: [b[1], b[0], b[3], b[2]]), "y first"),
    Operator("boxes with negative width", _boxes(lambda b: [b[0] + b[2], b[1], -b[2], b[3]]), "annotation"),
    Operator("bbox as a string", _bbox_strings, "annotation"),
    Operator("width/height of the RGB image", _rgb_size_as_width, "(the RGB image's size)"),
    Operator("width and height swapped", _swapped_size, "the thermal frame's size"),
    Operator("category ids +1", _categories(+1), "unknown category id"),
    Operator("category ids -1", _categories(-1), "unknown category id"),
    Operator("categories numbered from 0", _categories_zero_based, "unknown category id"),
    Operator("a category missing from categories", _missing_category, "unknown category id"),
    Operator("two categories of one name", _category_names_twice, "category name"),
    Operator("every annotation twice", _twice, "duplicate-boxes"),
    Operator("image ids that point nowhere", _image_ids_nowhere, "unknown image id"),
    Operator(
        "image ids shifted by one image", _image_ids_shifted, "misplaced-boxes: each image's boxes read as the previous"
    ),
    Operator("thermal files shifted by one image", _thermal_shifted, "mismatched-pairs"),
    Operator("no annotations", _empty, "no-labels"),
    Operator("annotations for a quarter of the images", _few_images_labelled, "unlabelled-images"),
    Operator("no groups", _no_groups, "group"),
)


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_coco_rgbt(tmp_path_factory.mktemp("coco-mutations") / "d")


def outcome(cli_runner: Any, source: Path, tmp: Path, op: Operator | None) -> tuple[int, str, Any]:
    """``harness prepare`` on a copy of the known-good folder, mutated by ``op``: (exit status, output, the
    prepared manifest or None)."""
    root = Path(shutil.copytree(source, tmp / "d"))
    if op is not None:
        coco = read_json(root)
        op.edit(root, coco)
        write_json(root, coco)
    cache = tmp / "cache"
    res = cli_runner(["prepare", "--dataset", "coco-rgbt", "--root", str(root), "--cache", str(cache)])
    found = sorted(cache.rglob("manifest.json"))
    return res.exit_code, res.output, json.loads(found[0].read_text()) if found and res.exit_code == 0 else None


def test_the_known_good_folder_prepares_with_no_risk(cli_runner, source, tmp_path):
    code, out, manifest = outcome(cli_runner, source, tmp_path, None)
    assert code == 0, out
    assert "12 aligned samples, 24 instances" in out and not manifest.get("input_risks")


CASES = [
    pytest.param(op, id=op.name, marks=pytest.mark.xfail(strict=True, reason=op.unseen) if op.unseen else ())
    for op in OPERATORS
]


@pytest.mark.parametrize("op", CASES)
def test_every_mutant_is_refused_or_labelled(op, cli_runner, source, tmp_path):
    code, out, manifest = outcome(cli_runner, source, tmp_path, op)
    risks = (manifest or {}).get("input_risks") or []
    verdict = "refused" if code == 2 else "labelled" if risks else "SILENT"
    print(f"{op.name:45} {verdict:8} exit {code}")
    assert verdict != "SILENT", f"{op.name} prepared silently:\n{out}"
    text = " ".join(out.split())
    if code == 2:
        assert ("annotations.json" in text or "coco-rgbt" in text) and op.says in text, out
    else:
        assert any(op.says in json.dumps(r) for r in risks), risks
    assert "Traceback" not in out


def test_the_operators_change_the_document(source):
    """Each operator changes the known-good JSON (an operator that changes nothing would pass for the wrong reason)."""
    for op in OPERATORS:
        coco = read_json(source)
        before = json.dumps(coco, sort_keys=True)
        if op.edit is not _rgb_size_as_width:
            op.edit(source, coco)
            assert json.dumps(coco, sort_keys=True) != before, op.name
