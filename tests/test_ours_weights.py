"""Importing public-layout YOLOv8 weights: 3 -> 4 channel inflation, another class count, fused sources, errors."""

from __future__ import annotations

import math

import pytest
import torch

from adapters.detectors.ours import build
from adapters.detectors.yolo.blocks import Conv
from adapters.detectors.yolo.v8 import build_yolov8
from adapters.detectors.yolo.weights import load_yolov8_weights, read_state_dict
from harness.errors import HarnessError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def trained_like(nc: int, in_channels: int, seed: int, scale: str = "n") -> torch.nn.Module:
    """A model whose weights and BatchNorm statistics are all non-trivial (as after training)."""
    torch.manual_seed(seed)
    model = build_yolov8(nc, in_channels=in_channels, scale=scale)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
                m.weight.uniform_(0.8, 1.2)
                m.bias.uniform_(-0.1, 0.1)
    return model.eval()


def test_rgb_weights_inflate_into_the_four_channel_stem(tmp_path):
    rgb = trained_like(8, 3, seed=0)
    path = tmp_path / "yolov8n-rgb.pt"
    torch.save(rgb.state_dict(), path)

    model = build(8, in_channels=4, scale="n", weights=str(path))  # through the plugin's build option
    report = model.load_report
    assert report["stem"] == {"checkpoint_channels": 3, "model_channels": 4, "extra_channels": "zeros"}
    assert report["reinitialised"] == [] and report["missing"] == [] and report["unexpected"] == []
    stem = model.model[0].conv.weight
    torch.testing.assert_close(stem[:, :3], rgb.model[0].conv.weight)
    assert torch.all(stem[:, 3] == 0)
    # zero C2 filters: the 4-channel model computes what the RGB model computed, whatever the fourth channel holds
    model.eval()
    x = torch.rand(2, 3, 64, 64)
    c2 = torch.rand(2, 1, 64, 64)
    with torch.no_grad():
        for a, b in zip(rgb.forward_raw(x), model.forward_raw(torch.cat((x, c2), 1))):
            torch.testing.assert_close(a, b)


def test_mean_inflation_keeps_the_response_to_a_grey_image():
    rgb = trained_like(8, 3, seed=1)
    model = build_yolov8(8, in_channels=4, scale="n").eval()
    report = load_yolov8_weights(model, rgb.state_dict(), extra_channels="mean")
    assert report["stem"]["extra_channels"] == "mean"
    w_rgb = rgb.model[0].conv.weight
    torch.testing.assert_close(model.model[0].conv.weight[:, 3], w_rgb.mean(1) * 3 / 4)
    grey = torch.rand(1, 1, 64, 64)
    with torch.no_grad():
        for a, b in zip(rgb.forward_raw(grey.expand(1, 3, 64, 64)), model.forward_raw(grey.expand(1, 4, 64, 64))):
            torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_four_channel_weights_load_unchanged_and_drop_to_three_channels():
    src = trained_like(8, 4, seed=2)
    same = build_yolov8(8, in_channels=4, scale="n").eval()
    report = load_yolov8_weights(same, src.state_dict())
    assert report["stem"] is None and report["loaded"] == len(src.state_dict())
    for (k, a), b in zip(src.state_dict().items(), same.state_dict().values()):
        assert torch.equal(a, b), k
    rgb_only = build_yolov8(8, in_channels=3, scale="n")
    report = load_yolov8_weights(rgb_only, src.state_dict())
    assert report["stem"]["model_channels"] == 3 and "dropped" in report["notes"][0]
    torch.testing.assert_close(rgb_only.model[0].conv.weight, src.model[0].conv.weight[:, :3])


def test_another_class_count_reinitialises_the_class_layers_and_says_so():
    src = trained_like(80, 3, seed=3, scale="s")  # e.g. COCO weights at scale s
    model = build_yolov8(8, in_channels=4, scale="s")
    report = load_yolov8_weights(model, src.state_dict())
    assert report["checkpoint_nc"] == 80
    assert report["reinitialised"] == sorted(f"model.22.cv3.{i}.2.{p}" for i in range(3) for p in ("bias", "weight"))
    assert any("80 classes" in n and "re-initialised" in n for n in report["notes"])
    for i, s in enumerate((8, 16, 32)):
        torch.testing.assert_close(model.model[22].cv3[i][2].bias, torch.full((8,), math.log(5 / 8 / (640 / s) ** 2)))
        torch.testing.assert_close(model.model[22].cv3[i][0].conv.weight, src.model[22].cv3[i][0].conv.weight)
    torch.testing.assert_close(model.model[21].cv2.bn.running_var, src.model[21].cv2.bn.running_var)


def test_narrow_class_branch_of_small_scales_is_reinitialised_whole():
    src = trained_like(80, 3, seed=4)  # scale n with 80 classes: class branch width max(64, 80) = 80
    model = build_yolov8(8, in_channels=4, scale="n")  # width 64
    report = load_yolov8_weights(model, src.state_dict())
    assert "model.22.cv3.0.0.conv.weight" in report["reinitialised"]
    assert all(k.startswith("model.22.cv3.") for k in report["reinitialised"])
    torch.testing.assert_close(model.model[22].cv2[0][0].conv.weight, src.model[22].cv2[0][0].conv.weight)


def test_fused_checkpoints_load_exactly():
    src = trained_like(8, 4, seed=5)
    x = torch.rand(1, 4, 64, 64)
    with torch.no_grad():
        ref = src.forward_raw(x)
        src.fuse()
    model = build_yolov8(8, in_channels=4, scale="n").eval()
    report = load_yolov8_weights(model, src.state_dict())
    n_conv_bn = sum(isinstance(m, Conv) for m in model.modules())
    assert "model.0" in report["fused_source"] and len(report["fused_source"]) == n_conv_bn
    with torch.no_grad():
        for a, b in zip(ref, model.forward_raw(x)):
            torch.testing.assert_close(a, b, atol=2e-4, rtol=1e-4)


def test_wrappers_and_safetensors_files(tmp_path):
    from safetensors.torch import save_file

    src = trained_like(8, 4, seed=6)
    sd = {k: v.contiguous() for k, v in src.state_dict().items()}
    save_file(sd, str(tmp_path / "w.safetensors"))
    torch.save({"model": {"module." + k: v for k, v in sd.items()}}, tmp_path / "wrapped.pt")
    for name in ("w.safetensors", "wrapped.pt"):
        model = build_yolov8(8, in_channels=4, scale="n")
        assert load_yolov8_weights(model, tmp_path / name)["loaded"] == len(sd)
        assert torch.equal(model.model[8].m[0].cv2.conv.weight, src.model[8].m[0].cv2.conv.weight)


def test_bad_checkpoints_are_clear_errors(tmp_path):
    model = build_yolov8(8, in_channels=4, scale="s")
    with pytest.raises(HarnessError, match="scale 'n'"):
        load_yolov8_weights(model, trained_like(8, 4, seed=7).state_dict())
    pickled = tmp_path / "whole-model.pt"
    torch.save({"model": torch.nn.Linear(2, 2)}, pickled)  # a pickled object, not plain tensors
    with pytest.raises(HarnessError, match="refused for safety"):
        read_state_dict(pickled)
    with pytest.raises(HarnessError, match="does not exist"):
        read_state_dict(tmp_path / "missing.pt")
    partial = {k: v for k, v in model.state_dict().items() if not k.startswith("model.22.")}
    with pytest.raises(HarnessError, match="lacks"):
        load_yolov8_weights(model, partial)
    report = load_yolov8_weights(model, partial, strict=False)
    assert report["missing"] and all(k.startswith("model.22.") for k in report["missing"])
    with pytest.raises(HarnessError, match="extra_channels"):
        load_yolov8_weights(
            build_yolov8(8, in_channels=4, scale="n"), trained_like(8, 3, seed=8).state_dict(), extra_channels="noise"
        )
