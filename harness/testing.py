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
``harness_batch_check``
    ``harness_batch_check(model, inputs, batches=(1, 2, 8))`` fails the test when the model's eval-mode detections
    of ``inputs`` (a ``[N, C, H, W]`` tensor, or a tuple of them for a dual-stream model) change with the number of
    images predicted at once (``eval.batch``) beyond the harness's bound (``assert_batch_independent``).

For a ``with`` block (or a fixture of wider scope) use ``temporary_plugin(obj, name)``; ``reset_plugins()`` forgets
everything registered. Set ``HARNESS_DISABLE_PLUGIN_AUTOLOAD=1`` before the harness loads its plugins to keep other
installed plugins out of your tests (the harness's own ``tests/conftest.py`` does).
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Any, Callable, Iterator

import pytest

# temporary_plugin and reset_plugins come from __getattr__ below
__all__ = [  # noqa: F822
    "temporary_plugin",
    "reset_plugins",
    "assert_batch_independent",
    "harness_host",
    "harness_plugin",
    "harness_cli",
    "fresh_harness",
    "harness_batch_check",
]


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


def assert_batch_independent(
    model: Any,
    inputs: Any,
    batches: tuple[int, ...] = (1, 2, 8),
    score_tol: float | None = None,
    box_tol: float | None = None,
) -> None:
    """Fail (``AssertionError``) when ``model``'s eval-mode detections of ``inputs`` change with the prediction batch:
    every detection at each batch of ``batches`` needs a counterpart at the first (same image and label) within
    ``score_tol`` in score and ``box_tol`` pixels in each box coordinate, both ways. The defaults are the harness's
    bounds (``harness.engine.predict.BATCH_SCORE_TOL``, ``BATCH_BOX_TOL``): what kernel arithmetic may change. Use
    inputs whose detections are not at a threshold (the model's ``conf``, its ``max_det``)."""
    from harness.engine import predict as P

    score_tol = P.BATCH_SCORE_TOL if score_tol is None else score_tol
    box_tol = P.BATCH_BOX_TOL if box_tol is None else box_tol
    for b, ch in P.batch_changes(model, inputs, batches).items():
        assert ch.within(score_tol, box_tol), (
            f"predictions {b} images at a time differ from {batches[0]} at a time: largest score change "
            f"{ch.score:.3g} (bound {score_tol:g}), largest box change {ch.box:.3g} px (bound {box_tol:g}), "
            f"{ch.unmatched} of {ch.detections} detections without a counterpart: does the model mix the images of a "
            f"batch (BatchNorm in train mode, padding to the batch's largest image, a batch-wide threshold)?"
        )


@pytest.fixture
def harness_batch_check() -> Callable[..., None]:
    """``harness_batch_check(model, inputs, batches=(1, 2, 8))``: ``assert_batch_independent``."""
    return assert_batch_independent
