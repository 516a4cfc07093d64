"""The baselines train and evaluate through ``harness run`` on every fold of the synthetic M3T data.

Reduced size (width 0.125, depth 0.33), one epoch at 128 px on the tiny synthetic set (8 pairs, five projects in
the seed's four folds): this checks the plumbing (the host's dual-stream inputs, the loss dict, detections in
the results store), not accuracy.
"""

from __future__ import annotations

import json

import pytest

from datasets_helpers import smoke_run_args
from engine_helpers import set_args

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]
pytest.importorskip("harness.runner", reason="needs the training engine (`harness run`), absent from this checkout")


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("baselines-cache")


@pytest.mark.parametrize("detector", ["icafusion", "eme", "cmadet"])
def test_harness_run_trains_and_evaluates_every_fold(
    detector,
    tiny_source,
    cache_dir,
    tmp_path,
    cli_runner,  # noqa: F811
    monkeypatch,
):
    monkeypatch.setenv("HARNESS_CACHE", str(cache_dir))
    store = tmp_path / "store"
    tiny = ["model.width=0.125", "model.depth=0.33", "protocol.imgsz=128"]
    result = cli_runner(smoke_run_args(detector, "all", store, tiny_source, *set_args(tiny)))
    assert result.exit_code == 0, result.output
    runs = sorted(store.glob(f"m3t-synth/{detector}/ir8/*/seed0/metrics.json"))
    assert [p.parent.parent.name for p in runs] == ["P1", "P2", "P3", "P4+P5"]
    for path in runs:
        metrics = json.loads(path.read_text())
        assert metrics["model"]["input_kind"] == "dual"
        assert metrics["support"]["images"] > 0
        assert metrics["train"]["epochs_run"] == 1
        predictions = json.loads((path.parent / "predictions.json").read_text())
        assert isinstance(predictions, list)
        if predictions:
            assert {"image_id", "category_id", "bbox", "score"} <= set(predictions[0])
