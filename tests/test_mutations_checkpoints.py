"""The mutation suite of the checkpoint boundaries: every wrong checkpoint is refused with one line naming the file, or
loaded in part with a warning saying so, never loaded silently.

Two boundaries: (a) ``--init`` (``harness.engine.checkpoint.init_from`` with the detector's importer, what ``harness
run --init`` and ``pretrain --init`` call) for the ``ours`` detector, whose known-good file is a checkpoint of the
same model; (b) ``harness weights import``, whose known-good file is an Ultralytics-style checkpoint (the stand-in of
``weights_standins``). Each operator of ``OPERATORS`` makes one mistake a user makes with weight files (another
detector's checkpoint, a truncated download, an empty file, a checkpoint for another number of classes, ...).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import pytest
import torch

from weights_standins import save_ultralytics

pytestmark = pytest.mark.usefixtures("one_torch_thread")

NAMES = {0: "window", 1: "warm", 2: "cold"}


def _ours(nc: int = 3, in_channels: int = 4, scale: str = "n", seed: int = 1) -> torch.nn.Module:
    from adapters.detectors import ours

    torch.manual_seed(seed)
    return ours.build(nc, in_channels=in_channels, scale=scale).eval()


@dataclass(frozen=True)
class Operator:
    """One mistake: ``make(good, path)`` writes the mutant at ``path`` from the known-good file ``good``; ``says``:
    what the refusal must say, or with ``partial`` what the log of a partial ``--init`` (or the note of an import)
    says; ``boundaries``: where it applies."""

    name: str
    make: Callable[[Path, Path], Path]
    says: str
    partial: bool = False
    boundaries: tuple[str, ...] = ("init", "import")


def _truncated(good: Path, path: Path) -> Path:
    path.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    return path


def _empty(good: Path, path: Path) -> Path:
    path.write_bytes(b"")
    return path


def _random(good: Path, path: Path) -> Path:
    g = torch.Generator().manual_seed(0)
    path.write_bytes(torch.randint(0, 256, (4096,), generator=g, dtype=torch.uint8).numpy().tobytes())
    return path


def _foreign(good: Path, path: Path) -> Path:
    g = torch.Generator().manual_seed(0)
    torch.save({"fc.weight": torch.randn(10, 512, generator=g), "fc.bias": torch.zeros(10)}, path)
    return path


def _no_tensors(good: Path, path: Path) -> Path:
    torch.save({"epoch": 3, "best_fitness": 0.5}, path)
    return path


def _state(model: torch.nn.Module, path: Path) -> Path:
    torch.save({"model": model.state_dict()}, path)
    return path


def _safetensors(good: Path, path: Path) -> Path:
    from safetensors.torch import save_file

    path = path.with_suffix(".pt")
    save_file({"fc.weight": torch.zeros(2, 2)}, str(path))  # a safetensors file named .pt
    return path


def _eme(good: Path, path: Path) -> Path:
    from adapters.detectors import eme

    torch.manual_seed(0)
    return _state(eme.build(3, in_channels=4), path)


OPERATORS = (
    Operator("truncated download", _truncated, "truncated"),
    Operator("empty file", _empty, "empty file"),
    Operator("random bytes", _random, "not a PyTorch checkpoint"),
    Operator("safetensors named .pt", _safetensors, "safetensors"),
    Operator("a foreign state dict", _foreign, "the checkpoint lacks", boundaries=("init",)),
    Operator("a checkpoint without tensors", _no_tensors, "no tensors", boundaries=("init",)),
    Operator("a checkpoint without a model", _no_tensors, "no model found", boundaries=("import",)),
    Operator("another detector's checkpoint (EME)", _eme, "do not fit the model", boundaries=("init",)),
    Operator("another model size", lambda g, p: _state(_ours(scale="s"), p), "scale 's'", boundaries=("init",)),
    Operator(
        "another number of classes",
        lambda g, p: _state(_ours(nc=5), p),
        "re-initialised",
        partial=True,
        boundaries=("init",),
    ),
    Operator("a foreign state dict", _foreign, "not a YOLO-family module tree", partial=True, boundaries=("import",)),
)


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The known-good file of each boundary."""
    tmp = tmp_path_factory.mktemp("checkpoint-mutations")
    return {
        "init": _state(_ours(seed=2), tmp / "ours.pt"),
        "import": save_ultralytics(_ours(in_channels=3), tmp / "best.pt", NAMES),
    }


def init_outcome(path: Path, caplog: Any) -> tuple[str, str, dict | None]:
    """(``refused``/``partial``/``loaded``, the message or warnings, the report) of ``--init path`` on ``ours``."""
    from harness.engine.checkpoint import init_from
    from harness.errors import HarnessError
    from harness.plugins import get_host, load_plugins

    load_plugins()
    det = get_host().detector("ours")
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="harness"):
        try:
            report = init_from(_ours(), path, det.load_official)
        except HarnessError as exc:
            return "refused", str(exc), None
    said = " ".join(r.getMessage() for r in caplog.records)
    changed = any(report.get(k) for k in ("missing", "mismatched", "shape_mismatch", "reinitialised"))
    return ("partial" if changed and said else "loaded"), said, report


def import_outcome(cli_runner: Any, path: Path, tmp: Path) -> tuple[str, str]:
    """(``refused``/``partial`` (imported with a note)/``loaded``, the output) of ``harness weights import path``."""
    res = cli_runner(["weights", "import", str(path), "--out", str(tmp / "w.safetensors")])
    if res.exit_code == 0:
        return ("partial" if "note:" in res.output else "loaded"), res.output
    return ("refused" if res.exit_code == 2 else f"exit {res.exit_code}"), res.output


def test_the_known_good_files_load_whole(files, cli_runner, tmp_path, caplog):
    verdict, said, report = init_outcome(files["init"], caplog)
    assert verdict == "loaded" and report is not None and report["loaded"] == len(_ours().state_dict()), said
    verdict, out = import_outcome(cli_runner, files["import"], tmp_path)
    assert verdict == "loaded" and "nc 3" in out, out


CASES = [(b, op) for op in OPERATORS for b in ("init", "import") if b in op.boundaries]


@pytest.mark.parametrize(("boundary", "op"), CASES, ids=[f"{b}:{op.name}" for b, op in CASES])
def test_every_mutant_is_refused_or_loaded_in_part_with_a_warning(boundary, op, files, cli_runner, tmp_path, caplog):
    path = op.make(files[boundary], tmp_path / ("mutant.pt"))
    if boundary == "init":
        verdict, said, _ = init_outcome(path, caplog)
    else:
        verdict, said = import_outcome(cli_runner, path, tmp_path)
    print(f"{boundary:6} {op.name:40} {verdict}")
    expected = "partial" if op.partial else "refused"
    assert verdict == expected, f"{boundary}: {op.name}: {verdict}:\n{said}"
    text = " ".join(said.split())
    assert (path.name in text or (op.partial and boundary == "import")) and op.says in text, said
    assert "Traceback" not in said and (op.partial or len(said.strip().splitlines()) <= 3), said
