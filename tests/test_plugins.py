"""The plugin host: registration hooks, discovery, allow-list, conflicts, broken plugins, listings."""

from __future__ import annotations

import importlib.metadata
import json
import sys
import types

import click
import pytest

from harness import DatasetSpec, DetectorSpec, EncodingSpec, hookimpl
from harness.errors import PluginError, UnknownNameError
from harness.testing import temporary_plugin


def _build(num_classes, in_channels=4, **_):  # a detector builder that is never called in these tests
    raise AssertionError("not built in this test")


def registering(hook: str, *records):
    """A throwaway plugin whose ``hook`` (``register_datasets``, ...) registers ``records``."""

    def impl(register):
        for record in records:
            register(record)

    return types.SimpleNamespace(**{hook: hookimpl(impl)})


def make_detector_plugin(*names, name="undo-plugin", raise_after=None):
    class Plugin:
        __name__ = name

        @hookimpl
        def register_detectors(self, register):
            for i, n in enumerate(names):
                if raise_after is not None and i == raise_after:
                    raise RuntimeError("boom while registering")
                register(DetectorSpec(name=n, build=_build, input_kind="single", description=f"detector {n}"))

    return Plugin()


# ------------------------------------------------------------------ one test per hook
def test_hook_register_detectors(host):
    with temporary_plugin(make_detector_plugin("undo-det"), name="undo-det-plugin"):
        spec = host.detector("undo-det")
        assert spec.input_kind == "single"
        assert host.owner("detector", "undo-det") == "undo-det-plugin"
    with pytest.raises(UnknownNameError, match="undo-det"):
        host.detector("undo-det")


def test_hook_register_datasets(host):
    plugin = registering(
        "register_datasets", DatasetSpec(name="undo-ds", open=lambda root=None: None, categories=("a", "b"))
    )
    with temporary_plugin(plugin, name="undo-ds-plugin"):
        assert host.dataset("undo-ds").categories == ("a", "b")
    assert "undo-ds" not in host.datasets()


def test_hook_register_encodings(host):
    import numpy as np

    plugin = registering(
        "register_encodings", EncodingSpec(name="undo-enc", fn=lambda s: np.zeros(s.ir8.shape, np.uint8), needs="ir8")
    )
    with temporary_plugin(plugin, name="undo-enc-plugin"):
        assert host.encoding("undo-enc").needs == "ir8"
    assert "undo-enc" not in host.encodings()


def test_hook_register_loggers(host):
    from harness.tracking import LoggerSpec

    plugin = registering("register_loggers", LoggerSpec(name="undo-logger", create=lambda options: None))
    with temporary_plugin(plugin, name="undo-logger-plugin"):
        assert host.logger("undo-logger").name == "undo-logger"
        assert {"mlflow", "tensorboard"} <= set(host.loggers())
    assert "undo-logger" not in host.loggers()


def test_hook_register_commands(host):
    class Plugin:
        @hookimpl
        def register_commands(self, cli):
            @cli.command(name="undo-hello")
            def hello():
                click.echo("hello from a plugin")

    group = click.Group(name="test-cli")
    with temporary_plugin(Plugin(), name="undo-cmd-plugin"):
        host.add_commands(group)
        assert "undo-hello" in group.commands
        assert host.owner("command", "undo-hello") == "undo-cmd-plugin"
        from click.testing import CliRunner

        assert CliRunner().invoke(group, ["undo-hello"]).output.strip() == "hello from a plugin"


# ------------------------------------------------------------------ conflicts and broken plugins
def test_duplicate_name_is_an_error_naming_both_plugins(host):
    with (
        temporary_plugin(make_detector_plugin("undo-twin"), name="first-plugin"),
        temporary_plugin(make_detector_plugin("undo-twin", "undo-other"), name="second-plugin"),
    ):
        with pytest.raises(PluginError) as err:
            host.detector("undo-twin")
        assert "first-plugin" in str(err.value) and "second-plugin" in str(err.value)
        conflicts = [p for p in host.problems if p.stage == "conflict"]
        assert (
            len(conflicts) == 1 and "first-plugin" in conflicts[0].message and "second-plugin" in conflicts[0].message
        )
        # the rest of the second plugin still works
        assert host.detector("undo-other").name == "undo-other"


def test_plugin_raising_at_registration_is_reported_and_others_load(host):
    with (
        temporary_plugin(make_detector_plugin("undo-a", "undo-b", raise_after=1), name="broken-plugin"),
        temporary_plugin(make_detector_plugin("undo-good"), name="good-plugin"),
    ):
        names = host.detectors()
        assert "undo-good" in names
        assert "undo-a" not in names  # a plugin that raised contributes nothing half-registered
        problems = [p for p in host.problems if p.plugin == "broken-plugin"]
        assert problems and "boom while registering" in problems[0].message
        with pytest.raises(UnknownNameError, match="broken-plugin"):
            host.detector("undo-a")


def test_register_rejects_wrong_record_type(host):
    with temporary_plugin(registering("register_detectors", {"name": "not-a-spec"}), name="sloppy-plugin"):
        assert any(p.plugin == "sloppy-plugin" and "DetectorSpec" in p.message for p in host.problems)


@pytest.mark.parametrize(
    "hook, record, message",
    [
        ("register_detectors", DetectorSpec(name="x", build=_build, input_kind="triple"), "input_kind"),
        ("register_detectors", DetectorSpec(name="Bad Name", build=_build), "invalid detector name"),
        ("register_encodings", EncodingSpec(name="e", fn=lambda s: None, channels=3), "channels"),
    ],
)
def test_invalid_spec_fields_are_errors_when_the_record_is_registered(host, hook, record, message):
    from harness.contracts import check_record

    with pytest.raises(PluginError, match=message):
        check_record(record)
    with temporary_plugin(registering(hook, record), name="undo-invalid-record"):
        problems = [p for p in host.problems if p.plugin == "undo-invalid-record"]
        assert len(problems) == 1 and message in problems[0].message, problems


# ------------------------------------------------------------------ discovery through entry points
class FakeDist:
    """Enough of importlib.metadata.Distribution for entry-point discovery."""

    def __init__(self, name, version, eps):
        self.metadata = {"Name": name}
        self.version = version
        self.entry_points = eps


def _install_fake(monkeypatch, dist_name, module_name, detector_name, version="1.2.3", broken=False):
    module = types.ModuleType(module_name)
    if broken:
        ep_target = f"{module_name}_missing_module"
    else:

        @hookimpl
        def register_detectors(register):
            register(DetectorSpec(name=detector_name, build=_build, input_kind="dual"))

        module.register_detectors = register_detectors
        monkeypatch.setitem(sys.modules, module_name, module)
        ep_target = module_name
    ep = importlib.metadata.EntryPoint(name=module_name, value=ep_target, group="harness")
    return FakeDist(dist_name, version, [ep])


@pytest.fixture
def fake_dists(monkeypatch):
    dists = [
        _install_fake(monkeypatch, "harness-alpha", "harness_alpha", "alpha-det"),
        _install_fake(monkeypatch, "harness-beta", "harness_beta", "beta-det", version="0.9"),
        FakeDist("unrelated", "1.0", [importlib.metadata.EntryPoint(name="x", value="os", group="console_scripts")]),
    ]
    monkeypatch.setattr(importlib.metadata, "distributions", lambda: iter(dists))
    return dists


def test_entry_point_plugins_are_discovered(fresh_plugins, fake_dists, monkeypatch):
    monkeypatch.delenv("HARNESS_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    host = fresh_plugins.load_plugins()
    assert {"alpha-det", "beta-det"} <= set(host.detectors())
    info = {r["name"]: r for r in host.plugin_info()}
    assert info["harness_alpha"]["distribution"] == "harness-alpha"
    assert info["harness_alpha"]["version"] == "1.2.3"
    assert info["harness_alpha"]["hooks"] == ["register_detectors"]
    assert info["harness_alpha"]["registered"] == {"detectors": ["alpha-det"]}
    assert info["harness_alpha"]["builtin"] is False


def test_autoload_switch_disables_entry_points(fresh_plugins, fake_dists, monkeypatch):
    monkeypatch.setenv("HARNESS_DISABLE_PLUGIN_AUTOLOAD", "1")
    host = fresh_plugins.load_plugins()
    assert "alpha-det" not in host.detectors()


@pytest.mark.parametrize(
    "allow, expected",
    [("harness-alpha", {"alpha-det"}), ("harness_beta,harness-alpha", {"alpha-det", "beta-det"}), ("", set())],
)
def test_allow_list(fresh_plugins, fake_dists, monkeypatch, allow, expected):
    monkeypatch.setenv("HARNESS_LOAD_PLUGINS", allow)
    monkeypatch.setenv("HARNESS_DISABLE_PLUGIN_AUTOLOAD", "1")  # the allow-list wins over the switch
    host = fresh_plugins.load_plugins()
    assert {"alpha-det", "beta-det"} & set(host.detectors()) == expected


def test_entry_point_that_fails_to_import_is_reported(fresh_plugins, monkeypatch):
    dists = [
        _install_fake(monkeypatch, "harness-broken", "harness_broken", "never", broken=True),
        _install_fake(monkeypatch, "harness-alpha", "harness_alpha", "alpha-det"),
    ]
    monkeypatch.setattr(importlib.metadata, "distributions", lambda: iter(dists))
    monkeypatch.delenv("HARNESS_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    host = fresh_plugins.load_plugins()
    assert "alpha-det" in host.detectors()
    assert any(p.plugin == "harness_broken" and p.stage == "import" for p in host.problems)


@pytest.fixture
def load_plugin_files(fresh_plugins, monkeypatch, tmp_path, caplog):
    """``load_plugin_files(module=source, ...) -> host``: the modules written into a plugins folder (``--plugins-dir``)
    and every plugin loaded from scratch, warnings captured by ``caplog``."""

    def load(**modules: str):
        for name, source in modules.items():
            (tmp_path / f"{name}.py").write_text(source)
        monkeypatch.setenv("HARNESS_PLUGINS_DIR", str(tmp_path))
        with caplog.at_level("WARNING", logger="harness.plugins"):
            return fresh_plugins.load_plugins()

    return load


def test_misspelled_hook_is_reported_by_check_pending(load_plugin_files):
    host = load_plugin_files(
        typo_plugin="from harness import hookimpl\n\n@hookimpl\ndef register_detector(register):\n    pass\n",
        fine_plugin="from harness import hookimpl, EncodingSpec\n\n@hookimpl\ndef register_encodings(register):\n"
        "    register(EncodingSpec(name='dir-enc', fn=lambda s: None, channels=0, needs=None))\n",
    )
    assert any(p.plugin == "typo_plugin" and "register_detector" in p.message for p in host.problems)
    assert "dir-enc" in host.encodings()


def test_a_hook_name_typo_names_the_plugin_and_the_nearest_hook(load_plugin_files, caplog):
    host = load_plugin_files(
        typo_det="from harness import hookimpl, DetectorSpec\n\n@hookimpl\ndef register_detector(register):\n"
        "    register(DetectorSpec(name='mydet', build=lambda n, **k: None, input_kind='single'))\n"
    )
    [problem] = [p for p in host.problems if p.plugin == "typo_det"]
    assert "unknown hook 'register_detector', did you mean 'register_detectors'?" in problem.message
    assert "typo_det" in caplog.text and "did you mean 'register_detectors'" in caplog.text
    with pytest.raises(UnknownNameError) as err:
        host.detector("mydet")
    assert "plugin 'typo_det'" in str(err.value) and "did you mean 'register_detectors'" in str(err.value)


def test_registering_an_object_with_a_hook_typo_is_a_plugin_error(host):
    from harness.errors import PluginError
    from harness.plugins import pm, register_plugin

    class Typo:
        @hookimpl
        def register_dataset(self, register):
            pass

    before = len(pm.list_name_plugin())
    with pytest.raises(
        PluginError, match=r"plugin 'typo-object'.*'register_dataset', did you mean 'register_datasets'"
    ):
        register_plugin(Typo(), name="typo-object")
    assert len(pm.list_name_plugin()) == before  # not kept


def test_a_hook_like_function_without_hookimpl_is_reported(load_plugin_files, caplog):
    host = load_plugin_files(
        forgot_marker="from harness import DetectorSpec\n\ndef register_detectors(register):\n"
        "    register(DetectorSpec(name='unmarked', build=lambda n, **k: None, input_kind='single'))\n"
    )
    assert "forgot_marker" in caplog.text and "@hookimpl" in caplog.text
    assert any(p.plugin == "forgot_marker" and "no @hookimpl" in p.message for p in host.problems)
    assert not [p for p in host.problems if p.plugin.startswith(("harness.", "adapters."))]  # built-ins are clean
    with pytest.raises(Exception, match=r"unknown detector 'unmarked'.*forgot_marker.*no @hookimpl"):
        host.detector("unmarked")


def test_load_plugins_is_idempotent(host):
    from harness.plugins import load_plugins, pm

    before = len(pm.list_name_plugin())
    assert load_plugins() is host
    assert len(pm.list_name_plugin()) == before


# ------------------------------------------------------------------ documentation of the plugin API
def test_every_hook_is_documented_and_tested():
    from pathlib import Path

    from harness import hookspecs
    from harness.plugins import pm

    hooks = sorted(n for n in dir(hookspecs) if hasattr(getattr(hookspecs, n), "harness_spec"))
    assert set(hooks) <= set(dir(pm.hook))
    assert hooks == [
        "register_commands",
        "register_datasets",
        "register_detectors",
        "register_encodings",
        "register_loggers",
    ]
    guide = (Path(__file__).resolve().parent.parent / "docs" / "plugins.md").read_text()
    this_file = Path(__file__).read_text()
    for name in hooks:
        doc = getattr(hookspecs, name).__doc__ or ""
        assert len(doc.split()) >= 20, f"hook {name} needs a real docstring"
        assert f"`{name}" in guide, f"hook {name} is missing from docs/plugins.md"
        assert f"def test_hook_{name}(" in this_file, f"hook {name} has no test_hook_{name}"


# ------------------------------------------------------------------ CLI listings
def test_cli_list_and_plugins(cli_runner):
    with temporary_plugin(make_detector_plugin("undo-cli-det"), name="undo-cli-plugin"):
        result = cli_runner(["list"])
        assert result.exit_code == 0
        assert "undo-cli-det" in result.output and "single-stream" in result.output
        data = json.loads(cli_runner(["list", "--format", "json"]).stdout)
        assert any(d["name"] == "undo-cli-det" and d["plugin"] == "undo-cli-plugin" for d in data["detectors"])
        plugins = json.loads(cli_runner(["plugins"]).stdout)["plugins"]
        rec = next(p for p in plugins if p["name"] == "undo-cli-plugin")
        assert rec["registered"] == {"detectors": ["undo-cli-det"]}
        only = json.loads(cli_runner(["plugins", "--hook", "register_detectors"]).stdout)["plugins"]
        assert all("register_detectors" in p["hooks"] for p in only)


def test_cli_reports_harness_errors_without_traceback(cli_runner):
    @click.command(name="undo-fail")
    def fail():
        from harness.errors import DataError

        raise DataError("data/x.json: invalid JSON at line 3")

    from harness.cli import get_cli

    cli = get_cli()
    cli.add_command(fail)
    try:
        result = cli_runner(["undo-fail"])
    finally:
        cli.commands.pop("undo-fail")
    assert result.exit_code == 2
    assert "error: data/x.json: invalid JSON at line 3" in result.output
    assert "Traceback" not in result.output
