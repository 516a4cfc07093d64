"""The pytest plugin the harness ships for plugin authors (``harness.testing``): its fixtures work in a project of
their own, leave nothing registered behind, and it registers once however it is named."""

from __future__ import annotations

import tomllib

from engine_helpers import REPO

AUTHOR_TESTS = """
import click
from harness import DetectorSpec, hookimpl


class Plugin:
    @hookimpl
    def register_detectors(self, register):
        register(DetectorSpec(name="mine-det", build=lambda num_classes, **_: None))

    @hookimpl
    def register_commands(self, cli):
        @cli.command(name="mine-hello")
        def hello():
            click.echo("hello from mine")


def test_registered_for_this_test(harness_plugin, harness_host):
    assert harness_plugin(Plugin(), name="mine") == "mine"
    assert harness_host.owner("detector", "mine-det") == "mine"


def test_gone_afterwards(harness_host):
    assert "mine-det" not in harness_host.detectors()


def test_its_command_runs(harness_plugin, harness_cli):
    harness_plugin(Plugin())
    assert harness_cli(["mine-hello"]).output.strip() == "hello from mine"


def test_a_fresh_host_loads_again(fresh_harness):
    assert not fresh_harness.pm.list_name_plugin()
    assert "ours" in fresh_harness.load_plugins().detectors()
"""


def test_a_plugin_authors_tests_use_the_shipped_fixtures(harness_host, pytester):
    # the host first: pytester forgets, when it ends, every module imported after it began, and a plugin module
    # imported again later would no longer hold the functions the host registered (pickling them then fails)
    before = sorted(name for name, _ in harness_host.pm.list_name_plugin())
    pytester.makeconftest('pytest_plugins = ["harness.testing"]\n')
    pytester.makepyfile(test_mine=AUTHOR_TESTS)
    # named twice (conftest and -p), as with the entry point installed: registered once, no error
    result = pytester.runpytest_inprocess("-p", "harness.testing", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=4)
    assert sorted(name for name, _ in harness_host.pm.list_name_plugin()) == before
    assert "mine-det" not in harness_host.detectors()


def test_the_pytest_plugin_is_declared_under_its_module_name():
    entry_points = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["entry-points"]
    assert entry_points["pytest11"] == {"harness.testing": "harness.testing"}


def test_the_old_import_of_temporary_plugin_still_works_with_a_deprecation():
    import warnings

    import harness.plugins
    import harness.testing

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert harness.plugins.temporary_plugin is harness.testing.temporary_plugin
    assert [w.category for w in caught] == [DeprecationWarning] and "harness.testing" in str(caught[0].message)
