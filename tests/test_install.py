"""The installed console script works: `harness --help`, `harness list`, `harness plugins`."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest


def harness_cmd():
    script = Path(sys.executable).parent / "harness"
    if script.exists():
        return [str(script)]
    if shutil.which("harness"):
        return ["harness"]
    return [sys.executable, "-m", "harness"]


@pytest.mark.parametrize("args", [["--help"], ["list"], ["plugins"], ["--version"]])
def test_console_script(args, tmp_path):
    env = {**os.environ, "HARNESS_DISABLE_PLUGIN_AUTOLOAD": "1"}
    out = subprocess.run(harness_cmd() + args, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert out.returncode == 0, out.stderr
    if args == ["plugins"]:
        data = json.loads(out.stdout)
        assert any(p["name"] == "harness.commands.core" for p in data["plugins"])
    if args == ["list"]:
        assert "detectors:" in out.stdout and "datasets:" in out.stdout and "encodings:" in out.stdout
