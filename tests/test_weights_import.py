"""``harness weights import``: checkpoints of other codebases read without running their code, and loaded exactly."""

from __future__ import annotations

import json
import os
import pickle
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from harness.engine import checkpoint as ckpt
from harness.weights import import_checkpoint, read_checkpoint_weights
from harness.weights.unpickle import CheckpointFormatError, UnsafeCheckpointError, load_checkpoint
from weights_standins import reference_float32, save_ultralytics, save_yolov5_style

pytestmark = pytest.mark.usefixtures("one_torch_thread")

NAMES = {0: "window", 1: "crack", 2: "vent"}


def _ours(nc: int = 3, in_channels: int = 3, seed: int = 0):
    from adapters.detectors import ours

    torch.manual_seed(seed)
    return ours.build(nc, in_channels=in_channels, scale="n").eval()


def _tiny_icafusion(seed: int = 0):
    from adapters.detectors import icafusion

    torch.manual_seed(seed)
    return icafusion.build(3, width=0.125, depth=0.33, tokens=(4, 2, 2)).eval()


def _cli(args: list[str]):
    from harness.cli import get_cli

    return CliRunner().invoke(get_cli(), args, catch_exceptions=False)


# ------------------------------------------------------------------------------------------------ safety
class _RunsShell:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_a_pickle_that_would_run_a_shell_command_is_refused_and_nothing_runs(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pt"
    torch.save({"model": {"w": torch.zeros(2)}, "payload": _RunsShell(marker)}, path)
    with pytest.raises(UnsafeCheckpointError, match=r"posix\.system|nt\.system"):
        load_checkpoint(path)
    assert not marker.exists()
    res = _cli(["weights", "import", str(path), "--out", str(tmp_path / "w.safetensors")])
    assert res.exit_code == 2 and "refused" in res.output
    assert not marker.exists() and not (tmp_path / "w.safetensors").exists()
    # the same payload is real: an ordinary unpickler does run it
    pickle.loads(pickle.dumps(_RunsShell(marker)))  # safety-scan: allow (control)
    assert marker.exists()


def test_every_call_outside_the_rebuild_list_is_refused(tmp_path):
    class Eval:
        def __reduce__(self):
            return (eval, ("1 + 1",))

    class GetAttr:
        def __reduce__(self):
            return (getattr, ("text", "upper"))

    for payload in (Eval(), GetAttr()):
        path = tmp_path / "x.pt"
        torch.save({"p": payload}, path)
        with pytest.raises(UnsafeCheckpointError, match="refused"):
            load_checkpoint(path)


class _WouldWriteOnSetstate:
    marker: Path | None = None

    def __setstate__(self, state):  # a real class's __setstate__ is code; a placeholder never runs it
        Path(state["marker"]).write_text("ran")


def test_unknown_classes_become_inert_placeholders_that_record_their_state(tmp_path):
    obj = _WouldWriteOnSetstate.__new__(_WouldWriteOnSetstate)
    obj.marker = str(tmp_path / "ran")
    path = tmp_path / "c.pt"
    torch.save({"thing": obj, "t": torch.arange(3)}, path)
    loaded, stubs = load_checkpoint(path)
    assert not (tmp_path / "ran").exists()
    assert f"{__name__}._WouldWriteOnSetstate" in stubs
    assert loaded["thing"].state == {"marker": str(tmp_path / "ran")}
    assert torch.equal(loaded["t"], torch.arange(3))


def test_a_file_that_is_no_checkpoint_gets_a_clear_error(tmp_path):
    path = tmp_path / "notes.pt"
    path.write_bytes(b"hello, not a checkpoint")
    with pytest.raises(CheckpointFormatError, match="notes.pt"):
        load_checkpoint(path)


def test_the_legacy_serialization_format_reads_too(tmp_path):
    path = tmp_path / "legacy.pt"
    sd = {"a": torch.arange(6, dtype=torch.float32).reshape(2, 3), "b": torch.tensor([1, 2], dtype=torch.int64)}
    torch.save({"model": sd}, path, _use_new_zipfile_serialization=False)
    obj, _ = load_checkpoint(path)
    assert torch.equal(obj["model"]["a"], sd["a"]) and torch.equal(obj["model"]["b"], sd["b"])


# ------------------------------------------------------------------------------------------------ Ultralytics
@pytest.mark.parametrize("style", ["trainer", "final"])
def test_a_standin_ultralytics_checkpoint_converts_and_loads_through_init_with_identical_outputs(tmp_path, style):
    src_model = _ours(nc=3, in_channels=3)
    src = save_ultralytics(src_model, tmp_path / "best.pt", NAMES, style=style)
    assert "ultralytics" not in sys.modules
    out = tmp_path / "yolov8n.safetensors"
    res = import_checkpoint(src, out)
    lay = res.info["layout"]
    assert (lay["family"], lay["scale"], lay["nc"], lay["in_channels"], lay["two_stream"]) == (
        "yolov8",
        "n",
        3,
        3,
        False,
    )
    assert lay["names"] == ["window", "crack", "vent"] and lay["suggested_detector"] == "ours"
    assert res.info["weights_from"] == ("ema" if style == "trainer" else "model")
    assert res.info["source_dtypes"] == ["float16"]
    assert "ultralytics.nn.tasks.DetectionModel" in res.info["placeholders"]
    assert json.loads(res.sidecar.read_text())["layout"]["scale"] == "n"

    reference = _ours(nc=3, in_channels=3, seed=1)
    reference.load_state_dict(reference_float32(src_model))
    target = _ours(nc=3, in_channels=3, seed=2)
    from adapters.detectors import ours

    report = ckpt.init_from(target, out, ours.load_official)
    assert report["missing"] == [] and report["unexpected"] == []
    x = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        a, b = reference.forward_raw(x) if hasattr(reference, "forward_raw") else reference(x), None
        b = target.forward_raw(x) if hasattr(target, "forward_raw") else target(x)
    for u, v in zip(a if isinstance(a, (list, tuple)) else [a], b if isinstance(b, (list, tuple)) else [b]):
        assert torch.equal(u, v)


def test_the_import_feeds_model_weights_and_inflates_to_four_channels(tmp_path):
    from adapters.detectors import ours

    src_model = _ours(nc=3, in_channels=3)
    out = tmp_path / "w.safetensors"
    import_checkpoint(save_ultralytics(src_model, tmp_path / "last.pt", NAMES), out)
    model = ours.build(8, in_channels=4, scale="n", weights=str(out))
    rep = model.load_report
    assert rep["stem"]["checkpoint_channels"] == 3 and rep["stem"]["model_channels"] == 4
    stem = model.state_dict()["model.0.conv.weight"]
    assert torch.equal(stem[:, :3], reference_float32(src_model)["model.0.conv.weight"])
    assert torch.count_nonzero(stem[:, 3]) == 0


def test_the_cli_prints_what_it_found(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    save_ultralytics(_ours(nc=3, in_channels=3), tmp_path / "best.pt", NAMES)
    res = _cli(["weights", "import", "best.pt", "--out", "w.safetensors"])
    assert res.exit_code == 0, res.output
    assert "yolov8, scale n, nc 3, 3 input channel(s)" in res.output
    assert "--init" in res.output and all(len(line) <= 100 for line in res.output.splitlines())


# ------------------------------------------------------------------------------------------------ ICAFusion
def test_a_standin_icafusion_checkpoint_converts_and_loads_with_identical_outputs(tmp_path):
    from adapters.detectors import icafusion

    src_model = _tiny_icafusion()
    src = save_yolov5_style(src_model, tmp_path / "icafusion_best.pt")
    assert "models" not in sys.modules
    out = tmp_path / "icafusion.safetensors"
    res = import_checkpoint(src, out)
    lay = res.info["layout"]
    assert lay["family"] == "yolov5" and lay["two_stream"] and lay["nc"] == 3 and lay["in_channels"] == 3
    assert lay["head_index"] == 37 and lay["suggested_detector"] == "icafusion"
    assert res.info["checkpoint"]["epoch"] == 5

    reference = _tiny_icafusion(seed=1)
    reference.load_state_dict(reference_float32(src_model))
    target = _tiny_icafusion(seed=2)
    report = ckpt.init_from(target, out, icafusion.load_official)
    assert not report.get("missing") and not report.get("mismatched")
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(1, 3, 64, 64, generator=g), torch.rand(1, 3, 64, 64, generator=g))
    with torch.no_grad():
        for u, v in zip(reference.forward_raw(x), target.forward_raw(x)):
            assert torch.equal(u, v)


def test_yolov5_single_stream_layout_is_named(tmp_path):
    from adapters.detectors import eme

    torch.manual_seed(0)
    model = eme.build(3, width=0.25, depth=0.33)
    sd, info = read_checkpoint_weights(save_yolov5_style(model, tmp_path / "v5.pt"))
    lay = info["layout"]
    assert lay["family"] == "yolov5" and not lay["two_stream"] and lay["scale"] == "n" and lay["nc"] == 3
    assert set(sd) == set(model.state_dict()) - {
        k for k in model.state_dict() if k.endswith("num_batches_tracked")
    } or set(sd) == set(model.state_dict())


@pytest.mark.slow
def test_pretrain_starts_from_an_imported_checkpoint(tmp_path, host, monkeypatch):
    """`harness pretrain --init` (and so `harness run --init`) takes the import: stem inflated to 4 channels."""
    from engine_helpers import ShapesPlugin
    from harness.commands.pretrain import pretrain
    from harness.store import RunKey, Store
    from harness.testing import temporary_plugin
    from scale_helpers import TINY

    monkeypatch.setenv("HARNESS_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "w.safetensors"
    import_checkpoint(save_ultralytics(_ours(nc=3, in_channels=3), tmp_path / "best.pt", NAMES), out)
    with temporary_plugin(ShapesPlugin(), name="shapes-test"):
        res = pretrain(
            "ours",
            "shapes",
            fold="A",
            overrides=TINY + ["model.scale=n", "protocol.epochs=1"],
            store=tmp_path / "store",
            progress=False,
            init=out,
        )
    assert res.checkpoint.exists()
    init = Store(tmp_path / "store").run(RunKey("shapes", "ours", "test-ir8", "A", 0)).read_metrics()["train"]["init"]
    assert init["path"] == str(out) and init["loaded"] > 300 and init["stem"]["checkpoint_channels"] == 3


def test_the_import_written_one_tensor_at_a_time_reads_back_as_the_safetensors_library_writes_it(tmp_path):
    """The import streams its output (``write_safetensors``) instead of building it in memory; the file holds
    exactly what the safetensors library writes for the same float32 state dict."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save

    g = torch.Generator().manual_seed(0)
    odd = {
        "model": {
            "half": torch.randn(3, 4, generator=g).half(),
            "bf16": torch.randn(5, generator=g).bfloat16(),
            "f64": torch.randn(2, 2, generator=g).double(),
            "mask": torch.tensor([True, False, True]),
            "steps": torch.tensor(7),
            "empty": torch.zeros(0, 3),
            "codes": torch.arange(6, dtype=torch.int8),
            "strided": torch.arange(12.0).reshape(3, 4).t(),
        }
    }
    torch.save(odd, tmp_path / "odd.pt")
    for src in (save_ultralytics(_ours(), tmp_path / "best.pt", NAMES), tmp_path / "odd.pt"):
        res = import_checkpoint(src, tmp_path / "w.safetensors")
        sd, info = read_checkpoint_weights(src)
        meta = {
            "format": "rgbt-harness-import",
            "family": info["layout"]["family"],
            "source_sha256": info["source_sha256"],
        }
        (tmp_path / "lib.safetensors").write_bytes(save(sd, metadata=meta))
        ours, lib = load_file(str(res.weights)), load_file(str(tmp_path / "lib.safetensors"))
        assert ours.keys() == lib.keys() == sd.keys()
        for k in lib:
            assert ours[k].dtype == lib[k].dtype and ours[k].shape == lib[k].shape and torch.equal(ours[k], lib[k]), k
        with safe_open(str(res.weights), "pt") as f:
            assert f.metadata() == meta


def test_tensors_are_written_in_pieces_that_cover_them_in_row_major_order():
    from harness.weights import _pieces

    g = torch.Generator().manual_seed(0)
    tensors = [
        torch.randn(7, 5, 3, generator=g),
        torch.randn(6, 4, generator=g).t(),
        torch.randn(1).expand(9, 4),
        torch.randn(3, 1, 5, generator=g).expand(3, 4, 5),
        torch.arange(50.0),
        torch.tensor(3.0),
        torch.zeros(0, 4),
    ]
    for t in tensors:
        for limit in (1, 12, 40, 10_000):
            pieces = list(_pieces(t, limit))
            assert torch.equal(torch.cat([p.reshape(-1) for p in pieces]), t.reshape(-1)), (t.shape, limit)
            assert all(p.numel() * 4 <= limit or p.numel() == 1 for p in pieces), (t.shape, limit)


def test_a_legacy_whole_model_checkpoint_reads_like_its_zip_twin(tmp_path):
    """A pre-1.6 file of a whole model names each module class by a ('module', class, file, source) persistent id;
    it reads (the class as an inert placeholder, its source never used) and imports to the same tensors."""
    model = _ours(nc=3, in_channels=3)
    legacy, modern = tmp_path / "legacy.pt", tmp_path / "modern.pt"
    torch.save({"model": model}, legacy, _use_new_zipfile_serialization=False)
    torch.save({"model": model}, modern)
    obj, stubs = load_checkpoint(legacy)
    assert any(name.endswith("Conv2d") for name in stubs)
    a = import_checkpoint(legacy, tmp_path / "a.safetensors")
    b = import_checkpoint(modern, tmp_path / "b.safetensors")
    assert a.info["layout"] == b.info["layout"]
    from safetensors.torch import load_file

    wa, wb = load_file(tmp_path / "a.safetensors"), load_file(tmp_path / "b.safetensors")
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
