"""Configuration: YAML layers, the schema, overrides and clear errors."""

from __future__ import annotations

import pytest

from harness.config import dump_yaml, load_config, parse_override, read_yaml
from harness.errors import ConfigError
from harness.store import Run, RunKey


def test_defaults_and_protocol_and_profile_layering():
    base = load_config()
    assert base["protocol"]["imgsz"] == 640 and base["protocol"]["epochs"] == 150
    m3t = load_config(protocol="m3t-4fold", profile="paper")
    assert m3t["protocol"]["folds"] == {"P1": ["P1"], "P2": ["P2"], "P3": ["P3"], "P4+P5": ["P4", "P5"]}
    assert m3t["protocol"]["imgsz"] == 640
    smoke = load_config(protocol="m3t-4fold", profile="smoke")
    assert smoke["protocol"]["imgsz"] < 640 and smoke["protocol"]["epochs"] < 150
    assert smoke["protocol"]["folds"] == m3t["protocol"]["folds"]  # a profile does not drop the protocol's folds
    assert smoke["meta"]["profile"] == "smoke"


def test_cli_overrides_win_and_are_typed():
    cfg = load_config(
        profile="smoke",
        overrides=["protocol.epochs=3", "protocol.imgsz=320", "eval.engine=pycocotools", "model.width=0.25"],
    )
    assert cfg["protocol"]["imgsz"] == 320
    assert cfg["eval"]["engine"] == "pycocotools"
    assert cfg["model"] == {"width": 0.25}  # open section


def test_detector_defaults_layer_below_profile():
    cfg = load_config(
        profile="smoke", detector="x", detector_defaults={"eval": {"iou": 0.5}, "protocol": {"imgsz": 999}}
    )
    assert cfg["eval"]["iou"] == 0.5
    assert cfg["protocol"]["imgsz"] != 999  # the profile is applied after the detector's defaults


def test_unknown_key_names_key_and_source(tmp_path):
    f = tmp_path / "mine.yaml"
    f.write_text("train:\n  epoch: 3\n")
    with pytest.raises(ConfigError, match=r"mine.yaml: unknown key 'train.epoch'"):
        load_config(files=[f])
    with pytest.raises(ConfigError, match=r"--set trian.epochs=3: unknown key 'trian'"):
        load_config(overrides=["trian.epochs=3"])


def test_wrong_type_is_an_error():
    with pytest.raises(ConfigError, match="expects int, got str"):
        load_config(overrides=["protocol.imgsz=big"])
    with pytest.raises(ConfigError, match="expects bool"):
        load_config(overrides=["train.ema=3"])


def test_bad_yaml_is_an_error_with_line(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("train:\n  epochs: [1, 2\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: invalid YAML at line"):
        read_yaml(f)
    g = tmp_path / "dup.yaml"
    g.write_text("train:\n  epochs: 1\n  epochs: 2\n")
    with pytest.raises(ConfigError, match="duplicate key 'epochs'"):
        read_yaml(g)
    h = tmp_path / "list.yaml"
    h.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        read_yaml(h)
    with pytest.raises(ConfigError, match="not found"):
        read_yaml(tmp_path / "missing.yaml")


def test_yaml_is_loaded_safely(tmp_path):
    f = tmp_path / "evil.yaml"
    f.write_text("train: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        read_yaml(f)


def test_unknown_profile_and_protocol():
    with pytest.raises(ConfigError, match="unknown profile 'fast'.*smoke"):
        load_config(profile="fast")
    with pytest.raises(ConfigError, match="unknown protocol"):
        load_config(protocol="nope")


def test_override_syntax():
    assert parse_override("a.b.c=[1, 2]") == {"a": {"b": {"c": [1, 2]}}}
    with pytest.raises(ConfigError, match="expected section.key=value"):
        parse_override("train.epochs")


def test_resolved_config_is_written_beside_results(tmp_path):
    cfg = load_config(protocol="m3t-4fold", profile="smoke", overrides=["train.batch=4"])
    run = Run(tmp_path, RunKey("m3t-synth", "ours", "c2", "P4+P5", 0))
    digest = run.write_config(cfg)
    text = run.config_path.read_text()
    assert digest in text
    assert read_yaml(run.config_path) == read_yaml_roundtrip(cfg)


def read_yaml_roundtrip(cfg):
    import yaml

    return yaml.safe_load(dump_yaml(cfg))


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.lr0=-1", r"--set train.lr0=-1: train.lr0=-1 must be a number > 0"),
        ("train.momentum=1.5", r"train.momentum=1.5 must be a number in \[0, 1\)"),
        ("eval.iou=0", r"eval.iou=0 must be a number in \(0, 1\]"),
        ("train.batch=0", r"train.batch=0 must be an integer >= 1"),
        ("augment.fliplr=.nan", r"augment.fliplr=nan must be a number in \[0, 1\]"),
    ],
)
def test_a_value_out_of_range_is_a_config_error_naming_key_and_source(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config("smoke", protocol="default", overrides=[override])


def test_a_value_out_of_range_in_a_file_names_the_file(tmp_path):
    f = tmp_path / "mine.yaml"
    f.write_text("eval:\n  conf: 2.0\n")
    with pytest.raises(ConfigError, match=r"mine.yaml: eval.conf=2.0 must be a number in \[0, 1\]"):
        load_config("smoke", files=[f])


def test_cli_bad_learning_rate_is_one_clear_line(cli_runner, tmp_path):
    res = cli_runner(
        [
            "run",
            "--detector",
            "ours",
            "--dataset",
            "m3t-synth",
            "--set",
            "train.lr0=-1",
            "--store",
            str(tmp_path / "store"),
        ]
    )
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert "train.lr0=-1 must be a number > 0" in res.output and not (tmp_path / "store").exists()
