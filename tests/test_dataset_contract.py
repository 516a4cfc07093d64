"""The dataset contract: documented in full in docs/plugins.md, protocols shipped by plugins, the ``sensing=``
argument, categories from the opened source, and the report's sensor sections only for datasets with a sensing
stage."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from engine_helpers import ContractSource as _Source
from harness import hookimpl, hookspecs
from harness.api import AlignedSample, DatasetSource, DatasetSpec, Fold, PrepareReport
from harness.errors import PluginError
from harness.testing import temporary_plugin

DOCS = (Path(__file__).resolve().parent.parent / "docs" / "plugins.md").read_text()


def _section(title: str) -> str:
    """The text of one ``##``/``###`` section of docs/plugins.md."""
    m = re.search(rf"^#+ {re.escape(title)}\n(.*?)(?=^## |\Z)", DOCS, flags=re.M | re.S)
    assert m, f"docs/plugins.md has no section {title!r}"
    return m.group(1)


# ------------------------------------------------------------------------------------------- documentation
def test_every_hook_is_documented():
    hooks = [n for n in dir(hookspecs) if n.startswith("register_")]
    assert hooks and all(f"`{h}(" in DOCS for h in hooks), [h for h in hooks if f"`{h}(" not in DOCS]


@pytest.mark.parametrize(
    "title, names",
    [
        ("`DatasetSpec`: what you register", [f.name for f in dataclasses.fields(DatasetSpec)]),
        ("`AlignedSample`: one pair in the thermal frame", [f.name for f in dataclasses.fields(AlignedSample)]),
        (
            "`DatasetSource`: what `open` returns",
            [n for n in vars(DatasetSource) if not n.startswith("_")] + list(DatasetSource.__annotations__),
        ),
        ("Skips and their reasons", [f"report.{m}" for m in ("skip", "note")]),
    ],
)
def test_every_part_of_the_dataset_contract_is_documented(title, names):
    text = _section("The dataset contract")
    part = text[text.index(title) :]
    missing = [n for n in set(names) if f"`{n}" not in part]
    assert not missing, f"undocumented in docs/plugins.md ({title}): {missing}"


def test_the_sensing_argument_and_shipped_protocols_are_documented():
    text = _section("The dataset contract")
    assert "`sensing=`" in text and "SensingOptions.from_config" in text
    assert '"package:path/in/package.yaml"' in text and "package-data" in text


# ------------------------------------------------------------------------------------------- protocols
def _package(tmp_path, monkeypatch, name="contract_pkg", protocol="protocol:\n  name: from-package\n  imgsz: 96\n"):
    pkg = tmp_path / "pkgs" / name
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    if protocol is not None:
        (pkg / "protocol.yaml").write_text(protocol)
    monkeypatch.syspath_prepend(str(tmp_path / "pkgs"))
    return pkg


def test_a_protocol_shipped_in_a_package_or_by_path_is_loaded(tmp_path, monkeypatch):
    from harness.config import load_config

    pkg = _package(tmp_path, monkeypatch)
    spec = DatasetSpec("contract-test", open=_Source, categories=("thing",), protocol="contract_pkg:protocol.yaml")
    cfg = load_config(protocol=spec.protocol)
    assert cfg["protocol"]["name"] == "from-package" and cfg["protocol"]["imgsz"] == 96
    assert cfg["meta"]["sources"][0] == str(pkg / "protocol.yaml")
    by_path = DatasetSpec("contract-test", open=_Source, categories=("thing",), protocol=pkg / "protocol.yaml")
    assert by_path.protocol == str(pkg / "protocol.yaml")  # a Path is kept as text (listings are JSON)
    assert load_config(protocol=by_path.protocol)["protocol"]["imgsz"] == 96
    assert load_config(protocol="m3t-4fold")["protocol"]["folds"]["P1"] == ["P1"]  # names are unchanged


@pytest.mark.parametrize(
    "protocol, message",
    [
        ("contract_pkg:missing.yaml", "no file .*missing.yaml"),
        ("no_such_pkg_xyz:protocol.yaml", "package 'no_such_pkg_xyz' cannot be imported"),
        ("protocols/mine.yaml", "is a relative path"),
        ("", "protocol must be"),
    ],
)
def test_a_bad_protocol_is_refused_when_the_plugin_registers(tmp_path, monkeypatch, harness_plugin, protocol, message):
    from harness.contracts import check_registered
    from harness.plugins import get_host

    _package(tmp_path, monkeypatch)
    spec = DatasetSpec("contract-test", open=_Source, categories=("thing",), protocol=protocol)
    with pytest.raises(PluginError, match=f"dataset 'contract-test': .*{message}"):
        check_registered(spec, DatasetSpec)

    class Plugin:
        @hookimpl
        def register_datasets(self, register):
            register(spec)

    harness_plugin(Plugin(), name="undo-bad-protocol")
    problems = [p for p in get_host().problems if p.plugin == "undo-bad-protocol"]
    assert len(problems) == 1 and re.search(f"dataset 'contract-test': .*{message}", problems[0].message)


# ------------------------------------------------------------------------------------------- open and prepare
def test_sensing_is_passed_only_to_an_open_that_takes_it_and_source_categories_win(tmp_path):
    from harness.cache import open_source, prepare, resolve_folds
    from harness.config import load_config

    cfg = load_config(protocol="default", overrides=["sensing.warp.crop=false"])
    with_sensing = DatasetSpec("contract-test", open=lambda root=None, sensing=None: _Source(sensing), categories=())
    _, source = open_source(with_sensing, cfg)
    assert source.sensing["warp"]["crop"] is False
    without = DatasetSpec("contract-test", open=lambda root=None: _Source(), categories=())
    _, source = open_source(without, cfg)
    assert source.sensing is None and isinstance(source, DatasetSource)

    ds = prepare(with_sensing, cfg, cache_root=tmp_path, progress=False)
    assert list(ds.categories) == ["thing", "other"] and ds.support()["categories"] == {"thing": 0, "other": 3}
    folds = resolve_folds(with_sensing, ds, cfg)
    assert [(f.name, f.val_groups) for f in folds] == [("a", ("a",)), ("b", ("b",))]  # none of its own: one per group


def test_skip_reasons_are_counted_by_their_label():
    report = PrepareReport()
    report.skip("x.png", "missing thermal partner: x_T.png not found")
    report.skip("y.png", "missing thermal partner: y_T.png not found")
    report.skip("a.json#annotation=3", "annotation box outside the image: [9, 9, 1, 1]")
    assert report.summary()["skip_reasons"] == {"missing thermal partner": 2, "annotation box outside the image": 1}
    assert Fold("a", ("b",), ("a",)).val_groups == ("a",)


# ------------------------------------------------------------------------------------------- the report
@pytest.mark.parametrize("sensing_stage", [False, True])
def test_report_shows_sensor_sections_only_for_datasets_with_a_sensing_stage(tmp_path, sensing_stage):
    pytest.importorskip("harness.evaluation")
    from harness.hookspecs import hookimpl
    from harness.report import build_report
    from report_fixtures import synthetic_store

    store = synthetic_store(tmp_path / "store", folds=("P1", "P2"), per_fold=3, detectors={"alpha": "strong"})

    class Plugin:
        @hookimpl
        def register_datasets(self, register):
            register(DatasetSpec("synth", open=_Source, categories=("thing",), sensing_stage=sensing_stage))

    with temporary_plugin(Plugin(), name="synth-sensing-stage-test"):
        report = build_report(store, resamples=0, formats=())
    keys = {s.key: s.absent for s in report.sections if s.dataset == "synth"}
    if sensing_stage:
        assert "harness sensing displacement" in keys["displacement"] and "registration" in keys
    else:
        assert "registration" not in keys and "displacement" not in keys and "folds" in keys
