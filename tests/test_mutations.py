"""The mutation suite of the prediction boundaries: every misreading of a known-good prediction set is refused or
labelled, never scored silently.

A known-good set (the objects of the shapes data found by colour, nearly perfect, with one low-scored false
positive per image) goes through each boundary where predictions enter the harness: (a) a detector plugin's eval-mode
output during ``harness run``, (b) a COCO results file for ``harness score``. Each operator of ``OPERATORS`` makes one
mistake a producer of predictions makes (a class list off by one, logits for scores, boxes in another convention,
...); for every (boundary, operator) the command must stop with exit status 2 and a message naming what was seen, or
store a result that carries a label. The unmutated set must score high with no label. A new kind of mistake goes in as
one more operator.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import torch
from torch import nn

from engine_helpers import CATEGORIES, ENCODINGS, ShapesSource, run_args, set_args
from harness import DatasetSpec, DetectorSpec, hookimpl
from harness.testing import temporary_plugin

pytestmark = pytest.mark.usefixtures("one_torch_thread")

NC = len(CATEGORIES)
#: The images' height and width: wider than high, so the run's 64 px input is letterboxed (padded above and below).
SIZE = (64, 80)
#: The run: one epoch of a model with one parameter at 64 px, no validation.
RUN = [
    "protocol.imgsz=64",
    "protocol.epochs=1",
    "protocol.selection=last",
    "train.batch=8",
    "train.nominal_batch=8",
    "train.warmup_epochs=0",
    "train.warmup_min_iters=0",
    "train.close_mosaic=0",
    "train.threads=1",
    "train.device=cpu",
    "eval.batch=8",
]

# ------------------------------------------------------------------------------------------------ the operators
#: One image's predictions: boxes x1, y1, x2, y2 [K, 4], scores [K], 0-based labels [K], in a w x h frame.
Arrays = tuple[np.ndarray, np.ndarray, np.ndarray]


def _xywh(b: np.ndarray) -> np.ndarray:
    return np.concatenate([b[:, :2], b[:, 2:] - b[:, :2]], axis=1)


def _cxcywh(b: np.ndarray) -> np.ndarray:
    return np.concatenate([(b[:, :2] + b[:, 2:]) / 2, b[:, 2:] - b[:, :2]], axis=1)


def _logit(s: np.ndarray) -> np.ndarray:
    p = np.clip(s, 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p))


@dataclass(frozen=True)
class Operator:
    """One mistake: ``image`` changes one image's predictions (both boundaries), ``file`` the written results list
    (``harness score`` only); ``images``: the results come with an image list (``--images``), ``listed`` changes
    that list (``harness score`` only); ``run`` and ``score``:
    what the refusal must say at each boundary; ``classes``: the model is built for this many classes more than the
    dataset has (``harness run`` only)."""

    name: str
    image: Callable[[np.ndarray, np.ndarray, np.ndarray, int, int], Arrays] | None = None
    run: str = ""
    score: str = ""
    file: Callable[[list[dict[str, Any]]], list[dict[str, Any]]] | None = None
    images: bool = False
    classes: int = 0
    listed: Callable[[list[dict[str, Any]]], list[dict[str, Any]]] | None = None


def _same(b: np.ndarray, s: np.ndarray, lab: np.ndarray, w: int, h: int) -> Arrays:
    return b, s, lab


def _image_shift(dets: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{**d, "image_id": d["image_id"] + 1} for d in dets]


#: Where the ids of another codebase that numbers its images itself begin.
OWN = 1000


def _own_ids(dets: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{**d, "image_id": d["image_id"] + OWN} for d in dets]


def _name_conflict(dets: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{**d, "category_name": CATEGORIES[d["category_id"] % NC]} for d in dets]


def _corners(dets: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{**d, "bbox": [x, y, x + w, y + h]} for d in dets for x, y, w, h in [d["bbox"]]]


#: (operator, what ``harness run`` must say, what ``harness score`` must say: "" where it does not apply)
OPERATORS = (
    Operator("label +1", lambda b, s, lab, w, h: (b, s, lab + 1), "got 3 (the dataset has 3 categories", "shift of -1"),
    Operator("label -1", lambda b, s, lab, w, h: (b, s, lab - 1), "got -1", "shift of +1"),
    Operator("label rolled (l+1) % nc", lambda b, s, lab, w, h: (b, s, (lab + 1) % NC), "rolled by -1", "rolled by -1"),
    Operator("label rolled (l-1) % nc", lambda b, s, lab, w, h: (b, s, (lab - 1) % NC), "rolled by +1", "rolled by +1"),
    Operator(
        "labels beyond the classes",
        lambda b, s, lab, w, h: (b, s, np.where(np.arange(len(lab)) % 2, lab + NC, lab)),
        "a model built for",
        "categories the dataset does not have",
    ),
    Operator("scores x 100", lambda b, s, lab, w, h: (b, s * 100, lab), "percentages?", "percentages?"),
    Operator("scores as logits", lambda b, s, lab, w, h: (b, _logit(s), lab), "logits", "logits"),
    Operator("scores NaN", lambda b, s, lab, w, h: (b, s * np.nan, lab), "must be finite", "not finite"),
    Operator(
        "every detection twice",
        lambda b, s, lab, w, h: (np.repeat(b, 2, 0), np.repeat(s, 2), np.repeat(lab, 2)),
        "listed twice",
        "listed twice",
    ),
    Operator("boxes x, y, w, h", lambda b, s, lab, w, h: (_xywh(b), s, lab), "inverted", "negative width or height"),
    Operator(
        "boxes cx, cy, w, h", lambda b, s, lab, w, h: (_cxcywh(b), s, lab), "inverted", "negative width or height"
    ),
    Operator("boxes y first", lambda b, s, lab, w, h: (b[:, [1, 0, 3, 2]], s, lab), "(y first)", "(y first)"),
    Operator(
        "boxes normalised", lambda b, s, lab, w, h: (b / np.array([w, h, w, h]), s, lab), "normalised", "normalised"
    ),
    Operator("corners written as bbox", score="as corners", file=_corners),
    Operator("category_name disagrees with category_id", score="category_id and category_name", file=_name_conflict),
    Operator("image ids +1", score="shift of -1", file=_image_shift),
    Operator("image ids +1 with --images", score="previous image", file=_image_shift, images=True),
    Operator(
        "--images lists every other image",
        score="not in the image list given with --images",
        file=_own_ids,
        images=True,
        listed=lambda names: [{**n, "id": n["id"] + OWN} for n in names[::2]],
    ),
    Operator("model built for fewer classes", run="built for 2 classes (model.nc), the dataset has 3", classes=-1),
)
BOUNDARIES = ("run", "score")
CASES = [(b, op) for op in OPERATORS for b in BOUNDARIES if getattr(op, b)]

# ------------------------------------------------------------------------------------------------ the known-good set


def found_by_colour(img: torch.Tensor) -> Arrays:
    """The shapes of one input image (RGB + 8-bit thermal, 0..1) found by colour: windows are dark blue, warm and
    cold squares bright grey told apart by their thermal channel; one low-scored false positive added."""
    from scipy import ndimage

    x = img.numpy()
    boxes, scores, labels = [], [], []
    for label, mask in ((0, (x[2] - x[0]) > 0.15), (None, x[:3].min(axis=0) > 0.8)):
        lab, _ = ndimage.label(mask)
        for sl in ndimage.find_objects(lab):
            if (sl[0].stop - sl[0].start) < 4 or (sl[1].stop - sl[1].start) < 4:
                continue
            c = label if label is not None else (1 if x[3][sl].mean() > 0.5 else 2)
            boxes.append([sl[1].start, sl[0].start, sl[1].stop, sl[0].stop])
            scores.append(0.9 - 0.01 * len(scores))
            labels.append(c)
    boxes.append([1.0, 1.0, 9.0, 9.0])  # a false positive in a corner
    scores.append(0.05)
    labels.append(0)
    return np.asarray(boxes, np.float64), np.asarray(scores, np.float64), np.asarray(labels, np.int64)


#: The operator the detector applies to its output (set by a test; None: the known-good set).
MUTATION: dict[str, Operator | None] = {"op": None}


class Mutant(nn.Module):
    """A detector plugin's model: one parameter to train, eval-mode output the known-good set as mutated."""

    conf, iou, max_det = 0.001, 0.7, 300

    def __init__(self, num_classes: int, in_channels: int = 4):
        super().__init__()
        self.w = nn.Parameter(torch.zeros(1))
        op = MUTATION["op"]
        self.nc = num_classes + (op.classes if op is not None else 0)

    def forward(self, inputs: Any, targets: Any = None) -> Any:
        if self.training:
            return {"loss": (self.w**2).sum() + 0.1}
        out = []
        op = MUTATION["op"]
        for img in inputs:
            b, s, lab = found_by_colour(img)
            if op is not None and op.image is not None:
                b, s, lab = op.image(b, s, lab, img.shape[2], img.shape[1])
            out.append(
                {
                    "boxes": torch.as_tensor(b, dtype=torch.float32).reshape(-1, 4),
                    "scores": torch.as_tensor(s, dtype=torch.float32),
                    "labels": torch.as_tensor(lab, dtype=torch.long),
                }
            )
        return out


class MutationPlugin:
    """The shapes dataset (``SIZE``), the test encodings and the ``mutant`` detector."""

    @hookimpl
    def register_encodings(self, register: Any) -> None:
        for e in ENCODINGS:
            register(e)

    @hookimpl
    def register_datasets(self, register: Any) -> None:
        register(
            DatasetSpec(
                name="wide-shapes",
                open=lambda root=None, sensing=None, **opts: ShapesSource(size=SIZE, per_group=24),
                categories=CATEGORIES,
                default_encoding="test-ir8",
                description="coloured shapes on 80 x 64 images",
            )
        )

    @hookimpl
    def register_detectors(self, register: Any) -> None:
        register(
            DetectorSpec(
                name="mutant",
                input_kind="single",
                description="returns the known-good predictions, mutated",
                build=lambda num_classes, in_channels=4, **cfg: Mutant(num_classes, in_channels),
            )
        )


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """The plugin registered with a cache of its own, and the known-good results file of fold A (the colour finder
    on the prepared samples, as COCO results in the prepared frame)."""
    import os

    from harness.cache import fold_indices, prepare, resolve_folds
    from harness.config import load_config
    from harness.plugins import get_host, load_plugins

    load_plugins()
    tmp = tmp_path_factory.mktemp("mutations")
    old = os.environ.get("HARNESS_CACHE")
    os.environ["HARNESS_CACHE"] = str(tmp / "cache")
    with temporary_plugin(MutationPlugin(), name="mutation-test"):
        spec = get_host().dataset("wide-shapes")
        cfg = load_config("smoke", protocol=spec.protocol, overrides=RUN)
        prepared = prepare(spec.name, cfg)
        (fold,) = resolve_folds(spec, prepared, cfg, "A")
        _, val_idx = fold_indices(prepared, fold)
        per_image = []
        for i in val_idx:
            r = prepared.records[i]
            ir8 = prepared.channel(i, ENCODINGS[0])
            img = torch.from_numpy(np.concatenate([prepared.rgb(i), np.asarray(ir8).reshape(*SIZE, 1)], axis=2))
            per_image.append((int(r["image_id"]), r["width"], r["height"], found_by_colour(img.permute(2, 0, 1) / 255)))
        names = [
            {"id": int(prepared.records[i]["image_id"]), "file_name": prepared.records[i]["meta"]["file_name"]}
            for i in range(len(prepared.records))
        ]
        yield tmp, per_image, names
    if old is None:
        os.environ.pop("HARNESS_CACHE", None)
    else:
        os.environ["HARNESS_CACHE"] = old


def results_file(per_image: list[Any], op: Operator | None) -> list[dict[str, Any]]:
    dets = []
    for image_id, w, h, (b, s, lab) in per_image:
        if op is not None and op.image is not None:
            b, s, lab = op.image(b, s, lab, w, h)
        for box, score, label in zip(b.tolist(), s.tolist(), lab.tolist()):
            x1, y1, x2, y2 = box
            dets.append(
                {"image_id": image_id, "category_id": label + 1, "bbox": [x1, y1, x2 - x1, y2 - y1], "score": score}
            )
    return op.file(dets) if op is not None and op.file is not None else dets


def outcome(
    cli_runner: Any, boundary: str, op: Operator | None, tmp: Path, per_image: Any, names: Any, *more: str
) -> Any:
    """Run the boundary's command on the (mutated) known-good set, with ``more`` options: (exit status, output,
    stored metrics or None)."""
    store = tmp / "store"
    if boundary == "run":
        MUTATION["op"] = op
        try:
            res = cli_runner(run_args("mutant", "wide-shapes", "A", store, *set_args(RUN), *more))
        finally:
            MUTATION["op"] = None
        found = sorted(store.glob("wide-shapes/mutant/*/A/seed0/metrics.json"))
    else:
        (tmp / "preds.json").write_text(json.dumps(results_file(per_image, op), allow_nan=True))
        extra = ["--images", str(tmp / "images.json")] if op is not None and op.images else []
        listed = op.listed(names) if op is not None and op.listed is not None else names
        (tmp / "images.json").write_text(json.dumps({"images": listed}))
        args = ["score", "--dataset", "wide-shapes", "--folds", "A", "--predictions", str(tmp / "preds.json")]
        res = cli_runner([*args, "--name", "x", "--store", str(store), *extra, *set_args(RUN), *more])
        found = sorted(store.glob("wide-shapes/external.x/*/A/seed0/metrics.json"))
    metrics = json.loads(found[0].read_text()) if found else None
    return res.exit_code, res.output, metrics


@pytest.mark.parametrize("boundary", BOUNDARIES)
def test_the_known_good_set_scores_high_with_no_label(boundary, world, cli_runner, tmp_path):
    _, per_image, names = world
    code, out, metrics = outcome(cli_runner, boundary, None, tmp_path, per_image, names)
    assert code == 0, out
    assert metrics is not None and not metrics.get("labels")
    assert metrics["metrics"]["mAP50"] > 0.8


SILENT: list[str] = []


@pytest.mark.parametrize(("boundary", "op"), CASES, ids=[f"{b}:{op.name}" for b, op in CASES])
def test_every_mutant_is_refused_or_labelled(boundary, op, world, cli_runner, tmp_path):
    _, per_image, names = world
    t0 = time.perf_counter()
    code, out, metrics = outcome(cli_runner, boundary, op, tmp_path, per_image, names)
    verdict = "refused" if code == 2 else "labelled" if metrics and metrics.get("labels") else "SILENT"
    print(f"{boundary:5} {op.name:45} {verdict:8} exit {code}  {time.perf_counter() - t0:.1f}s")
    for line in out.splitlines():
        if line.startswith(("error:", "  - ", "detector")):
            print("   ", line[:200])
    assert verdict != "SILENT", f"{boundary}: {op.name} scored silently (exit {code}):\n{out}"
    if code == 2:  # the message says what was seen and names who made the predictions
        assert "detector 'mutant'" in out if boundary == "run" else "--predictions" in out
        assert getattr(op, boundary) in " ".join(out.split()), out
    else:
        assert code == 0 and any(getattr(op, boundary) in label for label in metrics["labels"]), out


ACCEPTED = [
    (b, op) for b, op in CASES if op.name in ("label rolled (l+1) % nc", "scores x 100", "every detection twice")
]


@pytest.mark.parametrize(("boundary", "op"), ACCEPTED, ids=[f"{b}:{op.name}" for b, op in ACCEPTED])
def test_an_accepted_mutant_is_stored_with_the_finding_as_label(boundary, op, world, cli_runner, tmp_path):
    """``eval.allow_degenerate=true`` (run) and ``--allow-implausible`` (score) store the mutant labelled."""
    _, per_image, names = world
    allow = ["--set", "eval.allow_degenerate=true"] if boundary == "run" else ["--allow-implausible"]
    code, out, metrics = outcome(cli_runner, boundary, op, tmp_path, per_image, names, *allow)
    assert code == 0, out
    assert any(getattr(op, boundary) in label for label in metrics["labels"]), metrics["labels"]


def test_the_table_covers_both_boundaries():
    assert len(CASES) == sum(bool(op.run) + bool(op.score) for op in OPERATORS)
    assert all((op.image is not None) == bool(op.run and op.score) for op in OPERATORS)


def test_random_predictions_raise_no_finding(world):
    """A weak detector (random boxes, labels and scores, 100 per image) agrees little under every reading: noise
    never trips the agreement check."""
    from harness.scoring import agreement as ag

    _, per_image, _ = world
    rng = np.random.default_rng(0)
    truth = {image_id: (b[:-1], lab[:-1]) for image_id, _, _, (b, _, lab) in per_image}  # the found objects
    preds = []
    for image_id in truth:
        xy = rng.uniform(0, 56, (100, 2))
        wh = rng.uniform(4, 24, (100, 2))
        for box, s, lab in zip(
            np.concatenate([xy, xy + wh], 1).tolist(), rng.uniform(0, 1, 100), rng.integers(0, NC, 100)
        ):
            preds.append((image_id, box, float(s), int(lab)))
    assert ag.check(preds, lambda i: truth[i], sorted(truth), NC) == []
