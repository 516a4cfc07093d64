"""Shared fixtures. Installed third-party plugins are never auto-loaded in tests (results must not depend on what
else is installed): ``HARNESS_DISABLE_PLUGIN_AUTOLOAD`` is set before the harness loads any plugin. The plugin
fixtures are the ones the harness ships for plugin authors (``harness.testing``)."""

from __future__ import annotations

import os

os.environ["HARNESS_DISABLE_PLUGIN_AUTOLOAD"] = "1"
os.environ.pop("HARNESS_LOAD_PLUGINS", None)
os.environ.pop("HARNESS_PLUGINS_DIR", None)
# An unexpected exception in a command propagates with its traceback (the CLI would print a short `bug:` line and
# exit 70): tests of that path unset it.
os.environ["HARNESS_DEBUG"] = "1"

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

# Fixtures for every test module: ``engine_helpers`` (``shapes_run_plugins``: the shapes dataset and the example
# TinyDet registered for one test) and ``datasets_helpers`` (the tiny synthetic M3T set: ``tiny_source``, ``tiny``),
# in that order: ``datasets_helpers`` imports ``engine_helpers``, which pytest must load first to rewrite its asserts
pytest_plugins = ["harness.testing", "pytester", "engine_helpers", "datasets_helpers"]

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"


@pytest.fixture
def host(harness_host):
    """The plugin host with the built-in plugins loaded."""
    return harness_host


@pytest.fixture
def fresh_plugins(fresh_harness):
    """Start the plugin manager from scratch for this test and restore the normal state afterwards."""
    return fresh_harness


@pytest.fixture
def cli_runner():
    """Invoke the CLI in-process: ``cli_runner(["list", "--format", "json"])`` -> click Result."""
    from click.testing import CliRunner

    from harness.cli import get_cli

    runner = CliRunner()

    def invoke(args, **kw):
        return runner.invoke(get_cli(), args, catch_exceptions=False, **kw)

    return invoke


@pytest.fixture(scope="module")
def one_torch_thread():
    """One intra-op torch thread for a test module (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``):
    small tensors gain nothing from a second thread, and on a shared 2-core machine two threads can be 10x slower."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
