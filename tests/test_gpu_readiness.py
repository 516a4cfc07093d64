"""What a GPU run switches on, exercised on the CPU: mixed precision (autocast), channels-last memory format and
data-loader worker processes, for the four built-in detectors and the training loop.

CUDA autocast runs in float16; the CPU's autocast runs in bfloat16, the nearest stand-in: it finds losses, assigners
and post-processing that mix dtypes or build tensors in float32 against half-precision activations.
"""

from __future__ import annotations

import json

import pytest
import torch

from adapters.detectors import cmadet, eme, icafusion, ours

pytestmark = pytest.mark.usefixtures("one_torch_thread")

NC = 3
TINY = {"width": 0.125, "depth": 0.33}
BUILD = {
    "ours": (lambda: ours.build(NC, in_channels=4, scale="n"), "single"),
    "eme": (lambda: eme.build(NC, **TINY), "dual"),
    "icafusion": (lambda: icafusion.build(NC, **TINY, tokens=(4, 2, 2), dropout=0.0), "dual"),
    "cmadet": (lambda: cmadet.build(NC, **TINY, grid=4), "dual"),
}
TARGETS = [
    {"boxes": torch.tensor([[8.0, 10.0, 30.0, 40.0]]), "labels": torch.tensor([1])},
    {"boxes": torch.tensor([[30.0, 20.0, 60.0, 50.0], [5.0, 5.0, 20.0, 15.0]]), "labels": torch.tensor([0, 2])},
]


def _inputs(kind: str, channels_last: bool = False):
    from harness.engine.data import to_inputs

    g = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (2, 4, 64, 64), generator=g, dtype=torch.uint8)
    return to_inputs(images, kind, 3, "cpu", channels_last)


def _model(name: str):
    build, kind = BUILD[name]
    torch.manual_seed(0)
    return build(), kind


@pytest.mark.parametrize("name", list(BUILD))
def test_detector_trains_and_predicts_under_autocast(name):
    model, kind = _model(name)
    model.train()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        losses = model(_inputs(kind), TARGETS)
    total = sum(v.sum() for v in losses.values())
    assert torch.isfinite(total), {k: float(v) for k, v in losses.items()}
    total.backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad and p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    model.eval()
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(_inputs(kind))
    assert len(out) == 2
    for det in out:
        assert det["boxes"].shape[-1] == 4 and torch.isfinite(det["boxes"].float()).all()
        assert det["scores"].shape == det["labels"].shape


@pytest.mark.parametrize("name", list(BUILD))
def test_detector_gives_the_same_losses_in_channels_last(name):
    model, kind = _model(name)
    model.train()
    ref = {k: float(v.detach()) for k, v in model(_inputs(kind), TARGETS).items()}
    model = model.to(memory_format=torch.channels_last)
    got = {k: float(v.detach()) for k, v in model(_inputs(kind, channels_last=True), TARGETS).items()}
    assert got.keys() == ref.keys()
    for k in ref:
        assert got[k] == pytest.approx(ref[k], rel=1e-4, abs=1e-5), k


@pytest.mark.slow
def test_training_with_workers_and_channels_last_matches_the_plain_run(host, tmp_path, monkeypatch):
    """The same run with two data-loader worker processes and channels-last memory: the same batches (augmentation
    is seeded per sample), so the same losses up to the float rounding of the memory format."""
    pytest.importorskip("harness.cache")
    from engine_helpers import ShapesPlugin, tinydet_module
    from harness.runner import RunRequest, run
    from harness.testing import temporary_plugin

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    tinydet_module()
    import harness_tinydet.plugin as tinydet_plugin

    base = [
        "protocol.imgsz=64",
        "protocol.epochs=2",
        "train.batch=8",
        "train.nominal_batch=8",
        "train.warmup_epochs=0",
        "train.close_mosaic=1",
        "train.threads=1",
        "train.device=cpu",
    ]
    logs = {}
    with temporary_plugin(ShapesPlugin(), name="shapes-gpu"), temporary_plugin(tinydet_plugin, name="tiny-gpu"):
        for label, extra in (("plain", []), ("fast", ["train.workers=2", "train.channels_last=true"])):
            summary = run(
                RunRequest(
                    detector="tinydet",
                    dataset="shapes",
                    folds="A",
                    store=tmp_path / label,
                    overrides=[*base, *extra],
                    progress=False,
                )
            )
            (r,) = summary.results
            logs[label] = [json.loads(x) for x in (r.path / "log.jsonl").read_text().splitlines()]
    assert [x["epoch"] for x in logs["fast"]] == [1, 2]
    for a, b in zip(logs["plain"], logs["fast"]):
        for k, v in a["loss"].items():
            assert b["loss"][k] == pytest.approx(v, rel=1e-3, abs=1e-4), (a["epoch"], k)
