"""YOLOX losses and SimOTA assignment on hand-made cases and against a loop transcription of RVT's algorithm."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from davis_rig.errors import ShapeError
from davis_rig.training.losses import AnchorGrid, bboxes_iou_cxcywh, iou_loss, simota_assign, yolox_loss


def test_iou_hand_made():
    a = torch.tensor([[10.0, 10.0, 10.0, 10.0]])
    b = torch.tensor([[15.0, 10.0, 10.0, 10.0], [40.0, 40.0, 4.0, 4.0], [10.0, 10.0, 10.0, 10.0]])
    iou = bboxes_iou_cxcywh(a, b)
    assert iou.shape == (1, 3)
    assert iou[0, 0].item() == pytest.approx(50.0 / 150.0)
    assert iou[0, 1].item() == 0.0
    assert iou[0, 2].item() == 1.0
    loss = iou_loss(a.expand(3, 4), b)
    assert loss.tolist() == pytest.approx([1 - (1 / 3) ** 2, 1.0, 0.0])


def test_anchor_grid_order_and_decode():
    grid = AnchorGrid.build((64, 64), (8, 16, 32))
    assert grid.num_anchors == 64 + 16 + 4
    assert grid.cells[:3].tolist() == [[0, 0], [1, 0], [2, 0]]
    assert grid.cells[8].tolist() == [0, 1]  # row-major
    assert grid.strides[63].item() == 8 and grid.strides[64].item() == 16 and grid.strides[-1].item() == 32
    decoded = grid.decode(torch.zeros(grid.num_anchors, 4))
    assert decoded[9].tolist() == [8.0, 8.0, 8.0, 8.0]  # cell (1, 1) of stride 8, no +0.5 offset
    assert decoded[-1].tolist() == [32.0, 32.0, 32.0, 32.0]


def _raw_for_boxes(grid: AnchorGrid, boxes: torch.Tensor, num_classes: int = 2) -> torch.Tensor:
    """Raw outputs whose decoded boxes are ``boxes`` [A, 4] (cx, cy, w, h); obj/cls logits 0."""
    stride = grid.strides[:, None]
    txy = boxes[:, :2] / stride - grid.cells
    twh = torch.log(boxes[:, 2:] / stride)
    return torch.cat([txy, twh, torch.zeros(grid.num_anchors, 1 + num_classes)], 1)


def test_simota_candidates_and_single_match():
    grid = AnchorGrid.build((32, 32), (8, 16, 32))  # 16 + 4 + 1 anchors
    gt = torch.tensor([[12.0, 12.0, 16.0, 16.0]])
    preds = torch.tensor([[100.0, 100.0, 2.0, 2.0]]).repeat(grid.num_anchors, 1)  # IoU 0 everywhere
    preds[5] = gt[0]  # anchor (1, 1) of stride 8 predicts the label exactly
    raw = _raw_for_boxes(grid, preds)
    result = simota_assign(gt, torch.tensor([1]), grid.decode(raw[:, :4]), raw[:, 5:], raw[:, 4], grid)
    # dynamic k = int(1.0 + 0 ...) = 1 -> only the exact anchor
    assert result.fg_mask.nonzero().flatten().tolist() == [5]
    assert result.matched_gt.tolist() == [0] and result.matched_classes.tolist() == [1]
    assert result.matched_ious.tolist() == pytest.approx([1.0])


def test_simota_dynamic_k_and_geometry():
    grid = AnchorGrid.build((32, 32), (8, 16, 32))
    gt = torch.tensor([[12.0, 12.0, 16.0, 16.0]])
    preds = torch.tensor([[100.0, 100.0, 2.0, 2.0]]).repeat(grid.num_anchors, 1)
    # three candidates predict the label exactly -> k = 3; anchor 3 (centre x 28) is outside 1.5 strides
    for index in (0, 5, 16, 3):
        preds[index] = gt[0]
    raw = _raw_for_boxes(grid, preds)
    result = simota_assign(gt, torch.tensor([0]), grid.decode(raw[:, :4]), raw[:, 5:], raw[:, 4], grid)
    assert sorted(result.fg_mask.nonzero().flatten().tolist()) == [0, 5, 16]


def test_simota_conflict_goes_to_cheapest_label():
    grid = AnchorGrid.build((32, 32), (8, 16, 32))
    gts = torch.tensor([[12.0, 12.0, 16.0, 16.0], [13.0, 12.0, 16.0, 16.0]])
    preds = torch.tensor([[100.0, 100.0, 2.0, 2.0]]).repeat(grid.num_anchors, 1)
    preds[5] = gts[1]  # both labels want anchor 5 (k = 1 each); it is closer to label 1
    raw = _raw_for_boxes(grid, preds)
    result = simota_assign(gts, torch.tensor([1, 1]), grid.decode(raw[:, :4]), raw[:, 5:], raw[:, 4], grid)
    assert result.fg_mask.nonzero().flatten().tolist() == [5]
    assert result.matched_gt.tolist() == [1]
    assert result.matched_ious.tolist() == pytest.approx([1.0])


def _reference_simota(gt, gt_cls, pred, cls_logits, obj_logits, grid):
    """Loop transcription of RVT's get_geometry_constraint + get_assignments + simota_matching."""
    num_gt, num_anchors = gt.shape[0], grid.num_anchors
    centers = (grid.cells + 0.5) * grid.strides[:, None]
    in_center = torch.zeros(num_gt, num_anchors, dtype=torch.bool)
    for g in range(num_gt):
        for a in range(num_anchors):
            r = 1.5 * grid.strides[a]
            deltas = [centers[a, 0] - (gt[g, 0] - r), centers[a, 1] - (gt[g, 1] - r),
                      gt[g, 0] + r - centers[a, 0], gt[g, 1] + r - centers[a, 1]]
            in_center[g, a] = min(float(d) for d in deltas) > 0
    fg = in_center.sum(0) > 0
    geometry = in_center[:, fg]
    ious = bboxes_iou_cxcywh(gt, pred[fg])
    scores = (cls_logits[fg].sigmoid() * obj_logits[fg].sigmoid()[:, None]).sqrt()
    onehot = F.one_hot(gt_cls, cls_logits.shape[1]).float()
    cost = torch.zeros(num_gt, int(fg.sum()))
    for g in range(num_gt):
        for c in range(cost.shape[1]):
            cost[g, c] = (F.binary_cross_entropy(scores[c], onehot[g], reduction="none").sum()
                          - 3.0 * math.log(ious[g, c] + 1e-8) + (0.0 if geometry[g, c] else 1e6))
    matching = torch.zeros_like(cost, dtype=torch.uint8)
    k_cand = min(10, ious.shape[1])
    ks = torch.clamp(torch.topk(ious, k_cand, dim=1).values.sum(1).int(), min=1)
    for g in range(num_gt):
        order = sorted(range(cost.shape[1]), key=lambda c: (float(cost[g, c]), c))
        for c in order[: int(ks[g])]:
            matching[g, c] = 1
    counts = matching.sum(0)
    for c in range(cost.shape[1]):
        if counts[c] > 1:
            best = min(range(num_gt), key=lambda g: (float(cost[g, c]), g))
            matching[:, c] = 0
            matching[best, c] = 1
    fg_in = counts > 0
    fg_mask = fg.clone()
    fg_mask[fg.clone()] = fg_in
    matched = matching[:, fg_in].argmax(0)
    match_iou = (matching * ious).sum(0)[fg_in]
    return fg_mask, matched, match_iou


@pytest.mark.parametrize("seed", range(6))
def test_simota_matches_loop_reference(seed):
    gen = torch.Generator().manual_seed(seed)
    grid = AnchorGrid.build((64, 96), (8, 16, 32))
    num_gt = 1 + seed % 3
    gt = torch.cat([torch.rand(num_gt, 2, generator=gen) * torch.tensor([96.0, 64.0]),
                    8 + torch.rand(num_gt, 2, generator=gen) * 40], 1)
    cls = torch.randint(0, 2, (num_gt,), generator=gen)
    jitter = torch.randn(grid.num_anchors, 4, generator=gen) * torch.tensor([6.0, 6.0, 8.0, 8.0])
    pred = (gt[torch.randint(0, num_gt, (grid.num_anchors,), generator=gen)] + jitter).abs() + 1
    cls_logits = torch.randn(grid.num_anchors, 2, generator=gen)
    obj_logits = torch.randn(grid.num_anchors, generator=gen)
    result = simota_assign(gt, cls, pred, cls_logits, obj_logits, grid)
    fg_ref, matched_ref, iou_ref = _reference_simota(gt, cls, pred, cls_logits, obj_logits, grid)
    assert torch.equal(result.fg_mask, fg_ref)
    assert result.matched_gt.tolist() == matched_ref.tolist()
    assert torch.allclose(result.matched_ious, iou_ref)
    assert result.matched_classes.tolist() == cls[matched_ref].tolist()


def test_loss_without_labels_is_objectness_only():
    grid = AnchorGrid.build((32, 32), (8, 16, 32))
    raw = torch.zeros(1, grid.num_anchors, 7, requires_grad=True)
    out = yolox_loss(raw, [torch.zeros(0, 5)], grid)
    # every anchor: BCE(logit 0, target 0) = log 2; n_fg = max(0, 1) = 1
    assert out["conf_loss"].item() == pytest.approx(grid.num_anchors * math.log(2), rel=1e-6)
    assert out["iou_loss"].item() == 0.0 and out["cls_loss"].item() == 0.0
    out["loss"].backward()
    assert raw.grad is not None and raw.grad[..., 4].abs().sum() > 0


def test_loss_hand_made_single_match():
    grid = AnchorGrid.build((32, 32), (8, 16, 32))
    gt_box = torch.tensor([12.0, 12.0, 16.0, 16.0])
    preds = torch.tensor([[100.0, 100.0, 2.0, 2.0]]).repeat(grid.num_anchors, 1)
    preds[5] = gt_box
    raw = _raw_for_boxes(grid, preds)[None]
    out = yolox_loss(raw, [torch.cat([torch.tensor([1.0]), gt_box])[None]], grid)
    # one foreground anchor with IoU 1: iou loss 0; objectness: 20 anchors target 0 and one target 1, logits 0
    assert out["iou_loss"].item() == pytest.approx(0.0, abs=1e-6)
    assert out["conf_loss"].item() == pytest.approx(grid.num_anchors * math.log(2), rel=1e-6)
    # class target one-hot(1) · IoU 1 on logits 0: BCE(0, 0) + BCE(0, 1) = 2 log 2
    assert out["cls_loss"].item() == pytest.approx(2 * math.log(2), rel=1e-6)
    assert out["num_fg"].item() == 1.0
    assert out["loss"].item() == pytest.approx(out["conf_loss"].item() + out["cls_loss"].item(), rel=1e-6)


def test_l1_loss_optional_and_zero_for_exact_match():
    grid = AnchorGrid.build((32, 32), (8, 16, 32))
    gt_box = torch.tensor([12.0, 12.0, 16.0, 16.0])
    preds = torch.tensor([[100.0, 100.0, 2.0, 2.0]]).repeat(grid.num_anchors, 1)
    preds[5] = gt_box
    raw = _raw_for_boxes(grid, preds)[None]
    out = yolox_loss(raw, [torch.cat([torch.tensor([0.0]), gt_box])[None]], grid, use_l1=True)
    assert out["l1_loss"].item() == pytest.approx(0.0, abs=1e-5)


def test_loss_shape_errors():
    grid = AnchorGrid.build((32, 32), (8, 16, 32))
    with pytest.raises(ShapeError):
        yolox_loss(torch.zeros(1, 5, 7), [None], grid)
    with pytest.raises(ShapeError):
        yolox_loss(torch.zeros(1, grid.num_anchors, 7), [torch.zeros(2, 4)], grid)
    with pytest.raises(ShapeError):
        yolox_loss(torch.zeros(2, grid.num_anchors, 7), [None], grid)
