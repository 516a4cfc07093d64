"""The "ours" detector (YOLOv8 graph): published counts, public key layout, strides, bias init, the model contract."""

from __future__ import annotations

import math

import pytest
import torch

from adapters.detectors.yolo.v8 import build_yolov8
from harness.errors import ConfigError, HarnessError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def n_params(m: torch.nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def randomise_bn(model: torch.nn.Module, seed: int = 0) -> None:
    g = torch.Generator().manual_seed(seed)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(torch.rand(m.num_features, generator=g) * 0.2 - 0.1)
            m.running_var.copy_(torch.rand(m.num_features, generator=g) + 0.5)
            m.weight.data.copy_(torch.rand(m.num_features, generator=g) * 0.4 + 0.8)
            m.bias.data.copy_(torch.rand(m.num_features, generator=g) * 0.2 - 0.1)


@pytest.fixture(scope="module")
def small():
    torch.manual_seed(0)
    return build_yolov8(8, in_channels=4, scale="n")


def test_parameter_counts_match_the_reference_yolov8s_at_four_channels_and_eight_classes():
    model = build_yolov8(8, in_channels=4, scale="s")
    assert n_params(model) == 11_138_984  # unfused
    model.eval().fuse()
    assert n_params(model) == 11_128_968  # BatchNorm folded: the seed's 11.13 M
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())


def test_other_scales_and_three_channels_match_the_reference_table():
    assert n_params(build_yolov8(8, in_channels=4, scale="n")) == 3_012_552
    assert n_params(build_yolov8(8, in_channels=3, scale="s")) == 11_138_696


def test_flops_at_640_with_torch_flop_counter():
    from torch.utils.flop_counter import FlopCounterMode

    model = build_yolov8(8, in_channels=4, scale="s").eval().to("meta")  # meta: shapes only, no arithmetic
    with FlopCounterMode(display=False) as counter:
        model.forward_raw(torch.zeros(1, 4, 640, 640, device="meta"))
    # convolutions only (FlopCounterMode counts no BatchNorm, activation or upsampling), 2 FLOPs per multiply-add
    assert counter.get_total_flops() / 1e9 == pytest.approx(28.5057, abs=1e-3)


def test_state_dict_keys_and_shapes_follow_the_public_layout(small):
    model = build_yolov8(8, in_channels=4, scale="s")
    sd = model.state_dict()
    assert sd["model.0.conv.weight"].shape == (32, 4, 3, 3)
    assert sd["model.2.m.0.cv1.conv.weight"].shape == (32, 32, 3, 3)
    assert sd["model.9.cv2.conv.weight"].shape == (512, 1024, 1, 1)
    assert sd["model.22.cv2.0.0.conv.weight"].shape == (64, 128, 3, 3)
    assert sd["model.22.cv2.2.2.weight"].shape == (64, 64, 1, 1)
    assert sd["model.22.cv3.1.2.bias"].shape == (8,)
    assert sd["model.22.dfl.conv.weight"].flatten().tolist() == list(range(16))
    assert all(k.startswith("model.") for k in sd)
    assert len(sd) == 355


def test_strides_are_computed_and_head_biases_use_the_prior(small):
    assert small.stride.tolist() == [8.0, 16.0, 32.0]
    assert small.strides == (8, 16, 32)
    for i, s in enumerate((8, 16, 32)):
        assert torch.all(small.model[22].cv2[i][2].bias == 1.0)
        expected = math.log(5 / 8 / (640 / s) ** 2)
        torch.testing.assert_close(small.model[22].cv3[i][2].bias, torch.full((8,), expected))


def test_forward_raw_returns_one_map_per_level(small):
    small.eval()
    maps = small.forward_raw(torch.rand(2, 4, 64, 96))
    assert [tuple(m.shape) for m in maps] == [(2, 72, 8, 12), (2, 72, 4, 6), (2, 72, 2, 3)]


def test_train_mode_returns_scalar_losses_and_eval_mode_detections(small):
    x = torch.rand(2, 4, 64, 96)
    targets = [
        {"boxes": torch.tensor([[8.0, 8.0, 40.0, 50.0]]), "labels": torch.tensor([2])},
        {"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.long)},
    ]
    small.train()
    losses = small(x, targets)
    assert set(losses) == {"box", "cls", "dfl"}
    assert all(v.dim() == 0 and torch.isfinite(v) and v.requires_grad for v in losses.values())
    assert len(small(x)) == 3  # train mode without targets: the raw maps
    small.eval()
    with torch.no_grad():
        dets = small(x)
    assert len(dets) == 2
    for d in dets:
        assert set(d) == {"boxes", "scores", "labels"}
        k = len(d["scores"])
        assert d["boxes"].shape == (k, 4) and d["labels"].shape == (k,) and d["labels"].dtype == torch.long
        assert torch.all(d["scores"][:-1] >= d["scores"][1:])


def test_eval_boxes_lie_inside_the_image_and_respect_max_det():
    torch.manual_seed(1)
    model = build_yolov8(3, in_channels=4, scale="n", conf=0.0, max_det=50).eval()
    for det in model.head.cv2:  # large random box logits: many raw boxes cross the image border
        det[2].weight.data.normal_(0, 0.5)
    with torch.no_grad():
        raw_boxes, _ = model.decode(model.forward_raw(torch.rand(1, 4, 64, 64)))
        dets = model(torch.rand(1, 4, 64, 64))
    assert (raw_boxes < 0).any() or (raw_boxes > 64).any()
    b = dets[0]["boxes"]
    assert 0 < len(b) <= 50
    assert b.min() >= 0 and b[:, 0::2].max() <= 64 and b[:, 1::2].max() <= 64


def test_fused_model_gives_the_same_outputs():
    torch.manual_seed(2)
    model = build_yolov8(8, in_channels=4, scale="n")
    randomise_bn(model)
    model.eval()
    x = torch.rand(2, 4, 64, 64)
    with torch.no_grad():
        ref = model.forward_raw(x)
        ref_boxes, ref_scores = model.decode(ref)
        model.fuse()
        out = model.forward_raw(x)
        boxes, scores = model.decode(out)
    for a, b in zip(ref, out):
        torch.testing.assert_close(a, b, atol=2e-4, rtol=1e-4)
    torch.testing.assert_close(boxes, ref_boxes, atol=2e-3, rtol=1e-4)
    torch.testing.assert_close(scores, ref_scores, atol=1e-5, rtol=1e-4)


def test_bad_inputs_and_options_are_clear_errors(small):
    with pytest.raises(HarnessError, match="4 input channels but got 3"):
        small.forward_raw(torch.rand(1, 3, 64, 64))
    with pytest.raises(HarnessError, match="multiples of 32"):
        small.forward_raw(torch.rand(1, 4, 60, 64))
    with pytest.raises(ConfigError, match="unknown YOLOv8 option"):
        build_yolov8(8, scale="n", widht=0.5)
    with pytest.raises(ConfigError, match="scale"):
        build_yolov8(8, scale="q")
    with pytest.raises(HarnessError, match="outside 0..7"):
        small.train()(
            torch.rand(1, 4, 64, 64), [{"boxes": torch.tensor([[1.0, 1, 9, 9]]), "labels": torch.tensor([8])}]
        )
    with pytest.raises(HarnessError, match="one dict per image"):
        small.train()(torch.rand(2, 4, 64, 64), [{"boxes": torch.zeros(0, 4), "labels": torch.zeros(0)}])


def test_ours_is_a_registered_single_stream_detector(host):
    spec = host.detector("ours")
    assert spec.input_kind == "single"
    assert spec.reference.params_m == 11.13 and spec.reference.gflops == 28.5
    assert host.owner("detector", "ours") == "adapters.detectors.ours"
    model = spec.build(8, in_channels=4, scale="n", conf=0.25, iou=0.5, max_det=10)
    assert (model.nc, model.in_channels, model.conf, model.iou, model.max_det) == (8, 4, 0.25, 0.5, 10)
    assert callable(spec.load_official)


def test_harness_profile_reports_the_seed_figures(cli_runner):
    """``harness profile --detectors ours --format json``: 11,128,968 parameters fused and 28.5 GFLOPs (paper
    convention)."""
    import json

    pytest.importorskip("harness.profiling", reason="the profiling module is not in this checkout yet")
    result = cli_runner(
        ["profile", "--detectors", "ours", "--format", "json", "--no-latency", "--no-onnx", "--no-fvcore", "--no-store"]
    )
    assert result.exit_code == 0, result.output
    (record,) = json.loads(result.output)
    assert record["params"]["fused"] == 11_128_968
    assert record["params"]["total"] == 11_138_984
    assert round(record["flops"]["paper"]["gflops"], 1) == 28.5
    assert record["reference"] == {"params_m": 11.13, "gflops": 28.5, "source": "seed paper"}
