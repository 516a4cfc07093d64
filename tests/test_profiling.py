"""Profiling on small models whose parameters and FLOPs are worked out by hand.

TinyAttentionDetector, input [1, 4, 16, 16]:
  stem   Conv2d 4->8, 3x3, stride 2, no bias: 8*4*9 = 288 params; out 8x8x8 = 512 elements x 36 MACs = 18,432 MACs
  bn     BatchNorm2d(8): 16 params (+17 buffer elements); folded into the stem by fuse() (stem gains an 8-bias)
  q,k,v  Linear 8->8: 72 params each; 64 tokens x 8 x 8 = 4,096 MACs each
  attn   q @ k^T: 64 x 64 x 8 = 32,768 MACs; attn @ v: 64 x 8 x 64 = 32,768 MACs (torch.matmul, no module)
  head   Conv2d 8->6, 1x1, bias: 54 params; 64 x 6 x 8 = 3,072 MACs
  up     Upsample x2 nearest: 6 x 16 x 16 = 1,536 output elements (thop and fvcore: 1 op each)
  unused Linear 8->3, never called: 27 params;  dead: a 5-element parameter never used
"""

from __future__ import annotations

import json

import pytest
import torch
from torch import nn

from harness.api import DetectorSpec, Reference
from harness.hookspecs import hookimpl
from harness.profiling import example_inputs, profile_model
from harness.profiling.export import ExportError, check_onnx, export_onnx
from harness.profiling.flops import exact_flops, fvcore_flops, paper_flops
from harness.profiling.latency import torch_latency
from harness.profiling.model_io import fused_copy
from harness.profiling.params import reachable_parameters
from profiling_models import TinyAttentionDetector, TinyDualDetector

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CONV, LINEARS, ATTN, HEAD, UP = 18_432, 3 * 4_096, 2 * 32_768, 3_072, 1_536
BN_MACS = 2 * 512 * 2  # thop: 2 ops per input element, doubled for an affine BatchNorm


def _x():
    return torch.rand(1, 4, 16, 16, generator=torch.Generator().manual_seed(0))


def test_parameters_total_trainable_and_reachable():
    model = TinyAttentionDetector().eval()
    model.head.bias.requires_grad_(False)
    p = reachable_parameters(model, _x())
    assert p.total == 288 + 16 + 3 * 72 + 54 + 27 + 5 == 606
    assert p.trainable == 606 - 6
    assert p.buffers == 8 + 8 + 1
    assert p.reachable == 606 - 27 - 5
    assert sorted(p.unreachable) == ["dead", "unused.bias", "unused.weight"]
    assert p.unreachable_count == 32
    assert p.modules_not_called == ["unused"]
    assert p.frozen_unreachable == [] and p.frozen_unreachable_count == 0
    assert next(model.parameters()).device.type == "cpu"  # the analysis ran on a meta copy


def test_frozen_unreachable_parameters_are_told_apart_from_unused_ones():
    from harness.commands.profile import format_profiles

    model = TinyAttentionDetector().eval()
    model.dead.requires_grad_(False)  # like a fixed decoding projection applied after the raw forward
    p = reachable_parameters(model, _x())
    assert p.unreachable_count == 32
    assert p.frozen_unreachable == ["dead"] and p.frozen_unreachable_count == 5
    r = profile_model(model, _x(), latency=False, onnx=False, fvcore=False)
    r.update(detector="tiny", imgsz=16, num_classes=6)
    text = format_profiles([r])
    assert "tiny: 27 parameters never take part in the forward pass: unused.weight, unused.bias" in text
    assert "tiny: 5 frozen parameters are outside the raw forward" in text and text.count("dead") == 1
    from harness.commands.profile import profile_rows

    header, rows = profile_rows([r])
    assert rows[0][header.index("unused params")] == "27"
    assert all(len(line) <= 100 for line in text.splitlines())


def test_paper_flops_follow_thop_rules():
    model = TinyAttentionDetector().eval()
    fused, did = fused_copy(model)
    assert did and sum(p.numel() for p in fused.parameters()) == 606 - 16 + 8
    paper = paper_flops(fused, _x())
    assert paper.flops == 2 * (CONV + LINEARS + HEAD + UP)  # attention matmuls are not modules: not counted
    assert paper.by_module["stem"] == 2 * CONV and paper.by_module["up"] == 2 * UP
    assert paper_flops(model, _x()).flops == 2 * (CONV + BN_MACS + LINEARS + HEAD + UP)  # unfused: BN counted


def test_paper_flops_match_types_exactly_like_thop():
    class MyConv(nn.Conv2d):
        pass

    net = nn.Sequential(MyConv(3, 4, 3), nn.Conv2d(4, 2, 1))
    rep = paper_flops(net, torch.zeros(1, 3, 10, 10))
    assert rep.flops == 2 * (8 * 8 * 2 * 4)  # only the plain Conv2d: 64 positions x 2 out x 4 in
    assert rep.not_counted == ["MyConv"]


def test_exact_flops_count_the_attention_matmuls():
    fused, _ = fused_copy(TinyAttentionDetector().eval())
    exact = exact_flops(fused, _x())
    assert exact.flops == 2 * (CONV + LINEARS + ATTN + HEAD)  # no upsampling in this convention
    assert exact.flops - paper_flops(fused, _x()).flops == 2 * (ATTN - UP)


def test_exact_flops_count_fused_attention_kernels_on_meta():
    class SDPA(nn.Module):
        def forward_raw(self, x):  # x [B, 64, 8] used as q, k and v of one head
            q = x[:, None]
            return torch.nn.functional.scaled_dot_product_attention(q, q, q)

    assert exact_flops(SDPA(), torch.rand(1, 64, 8)).flops == 2 * 2 * 64 * 64 * 8
    assert paper_flops(SDPA(), torch.rand(1, 64, 8)).flops == 0


def test_fvcore_view_and_table():
    fused, _ = fused_copy(TinyAttentionDetector().eval())
    fv = fvcore_flops(fused, _x())
    assert fv.flops == 2 * (CONV + LINEARS + ATTN + HEAD + UP)
    assert any(op.startswith("aten::softmax") for op in fv.not_counted)
    assert "stem" in fv.table and "multiply-adds" in fv.table


def test_dual_stream_model():
    model = TinyDualDetector().eval()
    inputs = (torch.rand(1, 3, 16, 16), torch.rand(1, 1, 16, 16))
    p = reachable_parameters(model, inputs)
    assert (p.total, p.reachable, p.unreachable) == (108 + 36 + 18, 162, [])
    macs = 256 * 4 * 27 + 256 * 4 * 9 + 256 * 2 * 8
    assert paper_flops(model, inputs).flops == exact_flops(model, inputs).flops == 2 * macs


def test_example_inputs_follow_the_detector_contract():
    x = example_inputs("single", 32, channels=4)
    assert x.shape == (1, 4, 32, 32) and 0 <= float(x.min()) and float(x.max()) <= 1
    rgb, th = example_inputs("dual", (24, 32), thermal_channels=1)
    assert rgb.shape == (1, 3, 24, 32) and th.shape == (1, 1, 24, 32)


@pytest.mark.slow
def test_export_single_and_dual_input_models(tmp_path):
    import numpy as np
    import onnxruntime as ort

    rec = export_onnx(TinyAttentionDetector().eval(), _x(), tmp_path / "single.onnx")
    assert rec["opset"] >= 17 and rec["matches_torch"] and rec["max_abs_diff"] <= 1e-4
    assert list(rec["inputs"]) == ["images"] and rec["outputs"] == {"output0": [1, 6, 16, 16]}
    assert rec["fused"] and not rec["nms_in_graph"]

    dual = TinyDualDetector().eval()
    inputs = (torch.rand(1, 3, 16, 16), torch.rand(1, 1, 16, 16))
    rec = export_onnx(dual, inputs, tmp_path / "dual.onnx", dynamic_batch=True)
    assert list(rec["inputs"]) == ["rgb", "thermal"] and list(rec["outputs"]) == ["output0", "output1"]
    sess = ort.InferenceSession(str(tmp_path / "dual.onnx"))
    rgb, th = torch.rand(3, 3, 16, 16), torch.rand(3, 1, 16, 16)
    got = sess.run(None, {"rgb": rgb.numpy(), "thermal": th.numpy()})
    with torch.no_grad():
        want = dual.forward_raw((rgb, th))
    assert all(np.abs(g - w.numpy()).max() <= 1e-4 for g, w in zip(got, want))


def test_export_check_refuses_mismatching_outputs(tmp_path):
    model = TinyDualDetector().eval()
    inputs = (torch.rand(1, 3, 16, 16), torch.rand(1, 1, 16, 16))
    export_onnx(model, inputs, tmp_path / "m.onnx", check=False)
    with torch.no_grad():
        out = model.forward_raw(inputs)
    with pytest.raises(ExportError, match="output1 differs from torch"):
        check_onnx(tmp_path / "m.onnx", inputs, (out[0], out[1] + 1e-3))
    with pytest.raises(ExportError, match="opset 16 is too old"):
        export_onnx(model, inputs, tmp_path / "old.onnx", opset=16)


def test_latency_protocol_excludes_warmup_and_records_threads():
    class Counting(TinyDualDetector):
        calls = 0

        def forward_raw(self, inputs):
            Counting.calls += 1
            return super().forward_raw(inputs)

    inputs = (torch.rand(1, 3, 16, 16), torch.rand(1, 1, 16, 16))
    before = torch.get_num_threads()
    lat = torch_latency(Counting().eval(), inputs, warmup=3, runs=7, threads=1)
    assert Counting.calls == 3 + 7
    assert (lat["warmup"], lat["runs"], lat["threads"], lat["device"]) == (3, 7, 1, "cpu")
    assert 0 < lat["min_ms"] <= lat["median_ms"] <= lat["p90_ms"] and lat["first_ms"] > 0
    assert torch.get_num_threads() == before


def test_profile_model_end_to_end(tmp_path):
    r = profile_model(TinyAttentionDetector().eval(), _x(), warmup=2, runs=5, threads=1, onnx_path=tmp_path / "p.onnx")
    assert r["params"]["fused"] == 598 and r["params"]["unreachable_count"] == 32
    assert r["flops"]["paper"]["flops"] == 2 * (CONV + LINEARS + HEAD + UP)
    assert r["flops"]["exact"]["flops"] == 2 * (CONV + LINEARS + ATTN + HEAD)
    assert "thop-0.1.1" in r["flops"]["paper"]["convention"] and "meta" in r["flops"]["exact"]["convention"]
    assert r["onnx"]["matches_torch"] and r["latency"]["onnxruntime"]["threads"] == 1
    assert r["latency"]["torch"]["runs"] == 5
    json.dumps(r)  # storable as it is


class _TinyPlugin:
    @hookimpl
    def register_detectors(self, register):
        register(
            DetectorSpec(
                name="tiny-attn",
                build=lambda num_classes, in_channels=4, **kw: TinyAttentionDetector(),
                reference=Reference(params_m=0.0006, gflops=0.00007, source="hand count", imgsz=16),
            )
        )
        register(
            DetectorSpec(
                name="tiny-dual",
                build=lambda num_classes, in_channels=1, **kw: TinyDualDetector(),
                input_kind="dual",
                thermal_channels=1,
            )
        )
        register(DetectorSpec(name="tiny-broken", build=_broken))


def _broken(num_classes, **kw):
    raise ValueError("no weights for this width")


def test_published_figures_stand_only_beside_the_configuration_they_describe():
    ref = Reference(params_m=11.13, gflops=28.5, source="paper", num_classes=8)
    assert ref.applies(8, 640) and ref.applies(8, 640, {})
    assert not ref.applies(8, 640, {"scale": "n"})  # another model
    assert not ref.applies(1, 640) and not ref.applies(8, 320)  # other classes, other input size
    assert Reference(params_m=1.0).applies(3, 640)  # no class count published: any


def test_cli_profile_and_export(cli_runner, tmp_path):
    from harness.store import Store
    from harness.testing import temporary_plugin

    with temporary_plugin(_TinyPlugin(), name="tiny-profiling-plugin"):
        args = ["--imgsz", "16", "--runs", "3", "--warmup", "1", "--threads", "1", "--no-onnx"]
        res = cli_runner(["profile", "--detector", "tiny-attn,tiny-dual", *args, "--store", str(tmp_path / "store")])
        assert res.exit_code == 0, res.output
        lines = res.output.splitlines()
        row = next(line for line in lines if line.startswith("tiny-attn"))
        assert row.split()[2:5] == ["0.001", "0.00", "32"]  # fused params (M), ref, unused
        assert "GFLOPs paper: BatchNorm folded" in res.output
        assert "never take part in the forward pass: dead, unused.weight, unused.bias" in res.output
        folder = Store(tmp_path / "store").profile_path("x").parent
        stored = {p.stem: json.loads(p.read_text()) for p in folder.glob("*.json")}
        assert set(stored) == {"tiny-attn", "tiny-dual"}
        assert stored["tiny-attn"]["flops"]["exact"]["flops"] == 2 * (CONV + LINEARS + ATTN + HEAD)
        assert stored["tiny-attn"]["reference"]["source"] == "hand count"
        assert stored["tiny-dual"]["input"]["shapes"] == [[1, 3, 16, 16], [1, 1, 16, 16]]

        out = tmp_path / "dual.onnx"
        res = cli_runner(["export", "--detector", "tiny-dual", "--out", str(out), "--imgsz", "16"])
        assert res.exit_code == 0, res.output
        assert out.exists() and "inputs: rgb [1, 3, 16, 16], thermal [1, 1, 16, 16]" in res.output
        assert "onnxruntime matches torch" in res.output

        res = cli_runner(["profile", "--detector", "nope", "--no-store"])
        assert res.exit_code == 2 and "unknown detector 'nope'" in res.output

        # one detector that cannot be built does not stop the others
        res = cli_runner(["profile", "--detector", "tiny-broken,tiny-dual", *args, "--no-store", "--no-fvcore"])
        assert res.exit_code == 1
        assert any(line.startswith("tiny-dual") and "error" not in line for line in res.output.splitlines())
        assert "tiny-broken: not profiled: detector 'tiny-broken' could not be built" in res.output
        assert "no weights for this width" in res.output
