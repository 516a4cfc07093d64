"""The mutation suite of the thermal boundaries: every misreading of a known-good thermal input is refused, never
decoded or prepared silently.

Two boundaries, each run as a user runs it: (a) thermal files of a ``coco-rgbt`` folder (float ``.npy`` maps in
degrees C, no sidecar) through ``harness prepare``; (b) a user's converter for R-JPEGs (``harness sensing decode
--converter``), which writes raw float32 values. Each operator of ``OPERATORS`` changes the known-good temperatures
the way a producer of thermal data gets it wrong (Kelvin, Fahrenheit, 8-bit counts, big-endian floats, random bytes,
the wrong shape, ...); for every (boundary, operator) the command must fail with a message naming the file and what
was seen. The known-good input must pass. A new kind of mistake goes in as one more operator.
"""

from __future__ import annotations

import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from coco_rgbt_helpers import make_coco_rgbt, read_json, temperature, write_json
from test_sensing_dji_converter import builtin_table_file


@dataclass(frozen=True)
class Operator:
    """One mistake: ``temps`` turns a known-good map in degrees C into what the producer wrote (any dtype and
    shape: the file boundary saves it as ``.npy``, the converter writes its bytes); ``says``: what the refusal must
    say."""

    name: str
    temps: Callable[[np.ndarray], np.ndarray]
    says: str
    #: the boundaries where the operator is a mistake (a float64 .npy of degrees C is a good file)
    boundaries: tuple[str, ...] = ("file", "converter")
    #: what the converter's refusal must say, where it differs from ``says``
    converter_says: str = ""
    #: why the mistake cannot be told at the converter yet (an expected failure, listed in the suite's result)
    unseen: str = ""


def _big_endian(t: np.ndarray) -> np.ndarray:
    return np.frombuffer(t.astype(">f4").tobytes(), "<f4").reshape(t.shape)


def _random(t: np.ndarray) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, 4 * t.size, dtype=np.uint8).view("<f4").reshape(t.shape)


def _counts8(t: np.ndarray) -> np.ndarray:
    return np.rint((t - t.min()) / (t.max() - t.min()) * 255).astype(np.float32)


OPERATORS = (
    Operator("Kelvin", lambda t: t + 273.15, "Kelvin"),
    Operator("Fahrenheit", lambda t: t * 1.8 + 32, "Fahrenheit"),
    Operator("8-bit counts", _counts8, "8-bit counts"),
    Operator("centi-Kelvin as floats", lambda t: (t + 273.15) * 100, "outside the plausible"),
    Operator("big-endian floats", _big_endian, "big-endian"),
    Operator("random bytes", _random, "outside the plausible"),
    Operator("NaN only", lambda t: t * np.nan, "NaN"),
    Operator("float64", lambda t: t.astype(np.float64), "bytes, expected", boundaries=("converter",)),
    Operator("transposed", lambda t: t.T.copy(), "size mismatch", boundaries=("file",)),
    Operator("one row short", lambda t: t[:-1], "size mismatch", converter_says="bytes, expected"),
)

# ------------------------------------------------------------------------------------ (a) thermal files (prepare)


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A ``coco-rgbt`` folder whose thermal files are float32 ``.npy`` maps in degrees C."""
    root = make_coco_rgbt(tmp_path_factory.mktemp("thermal-mutations") / "d")
    coco = read_json(root)
    for k, im in enumerate(coco["images"]):
        (root / im["thermal_file_name"]).unlink()
        im["thermal_file_name"] = f"thermal/{k:03d}.npy"
        np.save(root / im["thermal_file_name"], temperature(k))
    write_json(root, coco)
    return root


def prepare_outcome(cli_runner: Any, folder: Path, tmp: Path, op: Operator | None) -> tuple[int, str]:
    root = Path(shutil.copytree(folder, tmp / "d"))
    if op is not None:
        for k, im in enumerate(read_json(root)["images"]):
            np.save(root / im["thermal_file_name"], op.temps(temperature(k)))
    res = cli_runner(["prepare", "--dataset", "coco-rgbt", "--root", str(root), "--cache", str(tmp / "cache")])
    return res.exit_code, res.output


def test_known_good_thermal_files_prepare(cli_runner, folder, tmp_path):
    code, out = prepare_outcome(cli_runner, folder, tmp_path, None)
    assert code == 0 and "12 aligned samples" in out, out


# ------------------------------------------------------------------------------------ (b) converter outputs (decode)
#: A converter writing the operator's values (``MUTATION`` names it) as raw bytes of the frame's size.
CONVERTER = """
import sys
import numpy as np
sys.path[:0] = [{tests!r}]
import test_mutations_thermal as m
out, w, h, name = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
t = (20.0 + (np.arange(w * h) % 97) / 10.0).reshape(h, w).astype("<f4")
op = next((o for o in m.OPERATORS if o.name == name), None)
np.ascontiguousarray(op.temps(t) if op is not None else t).tofile(out)
"""


@pytest.fixture(scope="module")
def converter(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the converter script, an R-JPEG whose built-in table only a converter can apply)."""
    tmp = tmp_path_factory.mktemp("converter-mutations")
    script = tmp / "conv.py"
    script.write_text(CONVERTER.format(tests=str(Path(__file__).parent)))
    return script, builtin_table_file(tmp / "m2ea.jpg")


def decode_outcome(cli_runner: Any, converter: tuple[Path, Path], tmp: Path, op: Operator | None) -> tuple[int, str]:
    script, src = converter
    name = op.name if op is not None else "none"
    template = f"{sys.executable} {script} {{input}} {{output}} {{width}} {{height}} '{name}'"
    res = cli_runner(["sensing", "decode", str(src), "--out", str(tmp / "out"), "--converter", template])
    return res.exit_code, res.output


def test_a_known_good_converter_decodes(cli_runner, converter, tmp_path):
    code, out = decode_outcome(cli_runner, converter, tmp_path, None)
    assert code == 0 and "decoded 1 of 1" in out, out


# ------------------------------------------------------------------------------------ every mutant, both boundaries
BOUNDARIES = ("file", "converter")
CASES = [
    pytest.param(
        b,
        op,
        id=f"{b}:{op.name}",
        marks=pytest.mark.xfail(strict=True, reason=op.unseen) if op.unseen and b == "converter" else (),
    )
    for op in OPERATORS
    for b in BOUNDARIES
    if b in op.boundaries
]


@pytest.mark.parametrize(("boundary", "op"), CASES)
def test_every_mutant_is_refused(boundary, op, cli_runner, folder, converter, tmp_path):
    if boundary == "file":
        code, out = prepare_outcome(cli_runner, folder, tmp_path, op)
        refused, named = code == 2, "000.npy"
    else:
        code, out = decode_outcome(cli_runner, converter, tmp_path, op)
        refused, named = code == 1 and "decoded 0 of 1" in out, "m2ea.jpg"
    print(f"{boundary:9} {op.name:25} {'refused' if refused else 'SILENT':8} exit {code}")
    text = " ".join(out.split())
    assert refused, f"{boundary}: {op.name} passed silently (exit {code}):\n{out}"
    says = op.converter_says if boundary == "converter" and op.converter_says else op.says
    assert named in text and says in text, out
    assert "Traceback" not in out
