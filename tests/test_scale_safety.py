"""Safe loading: checkpoints that would run code are refused (and the code does not run), YAML goes through a safe
loader, dataset and config files cannot name paths outside their root, and no Python file of the repository starts
a shell or unpickles untrusted data."""

from __future__ import annotations

import ast
import pathlib
import subprocess
from pathlib import Path

import pytest
import torch
import yaml

from harness.engine import checkpoint as ckpt
from harness.errors import ConfigError, DataError, HarnessError

REPO = Path(__file__).resolve().parent.parent


class _Payload:
    """Unpickling this calls ``Path.write_text(marker, ...)``: a stand-in for any code an attacker would run."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.write_text, (pathlib.Path(self.marker), "code ran")


def _evil_checkpoint(path: Path, marker: Path) -> Path:
    weights = {"w": torch.zeros(2)}
    torch.save(
        {"format": ckpt.FORMAT, "version": ckpt.VERSION, "epoch": 0, "model": weights, "optimizer": _Payload(marker)},
        path,
    )
    return path


def test_the_payload_is_real_when_unpickled_unsafely(tmp_path):
    """Control: an unsafe load of the same file does run the code (so the refusals below mean something)."""
    marker = tmp_path / "marker"
    torch.load(_evil_checkpoint(tmp_path / "evil.pt", marker), weights_only=False)  # safety-scan: allow (control)
    assert marker.read_text() == "code ran"


def test_a_checkpoint_that_would_run_code_is_refused_and_the_code_does_not_run(tmp_path):
    marker = tmp_path / "marker"
    evil = _evil_checkpoint(tmp_path / "evil.pt", marker)
    with pytest.raises(ckpt.CheckpointError, match=r"evil.pt: cannot be read as a weights-only checkpoint"):
        ckpt.load(evil)
    model = torch.nn.Linear(2, 2)
    with pytest.raises(ckpt.CheckpointError, match="weights-only"):
        ckpt.init_from(model, evil)  # harness run --init
    weights = pytest.importorskip("adapters.detectors.yolo.weights")
    with pytest.raises(HarnessError, match="refused for safety"):
        weights.read_state_dict(evil)  # official detector weights
    assert not marker.exists()


def test_resuming_from_a_tampered_last_checkpoint_is_refused(tmp_path):
    from engine_helpers import one_conv_trainer

    marker = tmp_path / "marker"
    (tmp_path / "ckpt").mkdir()
    _evil_checkpoint(tmp_path / "ckpt" / "last.pt", marker)
    trainer = one_conv_trainer(tmp_path)
    with pytest.raises(ckpt.CheckpointError, match="last.pt: cannot be read as a weights-only checkpoint"):
        trainer.fit(resume=True)
    assert not marker.exists()


@pytest.mark.parametrize(
    "text",
    [
        "train: !!python/object/apply:pathlib.Path.write_text [marker, pwned]\n",
        "train: !!python/object:harness.sweep.SweepSpec {detectors: [x]}\n",
        "train: !!python/name:os.getcwd\n",
    ],
)
def test_yaml_with_python_tags_is_refused_everywhere(tmp_path, text):
    from harness.config import read_yaml

    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match="bad.yaml: invalid YAML.*could not determine a constructor"):
        read_yaml(bad)
    from harness.config import _Loader

    assert issubclass(_Loader, yaml.SafeLoader)  # the one YAML reader of the harness is a safe loader
    # a dataset manifest goes through the same reader
    pytest.importorskip("adapters.datasets.m3t")
    from adapters.datasets.m3t import load_manifest

    (tmp_path / "m3t.yaml").write_text(text.replace("train:", "images:"))
    with pytest.raises((ConfigError, DataError), match="invalid YAML"):
        load_manifest(tmp_path)
    assert not (tmp_path / "marker").exists()


@pytest.mark.parametrize(
    "kw",
    [
        dict(profile="../../etc/passwd"),
        dict(profile="/etc/passwd"),
        dict(protocol="../profiles/smoke"),
        dict(profile="smoke", detector="../x"),
    ],
)
def test_config_names_cannot_reach_outside_the_config_folder(kw):
    from harness.config import load_config

    with pytest.raises(ConfigError, match="expected a plain name"):
        load_config(**kw)


def test_rgbt_tiny_annotation_paths_cannot_leave_the_images_folder(tmp_path):
    pytest.importorskip("adapters.datasets.rgbt_tiny")
    from adapters.datasets import rgbt_tiny
    from datasets_helpers import edited_json
    from eightbit_fixtures import rgbt_json, write_rgbt_tiny

    root = tmp_path / "RGBT-Tiny"
    write_rgbt_tiny(root, train_seqs=("DJI_0001_1",), test_seqs=("DJI_0101_1",), frames=2)
    path = rgbt_json(root, "01", "train")
    with edited_json(path) as doc:
        doc["images"][0]["file_name"] = "DJI_0001_1/../../../../secret/01/00000.jpg"
    with pytest.raises(DataError, match=r"instances_01_train2017.json: images\[0\]: file_name: .*leads outside"):
        rgbt_tiny.open_rgbt_tiny(root)
    with pytest.raises(ValueError, match="leads outside"):
        rgbt_tiny.parse_file_name("C:/DJI_0001_1/01/00000.jpg")
    assert rgbt_tiny.parse_file_name("images/DJI_0001_1/01/00000.jpg")[0] == "DJI_0001_1/01/00000.jpg"


def test_m3t_manifest_and_annotation_paths_cannot_leave_the_dataset_root(tmp_path):
    pytest.importorskip("adapters.datasets.m3t")
    from adapters.datasets.m3t import load_manifest, safe_join

    (tmp_path / "m3t.yaml").write_text("annotations: ../outside.json\n")
    with pytest.raises(DataError, match="leads outside the dataset root"):
        load_manifest(tmp_path).annotations_path
    with pytest.raises(DataError, match="leads outside the dataset root"):
        safe_join(tmp_path, "P1/../../x.jpg", "image file_name")


# ------------------------------------------------------------------------------------------------- the scan
def _python_files() -> list[Path]:
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "*.py"],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    if listed.returncode == 0 and listed.stdout.strip():
        files = [REPO / line for line in listed.stdout.splitlines()]
    else:  # not a git checkout (an sdist): every .py outside virtual environments and caches
        skip = {".venv", "venv", ".git", "build", "dist", "cache", "results", "__pycache__", ".tox"}
        files = [p for p in REPO.rglob("*.py") if not skip & set(p.relative_to(REPO).parts)]
    return [f for f in files if f.exists()]


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return ""


def _kw(call: ast.Call, name: str) -> ast.AST | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


def _is_true(node: ast.AST | None) -> bool:
    return isinstance(node, ast.Constant) and node.value is True


UNSAFE_CALLS = {
    "os.system": "starts a shell",
    "os.popen": "starts a shell",
    "subprocess.getoutput": "starts a shell",
    "subprocess.getstatusoutput": "starts a shell",
    "pickle.load": "unpickles arbitrary objects",
    "pickle.loads": "unpickles arbitrary objects",
    "yaml.unsafe_load": "constructs arbitrary Python objects",
    "yaml.full_load": "constructs Python objects",
    "eval": "evaluates code",
    "exec": "executes code",
}


ALLOW = "# safety-scan: allow"


def unsafe_calls(source: str, filename: str = "<string>") -> list[str]:
    """The unsafe calls in ``source``: shells, unpickling, unsafe YAML, ``torch.load`` without ``weights_only=True``.

    A line that ends with ``# safety-scan: allow (reason)`` is a deliberate exception (this file's control test)."""
    found = []
    lines = source.splitlines()
    for node in ast.walk(ast.parse(source, filename)):
        if not isinstance(node, ast.Call) or ALLOW in lines[node.lineno - 1]:
            continue
        name = _dotted(node.func)
        why = UNSAFE_CALLS.get(name)
        if _is_true(_kw(node, "shell")):
            why = "shell=True"
        elif name.endswith("torch.load") and not _is_true(_kw(node, "weights_only")):
            why = "torch.load without weights_only=True"
        elif name.endswith(("np.load", "numpy.load")) and _is_true(_kw(node, "allow_pickle")):
            why = "np.load with allow_pickle=True"
        elif name == "yaml.load":
            loader = _dotted(_kw(node, "Loader") or ast.Constant(None))
            if not loader or loader.split(".")[-1] in ("Loader", "FullLoader", "UnsafeLoader"):
                why = "yaml.load without a safe Loader"
        if why:
            found.append(f"{filename}:{node.lineno}: {name or 'call'}(...): {why}")
    return found


def test_the_scan_finds_what_it_looks_for():
    bad = (
        "import os, subprocess, pickle, torch, yaml, numpy as np\nos.system('x')\n"
        "subprocess.run('x', shell=True)\npickle.loads(b'')\ntorch.load('a')\n"
        "torch.load('a', weights_only=False)\nnp.load('a', allow_pickle=True)\nyaml.load('a')\n"
        "yaml.load('a', Loader=yaml.FullLoader)\n"
    )
    assert len(unsafe_calls(bad)) == 8
    good = (
        "import subprocess, torch, yaml\nsubprocess.run(['ls'])\ntorch.load('a', weights_only=True)\n"
        "yaml.load('a', Loader=yaml.SafeLoader)\ns = 'os.system(1) shell=True'\nmodel.eval()\n"
        "torch.load('a')  " + ALLOW + " (a test)\n"
    )
    assert unsafe_calls(good) == []


def test_no_python_file_of_the_repository_starts_a_shell_or_loads_unsafely():
    files = _python_files()
    assert len(files) > 50 and REPO / "harness" / "runner.py" in files
    problems = [p for f in files for p in unsafe_calls(f.read_text(encoding="utf-8"), str(f.relative_to(REPO)))]
    assert problems == [], "\n".join(problems)
