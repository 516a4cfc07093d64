"""The plugin contracts are typed in one module and checked where a plugin's output enters: one test per hole that
the contracts had (a command or name that silently replaced another, an opened dataset or an encoding's output that
was never checked, a contract record that was not exported)."""

from __future__ import annotations

import importlib.metadata
import re
import sys
import types

import click
import numpy as np
import pytest

from engine_helpers import ContractSource as _Good
from harness import DatasetSpec, DetectorSpec, EncodingSpec, Fold, hookimpl
from harness.errors import DataError, PluginError


# ------------------------------------------------------------------------------------------- one module, exported
def test_every_contract_record_is_exported_from_harness_and_the_old_paths_are_the_same_objects():
    import harness
    from harness import api
    from harness.sample import AlignedSample as old_sample
    from harness.sample import validate_sample as old_validate
    from harness.tracking import LoggerSpec as tracking_logger
    from harness.tracking.spec import LoggerSpec as old_logger
    from harness.tracking.spec import RunLogger, TrackingOptions

    for name in (
        "DetectorSpec",
        "Reference",
        "DatasetSpec",
        "DatasetSource",
        "Fold",
        "PrepareReport",
        "AlignedSample",
        "EncodingSpec",
        "LoggerSpec",
        "RunLogger",
        "TrackingOptions",
        "CommandGroup",
    ):
        assert getattr(harness, name) is getattr(api, name), name
        assert name in harness.__all__
    assert old_sample is api.AlignedSample and old_logger is tracking_logger is api.LoggerSpec
    assert RunLogger is api.RunLogger and TrackingOptions is api.TrackingOptions
    assert old_validate is harness.validate_sample


def test_a_dual_stream_detectors_input_channels_are_worked_out_in_one_place(monkeypatch):
    """``DetectorSpec.model_channels`` is what the runner's check, its training and profiling all build with."""
    from harness.profiling import build_detector
    from harness.runner import check_settings

    built = []

    def build(num_classes, in_channels, **_):
        built.append(in_channels)
        import torch

        return torch.nn.Identity()

    dual = DetectorSpec(name="undo-dual", build=build, input_kind="dual", thermal_channels=1)
    single = DetectorSpec(name="undo-single", build=build)
    assert (dual.model_channels(4), single.model_channels(4), single.model_channels(3)) == (1, 4, 3)

    class Host:
        def detector(self, name):
            return dual

    build_detector("undo-dual", in_channels=4, host=Host())
    enc = EncodingSpec(name="undo-enc", fn=lambda s: None, channels=1)
    check_settings(dual, types.SimpleNamespace(categories=("a",)), enc, {"train": {}, "model": {}})
    assert built == [1, 1]


# ------------------------------------------------------------------------------------------- name clashes
class _CommandPlugin:
    """Adds ``list`` (a built-in command's name) and a command of its own."""

    @hookimpl
    def register_commands(self, cli):
        cli.add_command(click.Command("list", callback=lambda: click.echo("the plugin's list")))
        cli.add_command(click.Command("undo-own", callback=lambda: click.echo("own")))


def test_a_plugin_command_named_like_a_builtin_is_a_conflict_naming_both(harness_host, harness_plugin):
    from click.testing import CliRunner

    harness_plugin(_CommandPlugin(), name="undo-shadow-plugin")
    group = click.Group(name="undo-cli")
    harness_host.add_commands(group)

    clash = [p for p in harness_host.problems if p.stage == "conflict" and "'list'" in p.message]
    assert len(clash) == 1
    assert "harness.commands.core" in clash[0].message and "undo-shadow-plugin" in clash[0].message
    assert harness_host.owner("command", "list") == "harness.commands.core"  # the first stays the owner
    result = CliRunner().invoke(group, ["list", "--format", "json"])
    assert result.exit_code != 0 and "the plugin's list" not in result.output
    assert isinstance(result.exception, PluginError)
    assert "harness.commands.core" in str(result.exception) and "undo-shadow-plugin" in str(result.exception)
    assert CliRunner().invoke(group, ["undo-own"]).output.strip() == "own"  # its other command works

    record = next(r for r in harness_host.plugin_info() if r["name"] == "undo-shadow-plugin")
    assert record["registered"] == {"commands": ["undo-own"]} and record["conflicts"] == {"commands": ["list"]}


def test_the_cli_lists_the_command_clash_under_problems(harness_plugin, harness_cli):
    import json

    harness_plugin(_CommandPlugin(), name="undo-shadow-cli")
    out = json.loads(harness_cli(["plugins"]).stdout)
    assert any(
        p["plugin"] == "undo-shadow-cli" and p["stage"] == "conflict" and "'list'" in p["message"]
        for p in out["problems"]
    )
    mine = next(p for p in out["plugins"] if p["name"] == "undo-shadow-cli")
    assert mine["conflicts"] == {"commands": ["list"]}


def test_a_plugin_that_raises_while_adding_commands_adds_none(harness_host, harness_plugin):
    class Half:
        @hookimpl
        def register_commands(self, cli):
            @cli.command(name="undo-half")
            def half():
                pass

            raise RuntimeError("boom after one command")

    harness_plugin(Half(), name="undo-half-plugin")
    group = click.Group(name="undo-cli")
    harness_host.add_commands(group)
    assert "undo-half" not in group.commands and "list" in group.commands
    assert any(p.plugin == "undo-half-plugin" and "boom" in p.message for p in harness_host.problems)


def test_a_detector_name_two_plugins_register_is_listed_for_both(harness_host, harness_plugin):
    def plugin():
        class P:
            @hookimpl
            def register_detectors(self, register):
                register(DetectorSpec(name="undo-same", build=lambda n, **_: None))

        return P()

    harness_plugin(plugin(), name="undo-first")
    harness_plugin(plugin(), name="undo-second")
    info = {r["name"]: r for r in harness_host.plugin_info()}
    assert info["undo-first"]["conflicts"] == info["undo-second"]["conflicts"] == {"detectors": ["undo-same"]}
    assert harness_host.conflicts()["detector"]["undo-same"] == ["undo-first", "undo-second"]


def test_one_entry_point_name_in_two_distributions_is_a_conflict_naming_both(fresh_harness, monkeypatch):
    def dist(name, module):
        mod = types.ModuleType(module)
        monkeypatch.setitem(sys.modules, module, mod)
        ep = importlib.metadata.EntryPoint(name="undo-same-ep", value=module, group="harness")
        return types.SimpleNamespace(metadata={"Name": name}, version="1.0", entry_points=[ep])

    dists = [dist("harness-one", "undo_one_mod"), dist("harness-two", "undo_two_mod")]
    monkeypatch.setattr(importlib.metadata, "distributions", lambda: iter(dists))
    monkeypatch.delenv("HARNESS_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    host = fresh_harness.load_plugins()
    clash = [p for p in host.problems if p.stage == "conflict" and p.plugin == "undo-same-ep"]
    assert len(clash) == 1 and "'harness-one'" in clash[0].message and "'harness-two'" in clash[0].message


def test_registering_a_plugin_under_a_taken_name_is_a_plugin_error(harness_plugin):
    from harness.plugins import register_plugin

    with pytest.raises(PluginError, match="plugin name 'harness.commands.core' is already registered"):
        register_plugin(types.SimpleNamespace(), name="harness.commands.core")


def test_a_logger_name_follows_the_rule_of_every_other_name():
    from harness import LoggerSpec
    from harness.contracts import check_registered

    with pytest.raises(PluginError, match="invalid logger name 'My Logger'"):
        check_registered(LoggerSpec(name="My Logger", create=lambda options: None), LoggerSpec)


def test_the_contract_records_are_plain_data_and_import_nothing_of_the_harness():
    import ast
    import inspect

    from harness import api

    tree = ast.parse(inspect.getsource(api))
    imported = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    imported += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    assert not [m for m in imported if m and m.split(".")[0] == "harness"], imported
    # a record is built without running a check: the check is the boundary's (registration, check_folds)
    assert DetectorSpec(name="Not A Name", build=lambda nc: None).name == "Not A Name"


def test_the_checks_do_not_import_the_plugin_host():
    import ast
    import inspect

    from harness import contracts

    tree = ast.parse(inspect.getsource(contracts))
    imported = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert "harness.plugins" not in imported


# ------------------------------------------------------------------------------------------- opened datasets
class _NoSamples(_Good):
    samples = None  # type: ignore[assignment]


class _NoneFingerprint(_Good):
    def fingerprint(self):
        return None


class _DictFolds(_Good):
    def folds(self):
        return [{"name": "a", "train_groups": ["b"], "val_groups": ["a"]}]


class _GroupsText(_Good):
    def groups(self):
        return "ab"


@pytest.mark.parametrize(
    "source, message",
    [
        (_NoSamples, r"open\(\) returned _NoSamples, which has no samples\(\)"),
        (_NoneFingerprint, r"fingerprint\(\) must return a non-empty string.*got None"),
        (_DictFolds, r"folds\(\) must return Fold records"),
        (_GroupsText, r"groups\(\) must return a list of non-empty strings, got 'ab'"),
    ],
)
def test_what_open_returns_is_checked_at_the_boundary(tmp_path, source, message):
    from harness.cache import prepare
    from harness.config import load_config

    spec = DatasetSpec("undo-src", open=lambda root=None: source(), categories=("thing",))
    with pytest.raises(PluginError, match=rf"dataset 'undo-src' \(plugin {__name__}\): {message}"):
        prepare(spec, load_config(protocol="default"), cache_root=tmp_path, progress=False)
    assert not list(tmp_path.rglob("manifest.json"))


def test_a_source_that_yields_something_else_than_a_sample_gets_a_counted_skip(tmp_path):
    from harness.cache import prepare
    from harness.config import load_config

    class Mixed(_Good):
        def samples(self, report):
            yield {"image_id": 9}
            yield from super().samples(report)

    spec = DatasetSpec("undo-src", open=lambda root=None: Mixed(), categories=("thing",))
    with pytest.raises(DataError, match=r"invalid-samples: 1 of the 4 samples the dataset yielded break the sample"):
        prepare(spec, load_config(protocol="default"), cache_root=tmp_path, progress=False)
    cfg = load_config(protocol="default", overrides=["inputs.accept=[invalid-samples]"])
    ds = prepare(spec, cfg, cache_root=tmp_path, progress=False)
    assert len(ds) == 3 and [r["kind"] for r in ds.input_risks] == ["invalid-samples"]
    assert ds.manifest["report"]["skip_reasons"] == {"invalid sample": 1}
    assert ds.manifest["report"]["skipped_files"] == [["dict", "invalid sample: expected an AlignedSample, got dict"]]


# ------------------------------------------------------------------------------------------- encodings
@pytest.mark.parametrize("form", ["raw", "compact"])
@pytest.mark.parametrize(
    "returned, got",
    [
        (lambda s: s.ir8.tolist(), "list"),
        (lambda s: s.ir8.astype(np.float32), "a float32 array of shape (8, 8)"),
        (lambda s: None, "NoneType"),
    ],
)
def test_an_encodings_output_is_checked_once_for_both_cache_forms(tmp_path, form, returned, got, harness_plugin):
    from harness.cache import PreparedWriter

    class Plugin:
        @hookimpl
        def register_encodings(self, register):
            register(EncodingSpec(name="undo-bad-enc", fn=returned, needs="ir8"))

    harness_plugin(Plugin(), name="undo-enc-plugin")
    from harness.plugins import get_host

    with PreparedWriter(tmp_path / "ds", "undo-src", _Good.categories, form=form) as writer:
        for sample in _Good().samples(None):
            writer.add(sample)
    from harness.cache import PreparedDataset

    ds = PreparedDataset(tmp_path / "ds")
    expected = (
        f"encoding 'undo-bad-enc' (plugin undo-enc-plugin): sample 1: fn returned {got}, expected a uint8 "
        "numpy array of shape (8, 8)"
    )
    with pytest.raises(PluginError, match=re.escape(expected)):
        ds.channel(0, get_host().encoding("undo-bad-enc"))


def test_an_exception_in_an_encoding_names_the_encoding_and_its_plugin(harness_plugin):
    def broken(sample):
        raise ValueError("no such channel")

    class Plugin:
        @hookimpl
        def register_encodings(self, register):
            register(EncodingSpec(name="undo-raising-enc", fn=broken, needs="ir8"))

    harness_plugin(Plugin(), name="undo-raising-plugin")
    from harness.contracts import encode
    from harness.plugins import get_host

    sample = next(_Good().samples(None))
    with pytest.raises(
        PluginError,
        match=r"encoding 'undo-raising-enc' \(plugin undo-raising-plugin\): sample 1: "
        r"fn\(\) raised ValueError: no such channel \(at .*test_contracts.py:\d+\)",
    ):
        encode(get_host().encoding("undo-raising-enc"), sample)


def test_a_fold_record_is_still_checked():
    from harness.contracts import check_folds, check_record

    with pytest.raises(PluginError, match="both trained on and held out"):
        check_record(Fold("x", ("a",), ("a",)))
    with pytest.raises(PluginError, match=r"dataset 'd': folds\(\): fold 'x': groups \['a'\] are both trained on"):
        check_folds([Fold("y", ("a",), ("b",)), Fold("x", ("a",), ("a",))], "dataset 'd'")


def test_commands_added_again_after_a_host_reset_are_no_conflict(harness_host):
    from harness.plugins import load_plugins, unload_plugins

    group = click.Group(name="undo-cli")
    harness_host.add_commands(group)
    unload_plugins()  # the host forgets; the group keeps its commands
    host = load_plugins()
    host.add_commands(group)
    assert not [p for p in host.problems if p.stage == "conflict"]
    from click.testing import CliRunner

    assert CliRunner().invoke(group, ["list", "--format", "json"]).exit_code == 0
    assert host.owner("command", "list") == "harness.commands.core"


def test_the_cli_group_handed_to_plugins_follows_the_command_contract():
    from harness import CommandGroup
    from harness.cli import get_cli

    assert isinstance(get_cli(), CommandGroup) and isinstance(click.Group(), CommandGroup)
    assert not isinstance(object(), CommandGroup)
