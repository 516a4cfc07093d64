"""A smoke run gives bit-identical predictions and metrics from the compact and the raw prepared cache."""

from __future__ import annotations

import json

import pytest

from datasets_helpers import smoke_run_args

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]
pytest.importorskip("harness.runner", reason="needs the training engine (`harness run`)")

RUNS = {
    "ours": ["--encoding", "c2", "--set", "model.scale=n", "--set", "protocol.imgsz=64"],
    "icafusion": [
        "--encoding",
        "ir8",
        "--set",
        "model.width=0.125",
        "--set",
        "model.depth=0.33",
        "--set",
        "protocol.imgsz=64",
    ],
}


@pytest.mark.parametrize("detector", sorted(RUNS))
def test_compact_and_raw_cache_give_identical_runs(
    detector,
    tiny_source,
    tmp_path,
    cli_runner,  # noqa: F811
    monkeypatch,
):
    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    out = {}
    for form in ("raw", "compact"):
        monkeypatch.setenv("HARNESS_CACHE_FORM", form)
        store = tmp_path / f"store-{form}"
        result = cli_runner(smoke_run_args(detector, "P1", store, tiny_source, *RUNS[detector]))
        assert result.exit_code == 0, result.output
        (run,) = store.glob(f"m3t-synth/{detector}/*/P1/seed0")
        out[form] = ((run / "predictions.json").read_bytes(), json.loads((run / "metrics.json").read_text()))
    names = sorted(p.name for p in (tmp_path / "cache" / "m3t-synth").iterdir())
    assert len(names) == 2 and names[1] == f"{names[0]}-raw"  # both forms were prepared and used
    assert out["raw"][0] == out["compact"][0] and len(json.loads(out["raw"][0])) > 0
    assert out["raw"][1]["metrics"] == out["compact"][1]["metrics"]
    assert out["raw"][1]["support"] == out["compact"][1]["support"]
