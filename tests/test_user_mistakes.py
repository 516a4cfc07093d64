"""Mistakes a user makes at the command line, each answered with what to do: an option given is not asked for
again, and a number is printed with its unit."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from harness.errors import ConfigError


def _wide_camera(path):
    from harness.sensing.calibration import CameraModel

    k = [[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]]
    return CameraModel(np.array(k), np.zeros(5), (64, 48), name="wide").save(path)


@pytest.mark.parametrize("given", ["rgb", "thermal", None])
def test_a_calibration_unknown_without_the_prepared_data_is_asked_for_by_its_own_option(given, tmp_path, monkeypatch):
    """The run's prepared data is not in the cache: the calibration still missing is asked for, never the one given."""
    from harness.screen.job import ScreenRequest, resolve_cameras

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    cam = str(_wide_camera(tmp_path / "camera.yaml"))
    req = ScreenRequest(
        flight=tmp_path,
        out=tmp_path / "out",
        run=tmp_path / "run",
        rgb_camera=cam if given == "rgb" else None,
        thermal_camera=cam if given == "thermal" else None,
    )
    model = SimpleNamespace(sensing={}, config={"meta": {"prepared_fingerprint": "f" * 16, "dataset": "m3t"}})
    with pytest.raises(ConfigError) as exc:
        resolve_cameras(req, model)  # type: ignore[arg-type]
    text = str(exc.value)
    assert "not in the cache" in text
    wanted = "--thermal-camera FILE" if given == "rgb" else "--rgb-camera FILE"
    assert wanted in text and f"--{given}-camera FILE" not in text
    if given is not None:  # the one given still counts: --no-undistort only for the other
        assert "--no-undistort if its dataset had no" in text
