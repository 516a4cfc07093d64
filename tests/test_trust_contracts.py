"""Plugin outputs are checked at the boundary, and the host calls only namespaced or declared names on a model."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from torch import nn

from harness.errors import PluginError


def _det(k=3, boxes=None, scores=None, labels=None):
    return {
        "boxes": torch.rand(k, 4) * 10 + torch.tensor([0, 0, 10, 10]) if boxes is None else boxes,
        "scores": torch.rand(k) if scores is None else scores,
        "labels": torch.zeros(k, dtype=torch.int64) if labels is None else labels,
    }


@pytest.mark.parametrize(
    "bad, field, expected",
    [
        (_det(boxes=torch.rand(4, 5)), "'boxes'", "[K, 4]"),  # 4 x 5 = 20 values reshape silently into 5 boxes
        (_det(scores=torch.rand(3, 1)), "'scores'", "[K] = [3]"),
        (_det(labels=torch.zeros(3)), "'labels'", "integer"),
        (_det(labels=torch.tensor([0, 1, 2])), "'labels'", "0..1"),
        (_det(scores=torch.tensor([0.5, float("nan"), 0.2])), "'scores'", "finite"),
        ({"boxes": torch.rand(2, 4)}, "'scores', 'labels'", "keys"),
    ],
)
def test_eval_outputs_that_break_the_contract_name_detector_field_and_expectation(bad, field, expected):
    from harness.engine.predict import detections_to_coco

    with pytest.raises(PluginError) as err:
        detections_to_coco(bad, 1, None, num_classes=2, name="broken-det")
    text = str(err.value)
    assert "broken-det" in text and field in text and expected in text


def test_a_valid_eval_output_passes_unchanged():
    from harness.engine.predict import detections_to_coco

    det = _det(
        k=2,
        boxes=torch.tensor([[1.0, 2.0, 11.0, 22.0], [0.0, 0.0, 5.0, 5.0]]),
        scores=torch.tensor([0.9, 0.4]),
        labels=torch.tensor([1, 0]),
    )
    out = detections_to_coco(det, 7, None, num_classes=2, name="ok")
    assert [(o["category_id"], o["bbox"]) for o in out] == [(2, [1.0, 2.0, 10.0, 20.0]), (1, [0.0, 0.0, 5.0, 5.0])]


def test_a_per_image_loss_vector_is_a_named_contract_error():
    from harness.engine.trainer import Trainer

    with pytest.raises(PluginError, match=r"vec-det.*loss 'box' must be a scalar.*\[4\]"):
        Trainer._total(SimpleNamespace(name="vec-det"), {"box": torch.ones(4), "cls": torch.ones(())}, 0, 0)
    total = Trainer._total(SimpleNamespace(name="ok"), {"box": torch.tensor(2.0), "cls": torch.ones(1)}, 0, 0)
    assert float(total) == 3.0


class FusionNet(nn.Module):
    """A fusion detector whose fusion block is an attribute named ``fuse`` and that declares no BN fold."""

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(4, 8, 3, padding=1, bias=False)
        self.bn = nn.BatchNorm2d(8)
        self.fuse = nn.Conv2d(8, 8, 1)

    def forward_raw(self, x):
        return self.fuse(self.bn(self.conv(x)))

    def forward(self, x):
        return self.forward_raw(x)


def test_an_attribute_named_fuse_is_never_called_and_the_model_is_not_labelled_folded():
    from harness.commands.profile import format_profiles
    from harness.profiling import profile_model

    rec = profile_model(FusionNet(), torch.rand(1, 4, 32, 32), latency=False, onnx=False, fvcore=False)
    assert rec["params"]["bn_folded"] is False
    assert rec["params"]["fused"] == sum(p.numel() for p in FusionNet().parameters())
    rec.update(detector="fusionnet", imgsz=32, num_classes=2)
    text = format_profiles([rec])
    assert "Params = BN-folded parameter count" not in text and "except fusionnet" in text


def test_the_namespaced_fold_is_preferred():
    from harness.contracts import fold_batchnorm

    class Declared(FusionNet):
        def harness_fuse(self):
            self.bn = nn.Identity()
            return self

    m, folded = fold_batchnorm(Declared())
    assert folded and isinstance(m.bn, nn.Identity) and isinstance(m.fuse, nn.Conv2d)


def test_fuse_conv_bn_keeps_the_model_dtype():
    from adapters.detectors.yolo.blocks import fuse_conv_bn

    conv, bn = nn.Conv2d(3, 4, 3, bias=False).double(), nn.BatchNorm2d(4).double().eval()
    bn.running_mean.uniform_(-1, 1)
    bn.running_var.uniform_(0.5, 2)
    fused = fuse_conv_bn(conv, bn)
    assert fused.weight.dtype == torch.float64
    x = torch.rand(1, 3, 8, 8, dtype=torch.float64)
    assert torch.allclose(fused(x), bn(conv(x)), atol=1e-12)
