"""The mutation suite of the dataset-plugin boundary: every misreading in a known-good plugin's samples is refused or
labelled, never prepared silently.

A known-good dataset plugin (the shapes data: two groups of 12 samples, temperatures in degrees C, ``x1, y1, x2, y2``
boxes, 0-based labels) is registered for the test and prepared with ``harness prepare`` as a user runs it. Each
operator of ``OPERATORS`` changes what the plugin yields the way a plugin author gets it wrong (8-bit counts declared
as degrees C, Kelvin, boxes outside the frame, labels past the class list, most samples broken, ...); for every
operator the command must stop with exit status 2 and a message naming the plugin and what was seen, or prepare with
the finding recorded as an input risk. The unmutated plugin must prepare with no risk. A new kind of mistake goes in
as one more operator.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from engine_helpers import CATEGORIES, ENCODINGS, ShapesSource
from harness import DatasetSpec, hookimpl
from harness.api import AlignedSample
from harness.testing import temporary_plugin

NC = len(CATEGORIES)
NAME = "mutated-shapes"


@dataclass(frozen=True)
class Operator:
    """One mistake: ``sample`` changes one yielded sample (``k``: its 0-based position); ``categories``: the
    source's category list, where it differs from the spec's; ``says``: what the refusal (or label) must say."""

    name: str
    says: str
    sample: Callable[[AlignedSample, int], AlignedSample] | None = None
    categories: tuple[str, ...] | None = None


def _thermal(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[AlignedSample, int], AlignedSample]:
    return lambda s, k: dataclasses.replace(s, thermal=np.ascontiguousarray(fn(s.thermal)).astype(np.float32))


def _boxes(fn: Callable[[np.ndarray, int, int], np.ndarray]) -> Callable[[AlignedSample, int], AlignedSample]:
    def edit(s: AlignedSample, k: int) -> AlignedSample:
        h, w = s.ir8.shape
        return dataclasses.replace(s, boxes=np.ascontiguousarray(fn(s.boxes, w, h), np.float32))

    return edit


def _labels(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[AlignedSample, int], AlignedSample]:
    return lambda s, k: dataclasses.replace(s, labels=np.ascontiguousarray(fn(s.labels), np.int64))


def _byteswapped(t: np.ndarray) -> np.ndarray:
    return np.frombuffer(t.astype(">f4").tobytes(), "<f4").reshape(t.shape)


def _most_broken(s: AlignedSample, k: int) -> AlignedSample:
    """22 of 24 samples with a thermal map of the wrong shape."""
    return s if k in (0, 12) else dataclasses.replace(s, thermal=s.thermal[:-1])


def _twice(s: AlignedSample, k: int) -> AlignedSample:
    return dataclasses.replace(s, boxes=np.repeat(s.boxes, 2, 0), labels=np.repeat(s.labels, 2))


def _same_id(s: AlignedSample, k: int) -> AlignedSample:
    return dataclasses.replace(s, image_id=1)


def _no_boxes(s: AlignedSample, k: int) -> AlignedSample:
    return dataclasses.replace(s, boxes=np.zeros((0, 4), np.float32), labels=np.zeros((0,), np.int64))


def _rgb_as_bgr_float(s: AlignedSample, k: int) -> AlignedSample:
    return dataclasses.replace(s, rgb=s.rgb.astype(np.float32) / 255)


OPERATORS = (
    Operator("8-bit counts declared as degrees C", "8-bit counts", _thermal(lambda t: np.rint((t - 14) / 12 * 255))),
    Operator("Kelvin", "Kelvin", _thermal(lambda t: t + 273.15)),
    Operator("Fahrenheit", "Fahrenheit", _thermal(lambda t: t * 1.8 + 32)),
    Operator("centi-Kelvin", "thermal", _thermal(lambda t: (t + 273.15) * 100)),
    Operator("byte-swapped floats", "big-endian", _thermal(_byteswapped)),
    Operator("NaN-only thermal", "non-finite", _thermal(lambda t: t * np.nan)),
    Operator("thermal of another shape", "thermal", _thermal(lambda t: t[:-1])),
    Operator("boxes outside the frame", "boxes", _boxes(lambda b, w, h: b + np.array([w, 0, w, 0]))),
    Operator(
        "boxes x, y, w, h",
        "invalid-samples",
        _boxes(lambda b, w, h: np.concatenate([b[:, :2], b[:, 2:] - b[:, :2]], 1)),
    ),
    Operator("boxes normalised", "normalised-boxes", _boxes(lambda b, w, h: b / np.array([w, h, w, h]))),
    Operator("boxes y first", "invalid-samples", _boxes(lambda b, w, h: b[:, [1, 0, 3, 2]])),
    Operator("every box twice", "duplicate-boxes", _twice),
    Operator("labels >= nc", "labels", _labels(lambda lab: lab + NC)),
    Operator("labels 1-based", "invalid-samples", _labels(lambda lab: lab + 1)),
    Operator("labels -1", "invalid-samples", _labels(lambda lab: lab - 1)),
    Operator("most samples fail validation", "22 of the 24 samples", _most_broken),
    Operator("one image id for every sample", "image", _same_id),
    Operator("no boxes", "no-labels", _no_boxes),
    Operator("rgb as floats 0..1", "rgb", _rgb_as_bgr_float),
    Operator("categories in another order", "category-order", categories=tuple(reversed(CATEGORIES))),
)

#: the operator the plugin applies (set by a test; None: the known-good plugin)
MUTATION: dict[str, Operator | None] = {"op": None}


class MutatedShapes(ShapesSource):
    """The shapes data, two groups of 12, each sample changed by the current operator."""

    def __init__(self) -> None:
        super().__init__(per_group=12)
        op = MUTATION["op"]
        self.op = op
        self.categories = op.categories if op is not None and op.categories else CATEGORIES

    def fingerprint(self) -> str:
        return super().fingerprint() + (self.op.name if self.op is not None else "")

    def samples(self, report: Any):
        for k, s in enumerate(super().samples(report)):
            yield self.op.sample(s, k) if self.op is not None and self.op.sample is not None else s


class Plugin:
    @hookimpl
    def register_encodings(self, register: Any) -> None:
        for e in ENCODINGS:
            register(e)

    @hookimpl
    def register_datasets(self, register: Any) -> None:
        register(
            DatasetSpec(
                name=NAME,
                open=lambda root=None, sensing=None, **opts: MutatedShapes(),
                categories=CATEGORIES,
                default_encoding="test-ir8",
                description="the shapes data, mutated",
            )
        )


@pytest.fixture(scope="module")
def plugin() -> Any:
    from harness.plugins import load_plugins

    load_plugins()
    with temporary_plugin(Plugin(), name="plugin-mutation-test"):
        yield


def outcome(cli_runner: Any, tmp: Path, op: Operator | None) -> tuple[int, str, Any]:
    """``harness prepare`` of the plugin mutated by ``op``: (exit status, output, the prepared manifest or None)."""
    MUTATION["op"] = op
    try:
        res = cli_runner(["prepare", "--dataset", NAME, "--cache", str(tmp / "cache")])
    finally:
        MUTATION["op"] = None
    found = sorted((tmp / "cache").rglob("manifest.json"))
    return res.exit_code, res.output, json.loads(found[0].read_text()) if found and res.exit_code == 0 else None


def test_the_known_good_plugin_prepares_with_no_risk(plugin, cli_runner, tmp_path):
    code, out, manifest = outcome(cli_runner, tmp_path, None)
    assert code == 0, out
    assert "24 aligned samples" in out and not manifest.get("input_risks")


@pytest.mark.parametrize("op", OPERATORS, ids=[op.name for op in OPERATORS])
def test_every_mutant_is_refused_or_labelled(op, plugin, cli_runner, tmp_path):
    code, out, manifest = outcome(cli_runner, tmp_path, op)
    risks = (manifest or {}).get("input_risks") or []
    verdict = "refused" if code == 2 else "labelled" if risks else "SILENT"
    print(f"{op.name:45} {verdict:8} exit {code}")
    assert verdict != "SILENT", f"{op.name} prepared silently:\n{out}"
    text = " ".join(out.split())
    if code == 2:
        assert NAME in text and op.says in text, out
    else:
        assert any(op.says in json.dumps(r) for r in risks), risks
    assert "Traceback" not in out
