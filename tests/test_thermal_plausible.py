"""One plausibility check for every thermal input (``harness.sensing.plausible``): Kelvin, Fahrenheit, 8-bit counts,
byte-swapped floats and random bytes are told apart from degrees C, and every entry point (decoded files, DJI
R-JPEGs, converters, a dataset plugin's samples, a screen's captures) refuses them with the fix, or counts the few
values outside the plausible range on the console."""

from __future__ import annotations

import json
import logging
import sys

import numpy as np
import pytest

from conftest import SHARED
from harness.api import AlignedSample
from harness.contracts import validate_sample
from harness.errors import DataError, SampleError
from harness.sensing import plausible
from harness.sensing.pipeline import read_capture_thermal
from harness.sensing.radiometry import read_thermal, sidecar_path
from test_sensing_dji_converter import builtin_table_file

REAL = SHARED / "data" / "dji-m3t-rjpeg" / "m3t_a.jpg"

CONVERTER = """
import os, sys
import numpy as np
out, w, h = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
t = (20.0 + (np.arange(w * h) % 97) / 10.0).astype("<f4")
mode = os.environ.get("CONVERTER_MODE", "")
if mode == "random":
    np.random.default_rng(0).integers(0, 256, 4 * w * h, dtype=np.uint8).tofile(out)
elif mode == "bigendian":
    t.astype(">f4").tofile(out)
elif mode == "counts8":
    (np.arange(w * h) % 200).astype("<f4").tofile(out)
else:
    t[::50] = 5000.0
    t.tofile(out)
"""


def facade(seed: int = 0, shape=(48, 64)) -> np.ndarray:
    """A facade-like map in degrees C: a 12..22 C gradient, a warm window, a little noise."""
    rng = np.random.default_rng(seed)
    h, w = shape
    t = 12.0 + 10.0 * np.linspace(0, 1, w)[None, :] + np.zeros((h, 1))
    t[10:20, 10:30] += 8.0
    return (t + rng.normal(0, 0.3, shape)).astype(np.float32)


def random_bytes(shape=(48, 64)) -> np.ndarray:
    return np.random.default_rng(1).integers(0, 256, 4 * shape[0] * shape[1], dtype=np.uint8).view("<f4").reshape(shape)


def big_endian(t: np.ndarray) -> np.ndarray:
    return np.frombuffer(t.astype(">f4").tobytes(), "<f4").reshape(t.shape).copy()


def counts8(shape=(48, 64)) -> np.ndarray:
    return (np.arange(shape[0] * shape[1]).reshape(shape) % 220).astype(np.float32)


MAPS = {
    "plausible": lambda: facade(),
    "kelvin": lambda: facade() + np.float32(273.15),
    "fahrenheit": lambda: facade() * np.float32(1.8) + np.float32(32.0),
    "counts8": counts8,
    "garbage": random_bytes,
    "byteswapped": lambda: big_endian(facade()),
}


@pytest.mark.parametrize("kind", list(MAPS))
def test_classify_tells_each_reading_apart(kind):
    assert plausible.classify(MAPS[kind]()).kind == kind


def test_garbage_only_looks_past_units_and_a_few_outside_values_stay_plausible():
    assert plausible.classify(MAPS["kelvin"](), units=False).kind == "plausible"
    t = facade()
    t.ravel()[::40] = 5000.0  # 2.5 %: a few dead pixels
    seen = plausible.classify(t)
    assert seen.kind == "plausible" and seen.outside == t.size // 40 + (t.size % 40 > 0)
    t.ravel()[::10] = 5000.0  # 10 %: no temperature map
    assert plausible.classify(t).kind == "garbage"


def test_a_real_dji_frame_is_plausible_and_passes_every_reading():
    if not REAL.is_file():
        pytest.skip(f"{REAL} not present")
    t, info = read_thermal(REAL)
    seen = plausible.classify(t)
    assert seen.kind == "plausible" and seen.outside == 0 and "implausible" not in info
    assert -30 < seen.median < 60


def test_check_refuses_with_the_fix_and_counts_the_few_outside_on_the_console(caplog):
    with pytest.raises(DataError, match=r"f\.npy: the test: values .* look like Kelvin: subtract 273\.15"):
        plausible.check(MAPS["kelvin"](), "f.npy", "the test")
    with pytest.raises(DataError, match=r"look like degrees Fahrenheit.*C = \(F - 32\) / 1\.8"):
        plausible.check(MAPS["fahrenheit"](), "f.npy", "the test")
    with pytest.raises(DataError, match=r"whole numbers within 0\.\.255 .*8-bit counts"):
        plausible.check(counts8(), "f.npy", "the test")
    with pytest.raises(DataError, match=r"f\.npy: the test gives \d+ of \d+ values outside the plausible"):
        plausible.check(random_bytes(), "f.npy", "the test")
    with pytest.raises(DataError, match=r"byte-swapped 1\d\.\d\.\.\d\d\.\d C: big-endian floats"):
        plausible.check(big_endian(facade()), "f.npy", "the test")
    t = facade()
    t[0, :5] = 2000.0
    with caplog.at_level(logging.WARNING, logger="harness.sensing.plausible"):
        assert plausible.check(t, "f.npy", "the test") == 5
    assert np.isnan(t[0, :5]).all() and np.isfinite(t[1:]).all()
    assert "f.npy: 5 of 3072 values from the test lie outside the plausible -100..800 C" in caplog.text


def test_a_file_read_as_c_refuses_unit_mix_ups_and_a_sidecar_declares_the_unit(tmp_path, caplog):
    for kind in ("kelvin", "fahrenheit", "counts8"):
        np.save(tmp_path / f"{kind}.npy", MAPS[kind]())
        with pytest.raises(DataError, match=rf"{kind}\.npy: read as celsius \(float32, no sidecar; write {kind}\.npy"):
            read_thermal(tmp_path / f"{kind}.npy")
        with pytest.raises(DataError, match=rf"{kind}\.npy"):  # the screen's input: the same check
            read_capture_thermal(tmp_path / f"{kind}.npy")
    sidecar_path(tmp_path / "fahrenheit.npy").write_text(json.dumps({"unit": "fahrenheit"}))
    t, info = read_thermal(tmp_path / "fahrenheit.npy")
    np.testing.assert_allclose(t, facade(), atol=1e-4)
    sidecar_path(tmp_path / "kelvin.npy").write_text(json.dumps({"unit": "celsius"}))  # stated: kept, with a warning
    with caplog.at_level(logging.WARNING, logger="harness.sensing.plausible"):
        t, _ = read_thermal(tmp_path / "kelvin.npy")
    assert float(np.median(t)) > 273 and "look like Kelvin" in caplog.text and "unit was stated" in caplog.text


@pytest.fixture
def converter(tmp_path):
    script = tmp_path / "conv.py"
    script.write_text(CONVERTER)
    return f"{sys.executable} {script} {{input}} {{output}} {{width}} {{height}}"


@pytest.mark.parametrize(
    "mode, said",
    [
        ("random", r"values outside the plausible -100\.\.800 C .*not temperatures in C"),
        ("bigendian", r"byte-swapped 20\.0\.\.29\.\d C: big-endian floats read as little-endian"),
        ("counts8", r"whole numbers within 0\.\.255 \(0\.\.199\): 8-bit counts"),
    ],
)
def test_a_converter_writing_no_temperatures_fails_the_file_with_what_it_wrote(
    tmp_path, cli_runner, converter, monkeypatch, mode, said
):
    import re

    src = builtin_table_file(tmp_path / "m2ea.jpg")
    monkeypatch.setenv("CONVERTER_MODE", mode)
    res = cli_runner(["sensing", "decode", str(src), "--out", str(tmp_path / "out"), "--converter", converter])
    assert res.exit_code == 1, res.output
    text = " ".join(res.output.split())
    assert "m2ea.jpg" in text and re.search(said, text), text
    assert not list((tmp_path / "out").glob("m2ea.png*"))


def test_a_converter_value_outside_the_range_is_counted_on_the_console(tmp_path, cli_runner, converter, caplog):
    src = builtin_table_file(tmp_path / "m2ea.jpg")
    with caplog.at_level(logging.WARNING, logger="harness.sensing.plausible"):
        res = cli_runner(["sensing", "decode", str(src), "--out", str(tmp_path / "out"), "--converter", converter])
    assert res.exit_code == 0, res.output
    assert "m2ea.jpg: 7 of 320 values from the converter (command) lie outside the plausible -100..800 C" in (
        caplog.text
    )


def _sample(thermal: np.ndarray, meta: dict | None = None) -> AlignedSample:
    h, w = thermal.shape
    return AlignedSample(
        image_id=1,
        group="a",
        rgb=np.zeros((h, w, 3), np.uint8),
        thermal=thermal,
        ir8=np.zeros((h, w), np.uint8),
        boxes=np.zeros((0, 4), np.float32),
        labels=np.zeros((0,), np.int64),
        meta=meta or {},
    )


@pytest.mark.parametrize("kind, said", [("counts8", "8-bit counts"), ("byteswapped", "big-endian floats")])
def test_a_dataset_plugins_sample_with_no_temperatures_breaks_the_contract(kind, said):
    with pytest.raises(SampleError, match=rf"field 'thermal': .*{said}"):
        validate_sample(_sample(MAPS[kind]()))


def test_a_plugins_fahrenheit_breaks_the_contract_unless_its_meta_states_celsius():
    validate_sample(_sample(facade()))
    with pytest.raises(SampleError, match=r"degrees Fahrenheit.*meta\['thermal_unit'\] = 'celsius'"):
        validate_sample(_sample(MAPS["fahrenheit"]()))
    validate_sample(_sample(MAPS["fahrenheit"](), {"thermal_unit": "celsius"}))
