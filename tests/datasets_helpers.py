"""Shared helpers of the dataset tests: one tiny synthetic M3T dataset per test session, copied per test."""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest

from engine_helpers import run_args, set_args


@pytest.fixture(scope="session")
def tiny_source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ``tiny`` profile (8 pairs, thermal 160x128), generated once per session. Do not modify it."""
    from adapters.datasets.synthetic import generate

    root = tmp_path_factory.getbasetemp() / "m3t-synth-tiny-seed0"
    if not (root / "synth.json").exists():
        generate(root, profile="tiny", seed=0, force=True, progress=False)
    return root


@pytest.fixture
def tiny(tiny_source: Path, tmp_path: Path) -> Path:
    """A private copy of the tiny dataset that a test may damage."""
    dst = tmp_path / "m3t"
    shutil.copytree(tiny_source, dst)
    return dst


def smoke_run_args(detector: str, folds: str, store: Path, root: Path, *extra: str) -> list[str]:
    """The arguments of ``harness run`` for one epoch of the smoke profile on the synthetic M3T set at ``root`` (batch
    4, one thread); ``extra`` (more options, ``--set`` pairs) comes last."""
    overrides = [
        f"dataset.root={root}",
        "protocol.epochs=1",
        "train.batch=4",
        "train.nominal_batch=4",
        "train.threads=1",
        "eval.batch=4",
    ]
    return run_args(detector, "m3t-synth", folds, store, "--profile", "smoke", *set_args(overrides), *extra)


def skip_reasons(prepared: Any) -> dict[str, int]:
    """The skips of a prepared dataset's prepare report, counted by reason."""
    return prepared.manifest["report"]["skip_reasons"]


@contextlib.contextmanager
def edited_json(path: Path) -> Iterator[Any]:
    """Damage a JSON file for a test: read it, let the ``with`` block change the document, write it back."""
    doc = json.loads(path.read_text())
    yield doc
    path.write_text(json.dumps(doc))


def write_or_remove(path: Path, content: str | None) -> None:
    """Damage a file for a test: write ``content`` over it, or remove it when ``content`` is ``None``."""
    if content is None:
        path.unlink()
    else:
        path.write_text(content)


def synth_cfg(root: Path, **dataset: Any) -> dict[str, Any]:
    """The resolved config of the m3t-synth protocol with ``dataset.root`` set."""
    from harness.config import load_config

    cfg = load_config(protocol="m3t-4fold")
    cfg["dataset"] = {"root": str(root), **dataset}
    return cfg


def corner_errors(prepared: Any, root: Path) -> tuple[np.ndarray, int]:
    """Distances (thermal px) between each prepared box's corners and the generator's true box (same annotation
    id, clipped to the frame, shifted by the crop origin): array N x 4, plus the number of prepared boxes that
    have no true counterpart (slivers of objects lying just outside the thermal frame)."""
    gt = json.loads((root / "ground_truth" / "instances_thermal.json").read_text())
    truth = {a["id"]: a["bbox"] for a in gt["annotations"]}
    out, unmatched = [], 0
    for s in prepared:
        ox, oy = s.meta["crop_origin"]
        for box, ann_id in zip(np.asarray(s.boxes), s.meta["ann_ids"]):
            if ann_id not in truth:
                unmatched += 1
                continue
            x, y, w, h = truth[ann_id]
            t = np.array([x - ox, y - oy, x + w - ox, y + h - oy])
            t[[0, 2]] = t[[0, 2]].clip(0, s.width)
            t[[1, 3]] = t[[1, 3]].clip(0, s.height)
            corners_p = box[[0, 1, 2, 1, 2, 3, 0, 3]].reshape(4, 2)
            corners_t = t[[0, 1, 2, 1, 2, 3, 0, 3]].reshape(4, 2)
            out.append(np.linalg.norm(corners_p - corners_t, axis=1))
    return np.array(out).reshape(-1, 4), unmatched
