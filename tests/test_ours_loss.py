"""YOLOv8 training loss: task-aligned assignment on hand-made cases, DFL and box-distance maths, padding, learning."""

from __future__ import annotations

import math

import pytest
import torch

from adapters.detectors.yolo.loss_v8 import (
    V8DetectionLoss,
    bbox2dist,
    dfl_expectation,
    dfl_loss,
    dist2bbox,
    make_anchors,
    pad_targets,
)
from adapters.detectors.yolo.tal import TaskAlignedAssigner, anchors_inside_boxes
from adapters.detectors.yolo.v8 import build_yolov8
from harness.errors import HarnessError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def grid(n: int = 4, stride: int = 8) -> torch.Tensor:
    """Anchor points (pixels) of an n x n grid: centres 4, 12, 20, 28 for stride 8."""
    pts, _ = make_anchors([torch.zeros(1, 1, n, n)], [stride])
    return pts * stride


def centred_boxes(points: torch.Tensor, size: float) -> torch.Tensor:
    return torch.cat((points - size / 2, points + size / 2), -1)


def test_make_anchors_are_cell_centres_row_major():
    pts, strides = make_anchors([torch.zeros(1, 1, 2, 3), torch.zeros(1, 1, 1, 2)], [8, 16])
    assert pts.tolist() == [
        [0.5, 0.5],
        [1.5, 0.5],
        [2.5, 0.5],
        [0.5, 1.5],
        [1.5, 1.5],
        [2.5, 1.5],
        [0.5, 0.5],
        [1.5, 0.5],
    ]
    assert strides.flatten().tolist() == [8] * 6 + [16] * 2


def test_box_distances_round_trip_and_clamp():
    pts = torch.tensor([[5.0, 5.0], [1.0, 1.0]])
    boxes = torch.tensor([[2.0, 3.0, 9.0, 6.0], [2.0, 2.0, 30.0, 3.0]])
    d = bbox2dist(pts, boxes, 14.99)
    assert d.tolist()[0] == [3.0, 2.0, 4.0, 1.0]
    # anchor outside the box on the left/top, far right clamped
    assert d[1].tolist() == pytest.approx([0.0, 0.0, 14.99, 2.0])
    torch.testing.assert_close(dist2bbox(d[:1], pts[:1]), boxes[:1])


def test_dfl_expectation_and_loss_on_hand_computed_values():
    logits = torch.full((1, 4 * 16), -1e4)
    logits[0, 3] = logits[0, 4] = 0.0  # side 0: half mass on bins 3 and 4 -> 3.5
    logits[0, 16 + 7] = 0.0  # side 1: all mass on bin 7
    logits[0, 32:48] = 0.0  # side 2: uniform -> 7.5
    logits[0, 48 + 15] = 0.0  # side 3: bin 15
    assert dfl_expectation(logits, 16).tolist() == [[3.5, 7.0, 7.5, 15.0]]
    # DFL with probabilities p3 = p4 = 0.5 and target 3.25: -(0.75 log 0.5 + 0.25 log 0.5) = log 2
    two_bins = torch.full((1, 16), -1e4)
    two_bins[0, 3] = two_bins[0, 4] = 0.0
    torch.testing.assert_close(dfl_loss(two_bins, torch.tensor([3.25])), torch.tensor([math.log(2)]))
    # a uniform distribution costs log(16) whatever the target
    torch.testing.assert_close(dfl_loss(torch.zeros(2, 16), torch.tensor([0.0, 9.7])), torch.full((2,), math.log(16)))


def test_pad_targets_pads_to_the_most_boxes_and_checks_labels():
    t = [
        {"boxes": torch.tensor([[0.0, 0, 4, 4], [1, 1, 5, 5]]), "labels": torch.tensor([1, 2])},
        {"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.long)},
        {"boxes": [[2.0, 2, 6, 6]], "labels": [0]},
    ]
    boxes, labels, mask = pad_targets(t, 3, nc=3, device=torch.device("cpu"))
    assert boxes.shape == (3, 2, 4) and labels.tolist() == [[1, 2], [0, 0], [0, 0]]
    assert mask.tolist() == [[True, True], [False, False], [True, False]]
    assert boxes[2, 0].tolist() == [2, 2, 6, 6]
    with pytest.raises(HarnessError, match="targets\\[0\\]"):
        pad_targets([{"boxes": torch.zeros(2, 5), "labels": torch.zeros(2)}], 1, 3, torch.device("cpu"))


def test_assigner_picks_the_topk_best_aligned_anchors_inside_the_box():
    pts = grid()  # 16 anchors, centres 4, 12, 20, 28
    pd_boxes = centred_boxes(pts, 24.0)[None]  # every anchor predicts a 24x24 box around itself
    pd_scores = torch.full((1, 16, 2), 0.5)
    gt = torch.tensor([[[0.0, 0.0, 24.0, 24.0]]])  # holds the 9 anchors with centres 4, 12, 20
    out = TaskAlignedAssigner(2, topk=5, alpha=0.5, beta=6.0)(
        pd_scores, pd_boxes, pts, torch.tensor([[1]]), gt, torch.tensor([[True]])
    )
    fg = out.fg_mask[0].view(4, 4)
    # the centre anchor (12,12) predicts the box exactly (CIoU 1); its 4 edge neighbours come next (CIoU 0.46);
    # the 4 corner anchors (CIoU 0.22) and the anchors outside the box are not chosen
    expected = torch.zeros(4, 4, dtype=torch.bool)
    expected[1, 1] = expected[0, 1] = expected[1, 0] = expected[2, 1] = expected[1, 2] = True
    assert torch.equal(fg, expected)
    assert torch.all(out.labels[0][out.fg_mask[0]] == 1) and torch.all(out.labels[0][~out.fg_mask[0]] == 2)
    assert torch.all(out.boxes[0][out.fg_mask[0]] == gt[0, 0])
    # soft targets: t * max IoU / max t with t = s^0.5 * u^6 -> (u / u_max)^6 * u_max; class 0 gets nothing
    ciou_edge = 0.5 - 64 / 1600  # IoU 0.5 minus centre distance^2 / enclosing diagonal^2 (aspect terms vanish)
    scores = out.scores[0, :, 1].view(4, 4)
    assert scores[1, 1].item() == pytest.approx(1.0, abs=1e-6)
    assert scores[0, 1].item() == pytest.approx(ciou_edge**6, rel=1e-4)
    assert out.scores[0, :, 0].abs().sum() == 0 and scores[~expected].abs().sum() == 0


def test_assigner_gives_a_shared_anchor_to_the_box_it_overlaps_most_and_ignores_padding():
    pts = grid()
    pd_boxes = centred_boxes(pts, 16.0)[None]
    pd_scores = torch.full((1, 16, 3), 0.5)
    gts = torch.tensor(
        [
            [
                [0.0, 0.0, 16.0, 24.0],  # anchors (4|12, 4|12|20)
                [8.0, 0.0, 24.0, 16.0],  # anchors (12|20, 4|12)
                [0.0, 0.0, 32.0, 32.0],
            ]
        ]
    )  # padding: must be ignored
    labels = torch.tensor([[0, 2, 1]])
    out = TaskAlignedAssigner(3, topk=10)(pd_scores, pd_boxes, pts, labels, gts, torch.tensor([[True, True, False]]))
    idx = {(4, 4): 0, (12, 4): 1, (4, 12): 4, (12, 12): 5, (20, 4): 2, (20, 12): 6, (4, 20): 8, (12, 20): 9}
    fg = out.fg_mask[0]
    assert fg.nonzero().flatten().tolist() == sorted(
        idx[p] for p in [(4, 4), (12, 4), (4, 12), (12, 12), (20, 4), (20, 12), (4, 20), (12, 20)]
    )
    # anchors (12,4) and (12,12) lie in both boxes. Their 16x16 predictions [4,-4,20,12] and [4,4,20,20] have
    # CIoU 0.222 / 0.351 with box 0 / box 1 at (12,4), and 0.412 / 0.351 at (12,12) (worked out by hand):
    # (12,4) goes to box 1 (label 2), (12,12) to box 0 (label 0)
    assert out.gt_index[0, idx[(12, 4)]].item() == 1 and out.labels[0, idx[(12, 4)]].item() == 2
    assert out.gt_index[0, idx[(12, 12)]].item() == 0 and out.labels[0, idx[(12, 12)]].item() == 0
    assert out.gt_index[0, idx[(20, 12)]].item() == 1 and out.gt_index[0, idx[(4, 20)]].item() == 0
    assert (out.gt_index[0][fg] != 2).all()


def test_assigner_without_any_box_assigns_nothing():
    pts = grid()
    out = TaskAlignedAssigner(2)(
        torch.rand(2, 16, 2),
        centred_boxes(pts, 8)[None].repeat(2, 1, 1),
        pts,
        torch.zeros(2, 0, dtype=torch.long),
        torch.zeros(2, 0, 4),
        torch.zeros(2, 0, dtype=torch.bool),
    )
    assert not out.fg_mask.any() and out.scores.sum() == 0 and torch.all(out.labels == 2)


def test_min_side_lets_a_box_thinner_than_the_stride_find_anchors():
    pts = grid()
    thin = torch.tensor([[[13.0, 2.0, 19.0, 30.0]]])  # 6 px wide, between anchor columns 12 and 20
    assert not anchors_inside_boxes(pts, thin).any()
    inside = anchors_inside_boxes(pts, thin, min_side=16.0)[0, 0].view(4, 4)
    assert inside[:, 1:3].all() and not inside[:, 0].any() and not inside[:, 3].any()


def test_loss_without_objects_is_classification_only_and_backpropagates():
    torch.manual_seed(0)
    maps = [torch.randn(2, 64 + 3, s, s, requires_grad=True) for s in (8, 4, 2)]
    crit = V8DetectionLoss(nc=3)
    crit.strides = (8, 16, 32)
    empty = [{"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.long)}] * 2
    losses = crit(maps, empty)
    assert losses["box"].item() == 0 and losses["dfl"].item() == 0 and losses["cls"].item() > 0
    sum(losses.values()).backward()
    # all targets are background: cls = 0.5 * batch * sum BCE(logit, 0) / 1
    logits = torch.cat([m.detach().reshape(2, 67, -1)[:, 64:] for m in maps], 2)
    expected = 0.5 * 2 * torch.nn.functional.softplus(logits).sum()
    torch.testing.assert_close(losses["cls"].detach(), expected)


def test_loss_decreases_over_a_few_steps_on_a_tiny_batch():
    torch.manual_seed(0)
    model = build_yolov8(4, in_channels=4, scale="n").train()
    x = torch.rand(2, 4, 96, 96)
    targets = [
        {"boxes": torch.tensor([[10.0, 12.0, 50.0, 60.0], [60.0, 40.0, 90.0, 92.0]]), "labels": torch.tensor([0, 3])},
        {"boxes": torch.tensor([[20.0, 20.0, 70.0, 44.0]]), "labels": torch.tensor([2])},
    ]
    opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9)
    history = []
    for _ in range(16):
        losses = model(x, targets)
        total = sum(losses.values())
        opt.zero_grad()
        total.backward()
        opt.step()
        history.append({k: v.item() for k, v in losses.items()})
    first, last = history[0], history[-1]
    assert sum(last.values()) < 0.6 * sum(first.values())
    assert last["box"] < first["box"] and last["cls"] < first["cls"] and last["dfl"] < first["dfl"]


def reference_assignment(scores, pd_boxes, points, labels, gt_boxes, gt_mask, topk, alpha=0.5, beta=6.0):
    """The task-aligned rule written the obvious way, with loops (only for small cases)."""
    from harness.boxes import bbox_iou

    n_img, n_anchor, _ = scores.shape
    fg = torch.zeros(n_img, n_anchor, dtype=torch.bool)
    gt_index = torch.zeros(n_img, n_anchor, dtype=torch.long)
    target = torch.zeros_like(scores)
    for b in range(n_img):
        real = [g for g in range(gt_boxes.shape[1]) if gt_mask[b, g]]

        def inside(a, g):
            x, y = points[a].tolist()
            x1, y1, x2, y2 = gt_boxes[b, g].tolist()
            return x1 < x < x2 and y1 < y < y2

        def overlap(a, g):
            return max(0.0, bbox_iou(gt_boxes[b, g], pd_boxes[b, a], kind="ciou").item()) if inside(a, g) else 0.0

        def metric(a, g):
            return scores[b, a, labels[b, g]].item() ** alpha * overlap(a, g) ** beta

        chosen: dict[int, list[int]] = {}
        for g in real:
            ranked = sorted((a for a in range(n_anchor) if inside(a, g)), key=lambda a: -metric(a, g))
            assert len(ranked) >= topk and metric(ranked[topk - 1], g) > 0  # no ties at zero in these cases
            for a in ranked[:topk]:
                chosen.setdefault(a, []).append(g)
        owner = {a: (gs[0] if len(gs) == 1 else max(real, key=lambda g: overlap(a, g))) for a, gs in chosen.items()}
        for g in real:
            mine = [a for a, o in owner.items() if o == g]
            if not mine:
                continue
            best_t = max(metric(a, g) for a in mine)
            best_u = max(overlap(a, g) for a in mine)
            for a in mine:
                fg[b, a] = True
                gt_index[b, a] = g
                target[b, a, labels[b, g]] = metric(a, g) * best_u / best_t
    return fg, gt_index, target


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_assigner_matches_the_rule_written_with_loops(seed):
    g = torch.Generator().manual_seed(seed)
    points, strides = make_anchors([torch.zeros(1, 1, 64 // s, 64 // s) for s in (8, 16, 32)], [8, 16, 32])
    points = points * strides  # 84 anchor points of a 64x64 image
    n_img, n_box, nc, topk = 2, 4, 3, 4
    centre = torch.rand(n_img, n_box, 2, generator=g) * 24 + 20
    half = torch.rand(n_img, n_box, 2, generator=g) * 8 + 14
    gt_boxes = torch.cat((centre - half, centre + half), -1)  # overlapping boxes, 28-44 px a side
    gt_mask = torch.tensor([[True, True, True, False], [True, True, True, True]])
    labels = torch.randint(0, nc, (n_img, n_box), generator=g)
    pd_centre = points[None] + torch.randn(n_img, len(points), 2, generator=g) * 3
    pd_half = torch.rand(n_img, len(points), 2, generator=g) * 10 + 10
    pd_boxes = torch.cat((pd_centre - pd_half, pd_centre + pd_half), -1)
    scores = torch.rand(n_img, len(points), nc, generator=g) * 0.9 + 0.05

    out = TaskAlignedAssigner(nc, topk=topk)(scores, pd_boxes, points, labels, gt_boxes, gt_mask)
    fg, gt_index, target = reference_assignment(scores, pd_boxes, points, labels, gt_boxes, gt_mask, topk)
    assert torch.equal(out.fg_mask, fg)
    assert torch.equal(out.gt_index[fg], gt_index[fg])
    torch.testing.assert_close(out.scores, target, atol=1e-6, rtol=1e-4)
    # fewer positives than boxes x topk: some anchors were wanted by several boxes, so the conflict rule is exercised
    assert int(fg.sum()) < int(gt_mask.sum()) * topk


def test_gains_scale_the_losses():
    torch.manual_seed(3)
    maps = [torch.randn(2, 64 + 3, s, s) for s in (8, 4, 2)]
    targets = [
        {"boxes": torch.tensor([[4.0, 6.0, 40.0, 50.0]]), "labels": torch.tensor([1])},
        {"boxes": torch.tensor([[20.0, 10.0, 60.0, 30.0]]), "labels": torch.tensor([2])},
    ]

    def run(**gains):
        crit = V8DetectionLoss(nc=3, **gains)
        crit.strides = (8, 16, 32)
        return crit(maps, targets)

    base = run()
    doubled = run(box=15.0, cls=1.0, dfl=3.0)
    for k in ("box", "cls", "dfl"):
        assert base[k].item() > 0
        torch.testing.assert_close(doubled[k], 2 * base[k])
