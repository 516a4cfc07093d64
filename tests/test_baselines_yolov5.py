"""YOLOv5 pieces: scaling rules, the anchor head's decoding and bias prior, target matching, loss and NMS."""

from __future__ import annotations

import math

import pytest
import torch

from adapters.detectors.yolo.blocks import fuse_model
from adapters.detectors.yolo.loss_v5 import YOLOv5Loss, match_targets
from adapters.detectors.yolo.v5 import (
    ANCHORS_P3_P5,
    Detect,
    backbone_layers,
    make_divisible,
    pan_layers,
    postprocess,
    scale_depth,
    scale_width,
    targets_to_tensor,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def n_params(modules) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def test_scaling_rules_of_the_yolov5_parser():
    assert make_divisible(64 * 0.25) == 16 and make_divisible(1024 * 0.33) == 344
    assert [scale_width(c, 0.5) for c in (64, 256, 1024)] == [32, 128, 512]
    assert [scale_depth(n, 0.33) for n in (1, 3, 6, 9)] == [1, 1, 2, 3]
    assert [scale_depth(n, 0.67) for n in (3, 6, 9)] == [2, 4, 6]


def test_yolov5l_and_yolov5s_parameter_counts_from_the_published_layer_table():
    # ICAFusion layer table (YOLOv5l, nc=8): one stream's backbone 26,582,912; neck+head 19,593,077 (incl. Detect)
    assert n_params(backbone_layers(3, 1.0, 1.0)) == 26_582_912
    assert n_params(pan_layers(1.0, 1.0)) + n_params([Detect(8, (256, 512, 1024))]) == 19_593_077
    # YOLOv5s at nc=80: 7,235,389 parameters, 7,225,885 with BatchNorm folded (YOLOv5's own summaries)
    s = torch.nn.ModuleList(backbone_layers(3, 0.5, 0.33) + pan_layers(0.5, 0.33) + [Detect(80, (128, 256, 512))])
    assert n_params([s]) == 7_235_389
    assert n_params([fuse_model(s)]) == 7_225_885


def test_detect_decodes_zero_logits_to_cell_centres_and_anchor_sizes():
    head = Detect(2, (4, 4, 4))
    assert torch.allclose(head.anchors[0, 0], torch.tensor([10 / 8, 13 / 8]))  # grid units, as checkpoints store them
    raw = [torch.zeros(1, 3, s, s, 7) for s in (4, 2, 1)]
    out = head.decode(raw)
    assert out.shape == (1, 3 * (16 + 4 + 1), 7)
    # level 0, anchor 1, cell (x=2, y=1): xy = (2*0.5 - 0.5 + cell) * 8, wh = (2*0.5)^2 * anchor
    torch.testing.assert_close(out[0, 16 + 1 * 4 + 2], torch.tensor([20.0, 12.0, 16.0, 30.0, 0.5, 0.5, 0.5]))
    with_grid = Detect(2, (4, 4, 4), anchor_grid_buffer=True)
    torch.testing.assert_close(with_grid.decode(raw), out)
    assert tuple(with_grid.anchor_grid.shape) == (3, 1, 3, 1, 1, 2)


def test_prior_bias_of_yolov5():
    torch.manual_seed(0)
    head = Detect(8, (4, 4, 4))
    before = [m.bias.detach().clone().view(3, -1) for m in head.m]
    head.init_prior_bias()
    for s, b0, m in zip((8, 16, 32), before, head.m):
        d = m.bias.detach().view(3, -1) - b0
        torch.testing.assert_close(d[:, 4], torch.full((3,), math.log(8 / (640 / s) ** 2)))
        torch.testing.assert_close(d[:, 5:], torch.full((3, 8), math.log(0.6 / (8 - 0.99999))))
        assert d[:, :4].abs().max() == 0


def test_matching_by_wh_ratio_and_two_neighbour_cells():
    anchors = torch.tensor(ANCHORS_P3_P5[0], dtype=torch.float32).view(3, 2) / 8
    # a 40x40 box centred at (102, 58) px on the stride-8, 80x80 grid: centre (12.75, 7.25) cells
    targets = torch.tensor([[0.0, 3.0, 102.0, 58.0, 40.0, 40.0]])
    b, a, gj, gi, tbox, anch, cls = match_targets(targets, anchors, (80, 80), 8.0)
    # anchor 0 (10x13 px): 40/10 = 4 is not < 4 -> no match; anchors 1 and 2 match
    # cells: own (12, 7); right neighbour (13, 7) since x is 0.25 cell from its edge; upper (12, 6) likewise
    got = sorted(zip(a.tolist(), gi.tolist(), gj.tolist(), [tuple(round(v, 4) for v in t) for t in tbox.tolist()]))
    want = sorted(
        (ai, x, y, t)
        for ai in (1, 2)
        for x, y, t in (
            (12, 7, (0.75, 0.25, 5.0, 5.0)),
            (13, 7, (-0.25, 0.25, 5.0, 5.0)),
            (12, 6, (0.75, 1.25, 5.0, 5.0)),
        )
    )
    assert got == want
    assert set(cls.tolist()) == {3} and set(b.tolist()) == {0}
    torch.testing.assert_close(anch[a == 1][0], anchors[1])


def test_loss_terms_against_hand_values():
    # one anchor per level; the target equals level 0's anchor and sits on a cell centre: exactly one positive
    head = Detect(2, (4, 4, 4), anchors=((16, 30), (160, 300), (320, 600)))
    loss = YOLOv5Loss(head)
    raw = [torch.zeros(1, 1, s, s, 7) for s in (8, 4, 2)]  # a 64x64 input, all logits 0
    targets = torch.tensor([[0.0, 1.0, 8 * 3.5, 8 * 2.5, 16.0, 30.0]])
    out = loss(raw, targets, (64, 64))
    ln2 = math.log(2.0)
    # zero logits predict exactly the anchor at the cell centre: CIoU = 1, box loss 0
    assert out["box"].item() == pytest.approx(0.0, abs=1e-6)
    # BCE(0, y) = log 2 for any y: obj = log2 * (4.0 + 1.0 + 0.4) * (64/640)^2, cls = log2 * 0.5 * 2/80
    assert out["obj"].item() == pytest.approx(ln2 * 5.4 * (64 / 640) ** 2, rel=1e-5)
    assert out["cls"].item() == pytest.approx(ln2 * 0.5 * 2 / 80, rel=1e-5)
    # the batch size multiplies every term; no targets: box and cls are zero
    empty = loss([torch.zeros(3, 1, s, s, 7) for s in (8, 4, 2)], torch.zeros(0, 6), (64, 64))
    assert empty["box"].item() == 0 and empty["cls"].item() == 0
    assert empty["obj"].item() == pytest.approx(3 * ln2 * 5.4 * 0.01, rel=1e-5)


def test_targets_are_converted_and_degenerate_boxes_dropped():
    rows = targets_to_tensor(
        [
            {"boxes": torch.tensor([[10.0, 20.0, 30.0, 60.0], [5.0, 5.0, 5.0, 9.0]]), "labels": torch.tensor([2, 1])},
            {"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.long)},
        ],
        torch.device("cpu"),
        "t",
    )
    assert rows.tolist() == [[0.0, 2.0, 20.0, 40.0, 20.0, 40.0]]


def _pred(rows: list[list[float]], nc: int = 3) -> torch.Tensor:
    """Decoded predictions from (cx, cy, w, h, obj, cls...) rows."""
    return torch.tensor(rows, dtype=torch.float32).view(1, -1, 5 + nc)


def test_nms_keeps_the_best_box_per_class_and_the_harness_format():
    p = _pred(
        [
            [50, 50, 20, 20, 0.9, 0.9, 0.0, 0.0],  # class 0, score 0.81
            [52, 50, 20, 20, 0.8, 0.9, 0.0, 0.0],  # overlaps the first, class 0: suppressed
            [52, 50, 20, 20, 0.8, 0.0, 0.5, 0.0],  # same box, class 1: kept (classes never suppress each other)
            [150, 150, 10, 10, 0.5, 0.0, 0.0, 0.1],  # score 0.05 < conf 0.1: dropped
        ]
    )
    (det,) = postprocess(p, conf=0.1, iou=0.5, max_det=300, multi_label=False, image_size=(200, 200))
    assert set(det) == {"boxes", "scores", "labels"}
    assert det["labels"].tolist() == [0, 1]
    torch.testing.assert_close(det["scores"], torch.tensor([0.81, 0.4]))
    torch.testing.assert_close(det["boxes"], torch.tensor([[40.0, 40.0, 60.0, 60.0], [42.0, 40.0, 62.0, 60.0]]))
    assert det["boxes"].dtype == torch.float32 and det["labels"].dtype == torch.int64


def test_nms_multi_label_max_det_and_clipping():
    p = _pred([[5, 50, 20, 20, 1.0, 0.6, 0.5, 0.0], [100, 100, 20, 20, 1.0, 0.0, 0.0, 0.3]])
    (det,) = postprocess(p, conf=0.1, iou=0.5, max_det=300, multi_label=True, image_size=(120, 110))
    assert det["labels"].tolist() == [0, 1, 2]  # the first box carries two classes
    assert det["boxes"][0].tolist() == [0.0, 40.0, 15.0, 60.0]  # clipped at x = 0
    assert det["boxes"][2].tolist() == [90.0, 90.0, 110.0, 110.0]  # clipped at w = 110
    (top,) = postprocess(p, conf=0.1, iou=0.5, max_det=2, multi_label=True)
    assert top["labels"].tolist() == [0, 1]
    (none,) = postprocess(p, conf=0.99, iou=0.5)
    assert none["boxes"].shape == (0, 4) and none["labels"].dtype == torch.int64
