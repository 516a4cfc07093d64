"""A pytest plugin for testing harness plugins (and the harness itself): throwaway plugins, a fresh host, the CLI.

It is registered through the ``pytest11`` entry point of rgbt-harness, so installing the harness makes the fixtures
available; ``pytest_plugins = ["harness.testing"]`` in a ``conftest.py`` (or ``pytest -p harness.testing``) names it
explicitly, and ``-p no:harness.testing`` turns it off. Importing it imports no plugin: nothing is loaded before a
fixture asks.

Fixtures:

``harness_host``
    the plugin host with every plugin loaded (``harness.plugins.load_plugins()``).
``harness_plugin``
    ``harness_plugin(obj, name=None) -> str`` registers a module, class or object with ``@hookimpl`` functions for
    this test and unregisters it afterwards, whatever happens. A plugin already loaded through its entry point (your
    package installed in development mode) is used as it is and left loaded.
``harness_cli``
    ``harness_cli(["list", "--format", "json"]) -> click.testing.Result``: the ``harness`` command line run
    in-process, with the commands of every plugin registered at that moment (stdout and stderr apart:
    ``result.stdout``).
``fresh_harness``
    the ``harness.plugins`` module with nothing registered, for tests of loading itself (entry points, plugin
    folders, the allow-list): call ``fresh_harness.load_plugins()``; the normal state is restored afterwards.

For a ``with`` block (or a fixture of wider scope) use ``temporary_plugin(obj, name)``; ``reset_plugins()`` forgets
everything registered. Set ``HARNESS_DISABLE_PLUGIN_AUTOLOAD=1`` before the harness loads its plugins to keep other
installed plugins out of your tests (the harness's own ``tests/conftest.py`` does).
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Any, Callable, Iterator

import pytest

# temporary_plugin and reset_plugins come from __getattr__ below
__all__ = ["temporary_plugin", "reset_plugins", "harness_host", "harness_plugin", "harness_cli", "fresh_harness"]  # noqa: F822


def __getattr__(name: str) -> Any:
    """``temporary_plugin`` and ``reset_plugins``, the plugin host's own, looked up on first use: pytest imports this
    module at every start (``pytest11``), and it imports nothing of the harness until a test asks."""
    if name in ("temporary_plugin", "reset_plugins"):
        from harness import plugins

        return plugins._temporary_plugin if name == "temporary_plugin" else plugins.reset_plugins
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if TYPE_CHECKING:  # pragma: no cover
    from types import ModuleType

    from click.testing import Result

    from harness.plugins import PluginHost


@pytest.fixture
def harness_host() -> PluginHost:
    """The plugin host with every plugin loaded."""
    from harness.plugins import load_plugins

    return load_plugins()


@pytest.fixture
def harness_plugin() -> Iterator[Callable[..., str]]:
    """``harness_plugin(obj, name=None) -> name``: register a throwaway plugin for this test."""
    from harness.plugins import pm, register_plugin, unregister_plugin

    mine: list[str] = []

    def register(plugin: Any, name: str | None = None) -> str:
        if pm.is_registered(plugin):  # already loaded (through its entry point): leave it as it is
            return pm.get_name(plugin) or str(name)
        mine.append(register_plugin(plugin, name))
        return mine[-1]

    try:
        yield register
    finally:
        for name in reversed(mine):
            unregister_plugin(name)


@pytest.fixture
def harness_cli() -> Callable[..., Result]:
    """``harness_cli(args, **kwargs) -> Result``: run the ``harness`` CLI in-process (``click.testing.CliRunner``)."""
    from click.testing import CliRunner

    from harness.cli import get_cli
    from harness.plugins import load_plugins

    runner = CliRunner()

    def invoke(args: list[str], **kwargs: Any) -> Result:
        group = copy.copy(get_cli())  # a new group each call: the commands of the plugins registered now
        group.commands = {}
        load_plugins().add_commands(group)
        return runner.invoke(group, args, catch_exceptions=False, **kwargs)

    return invoke


@pytest.fixture
def fresh_harness() -> Iterator[ModuleType]:
    """The plugin machinery with nothing loaded; the normal state (every plugin loaded) is restored afterwards."""
    from harness import plugins

    plugins.reset_plugins()
    try:
        yield plugins
    finally:
        plugins.reset_plugins(plugins.load_plugins)
