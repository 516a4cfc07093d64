"""benchmarks/learning_curves.py: the commands of its runs for each suite, and reading a curve from a store."""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def lc():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        spec = importlib.util.spec_from_file_location("learning_curves", ROOT / "benchmarks" / "learning_curves.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


def _args(**kw):
    base = dict(epochs="60,cmadet=40", fold="P1", seed=0, store="/tmp/s", suite="m3t-synth", set=[])
    return argparse.Namespace(**{**base, **kw})


def test_m3t_synth_command_is_the_benchmark_files_at_validation_selection(lc):
    cmd = lc.command("cmadet", _args())
    assert cmd[cmd.index("--dataset") + 1] == "m3t-synth"
    assert [cmd[i + 1] for i, c in enumerate(cmd) if c == "--config"] == [
        str(ROOT / "configs" / "benchmark" / "cmadet.yaml")
    ]
    sets = [cmd[i + 1] for i, c in enumerate(cmd) if c == "--set"]
    assert sets == [
        "protocol.selection=validation",
        "protocol.epochs=40",
        "protocol.patience=40",
        "eval.log_held_out=true",
        "train.threads=1",
    ]


def test_rgbt_tiny_command_reads_the_suite_data_layers_and_overrides(lc, tmp_path, monkeypatch):
    monkeypatch.setenv("HARNESS_DATA", str(tmp_path))
    cmd = lc.command("ours", _args(suite="rgbt-tiny-synth", fold="test-T", set=["protocol.imgsz=416"]))
    assert cmd[cmd.index("--dataset") + 1] == "rgbt-tiny"
    configs = [cmd[i + 1] for i, c in enumerate(cmd) if c == "--config"]
    assert [Path(c).relative_to(ROOT / "configs").as_posix() for c in configs] == [
        "benchmark-rgbt-tiny/suite.yaml",
        "benchmark-rgbt-tiny/ours.yaml",
    ]
    sets = [cmd[i + 1] for i, c in enumerate(cmd) if c == "--set"]
    assert sets[0] == f"dataset.root={(tmp_path / 'rgbt-tiny-synth-small-320-seed0').resolve()}"
    assert "dataset.gt=thermal" in sets
    assert "protocol.epochs=60" in sets
    assert sets[-1] == "protocol.imgsz=416"  # the passthrough comes after the script's own settings


def test_unknown_suite_is_refused_with_the_known_ones(lc):
    from harness.errors import ConfigError

    with pytest.raises(ConfigError, match="rgbt-tiny-synth"):
        lc.command("ours", _args(suite="nope"))


def test_read_curve_finds_an_rgbt_tiny_run_and_its_cpu_seconds(lc, tmp_path):
    run = tmp_path / "rgbt-tiny" / "ours" / "proxy8" / "test-T" / "seed0"
    run.mkdir(parents=True)
    rows = [
        {"epoch": e, "time_s": 10.0, "fitness": 0.01 * e, "metrics": {"mAP50_95": 0.01 * e}, "observed": {}}
        for e in (1, 2)
    ]
    (run / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (tmp_path / "ours-test-T-seed0.usage.json").write_text(json.dumps({"exit": 0, "wall_s": 30.0, "cpu_s": 25.0}))
    assert lc.read_curve(tmp_path, "ours", "test-T", 0) is None  # the m3t-synth folder
    curve = lc.read_curve(tmp_path, "ours", "test-T", 0, "rgbt-tiny")
    assert curve["encoding"] == "proxy8" and [r["fitness"] for r in curve["rows"]] == [1.0, 2.0]
    assert curve["run_cpu_s"] == 25.0
    assert lc.summarise(curve, [2], [2])["cpu_s_per_epoch"] == 12.5
