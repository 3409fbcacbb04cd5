"""YOLOX training losses with SimOTA label assignment, as RVT trains its head (``yolo_head.py::get_losses``).

Semantics (checked against RVT's ``models/detection/yolox/models/yolo_head.py`` and ``losses.py``):

* predictions are decoded like the head: ``cx, cy = (t_xy + cell) · stride``, ``w, h = exp(t_wh) · stride``
  (no +0.5 cell offset); objectness and class outputs stay logits;
* candidates of a label: anchors whose cell centre ``(cell + 0.5) · stride`` lies strictly within
  ``1.5 · stride`` of the label centre in x and y (``get_geometry_constraint``); the union over labels is the
  candidate set;
* cost = BCE(sqrt(σ(cls) · σ(obj)), one-hot class) summed over classes + 3 · (−log(IoU + 1e-8)) + 1e6 outside
  the label's own centre region;
* dynamic k per label = max(1, int(sum of its top-min(10, candidates) IoUs)); each label takes its k
  cheapest candidates; an anchor claimed by several labels goes to the cheapest one;
* targets: objectness 1 on matched anchors (0 elsewhere, every anchor of every image); class target one-hot ·
  IoU of the match; box target the matched label;
* loss = 5 · Σ(1 − IoU²) / n_fg + Σ BCE(obj) / n_fg + Σ BCE(cls) / n_fg (+ L1 on raw offsets, off as in RVT),
  with n_fg = max(total matched anchors in the batch, 1).

The assignment is computed in float32 without gradients; the losses in float32 (safe under autocast).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from davis_rig._lazy import optional_dependency
from davis_rig.errors import ShapeError

with optional_dependency("training"):
    import torch
    import torch.nn.functional as F

__all__ = ["AnchorGrid", "SimOTAResult", "bboxes_iou_cxcywh", "iou_loss", "simota_assign", "yolox_loss",
           "yolox_targets", "init_head_biases"]

CENTER_RADIUS = 1.5
IOU_COST_WEIGHT = 3.0
OUTSIDE_COST = 1e6
REG_WEIGHT = 5.0
MAX_CANDIDATE_K = 10


@dataclass(frozen=True)
class AnchorGrid:
    """Anchor cells of the YOLOX head, in the head's output order (levels by stride, cells row-major).

    Attributes:
        cells: float32 [A, 2] (column, row) of each anchor's cell.
        strides: float32 [A] stride of each anchor, px.
    """

    cells: torch.Tensor
    strides: torch.Tensor

    @classmethod
    def build(cls, in_res_hw: tuple[int, int], strides: Sequence[int] = (8, 16, 32), device=None) -> "AnchorGrid":
        """Anchors for a padded input (height, width) px and the head strides."""
        cells, per_anchor = [], []
        for stride in strides:
            height, width = in_res_hw[0] // stride, in_res_hw[1] // stride
            rows, cols = torch.meshgrid(torch.arange(height, dtype=torch.float32, device=device),
                                        torch.arange(width, dtype=torch.float32, device=device), indexing="ij")
            cells.append(torch.stack([cols.reshape(-1), rows.reshape(-1)], dim=1))
            per_anchor.append(torch.full((height * width,), float(stride), device=device))
        return cls(torch.cat(cells), torch.cat(per_anchor))

    @property
    def num_anchors(self) -> int:
        return int(self.strides.shape[0])

    def to(self, device) -> "AnchorGrid":
        return AnchorGrid(self.cells.to(device), self.strides.to(device))

    def decode(self, raw_boxes: torch.Tensor) -> torch.Tensor:
        """Decode raw box outputs [..., A, 4] ``(t_x, t_y, t_w, t_h)`` into (cx, cy, w, h) px like the head."""
        stride = self.strides[:, None]
        return torch.cat([(raw_boxes[..., :2] + self.cells) * stride, torch.exp(raw_boxes[..., 2:4]) * stride], -1)


def bboxes_iou_cxcywh(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """Pairwise IoU of (cx, cy, w, h) boxes (YOLOX ``bboxes_iou(xyxy=False)``).

    Args:
        boxes_a: float [N, 4]; boxes_b: float [M, 4] (px).

    Returns:
        float [N, M] IoU (intersection 0 when the boxes do not overlap).
    """
    if boxes_a.shape[-1] != 4 or boxes_b.shape[-1] != 4:
        raise ShapeError(f"bboxes_iou: expected [N, 4] and [M, 4], got {tuple(boxes_a.shape)}, {tuple(boxes_b.shape)}")
    tl = torch.max(boxes_a[:, None, :2] - boxes_a[:, None, 2:] / 2, boxes_b[None, :, :2] - boxes_b[None, :, 2:] / 2)
    br = torch.min(boxes_a[:, None, :2] + boxes_a[:, None, 2:] / 2, boxes_b[None, :, :2] + boxes_b[None, :, 2:] / 2)
    area_a = boxes_a[:, 2] * boxes_a[:, 3]
    area_b = boxes_b[:, 2] * boxes_b[:, 3]
    overlap = (tl < br).to(boxes_a.dtype).prod(dim=2)
    area_i = (br - tl).prod(dim=2) * overlap
    return area_i / (area_a[:, None] + area_b[None, :] - area_i)


def iou_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Element-wise YOLOX IoU loss ``1 − IoU²`` of matched (cx, cy, w, h) boxes [K, 4] → [K]."""
    tl = torch.max(pred[:, :2] - pred[:, 2:] / 2, target[:, :2] - target[:, 2:] / 2)
    br = torch.min(pred[:, :2] + pred[:, 2:] / 2, target[:, :2] + target[:, 2:] / 2)
    area_p = pred[:, 2] * pred[:, 3]
    area_g = target[:, 2] * target[:, 3]
    overlap = (tl < br).to(pred.dtype).prod(dim=1)
    area_i = (br - tl).prod(dim=1) * overlap
    iou = area_i / (area_p + area_g - area_i + 1e-16)
    return 1 - iou**2


@dataclass
class SimOTAResult:
    """Assignment of one image.

    Attributes:
        fg_mask: bool [A] anchors matched to a label.
        matched_gt: int64 [F] label index of each matched anchor (anchors in increasing order).
        matched_classes: int64 [F] class of the matched label.
        matched_ious: float32 [F] IoU between the anchor's prediction and its label.
    """

    fg_mask: torch.Tensor
    matched_gt: torch.Tensor
    matched_classes: torch.Tensor
    matched_ious: torch.Tensor

    @property
    def num_fg(self) -> int:
        return int(self.matched_gt.shape[0])


@torch.no_grad()
def simota_assign(
    gt_boxes: torch.Tensor,
    gt_classes: torch.Tensor,
    pred_boxes: torch.Tensor,
    cls_logits: torch.Tensor,
    obj_logits: torch.Tensor,
    anchors: AnchorGrid,
) -> SimOTAResult:
    """SimOTA dynamic-k assignment of one image (YOLOX / RVT ``get_assignments`` + ``simota_matching``).

    Args:
        gt_boxes: float [G, 4] labels (cx, cy, w, h), input px; G ≥ 1.
        gt_classes: int [G] class ids.
        pred_boxes: float [A, 4] decoded predictions (cx, cy, w, h).
        cls_logits: float [A, nc] class logits.
        obj_logits: float [A] or [A, 1] objectness logits.
        anchors: the anchor grid (A anchors).

    Returns:
        The :class:`SimOTAResult`.
    """
    num_gt = int(gt_boxes.shape[0])
    num_anchors = anchors.num_anchors
    device = pred_boxes.device
    gt_boxes = gt_boxes.float()
    pred_boxes = pred_boxes.float()
    centers = (anchors.cells + 0.5) * anchors.strides[:, None]  # [A, 2]
    radius = anchors.strides * CENTER_RADIUS  # [A]
    delta = (centers[None, :, :] - gt_boxes[:, None, :2]).abs()  # [G, A, 2]
    in_center = (delta < radius[None, :, None]).all(dim=2)  # strict, as min(deltas) > 0
    candidates = in_center.any(dim=0)
    cand_index = torch.nonzero(candidates).flatten()
    fg_mask = torch.zeros(num_anchors, dtype=torch.bool, device=device)
    empty = torch.zeros(0, dtype=torch.int64, device=device)
    if cand_index.numel() == 0:
        return SimOTAResult(fg_mask, empty, empty, torch.zeros(0, device=device))
    geometry = in_center[:, cand_index]  # [G, C]
    ious = bboxes_iou_cxcywh(gt_boxes, pred_boxes[cand_index])  # [G, C]
    num_classes = int(cls_logits.shape[-1])
    scores = (cls_logits[cand_index].float().sigmoid() * obj_logits.reshape(-1, 1)[cand_index].float().sigmoid())
    scores = scores.sqrt()  # [C, nc]
    onehot = F.one_hot(gt_classes.long(), num_classes).float()  # [G, nc]
    cls_cost = F.binary_cross_entropy(scores[None].expand(num_gt, -1, -1),
                                      onehot[:, None, :].expand(-1, scores.shape[0], -1), reduction="none").sum(-1)
    cost = cls_cost + IOU_COST_WEIGHT * (-torch.log(ious + 1e-8)) + OUTSIDE_COST * (~geometry).float()

    num_cand = int(cand_index.numel())
    top_k = min(MAX_CANDIDATE_K, num_cand)
    dynamic_k = torch.clamp(torch.topk(ious, top_k, dim=1).values.sum(1).int(), min=1)  # [G]
    order = torch.sort(cost, dim=1, stable=True).indices  # cheapest first
    take = torch.arange(num_cand, device=device)[None, :] < dynamic_k[:, None]
    matching = torch.zeros_like(cost, dtype=torch.bool)
    matching.scatter_(1, order, take)
    multiple = matching.sum(0) > 1
    if bool(multiple.any()):
        cheapest = cost[:, multiple].argmin(dim=0)
        matching[:, multiple] = False
        matching[cheapest, multiple] = True
    fg_cand = matching.any(dim=0)
    matched_gt = matching[:, fg_cand].float().argmax(dim=0)
    matched_ious = (matching.float() * ious).sum(0)[fg_cand]
    fg_mask[cand_index[fg_cand]] = True
    return SimOTAResult(fg_mask, matched_gt, gt_classes.long()[matched_gt], matched_ious)


def yolox_targets(labels: torch.Tensor) -> torch.Tensor:
    """Training labels float [K, 5] ``(class, x, y, w, h)`` (px, top-left corner) as the label format of
    :func:`yolox_loss`, float [K, 5] ``(class, cx, cy, w, h)``."""
    return torch.stack([labels[:, 0], labels[:, 1] + labels[:, 3] / 2, labels[:, 2] + labels[:, 4] / 2,
                        labels[:, 3], labels[:, 4]], dim=1)


def _l1_target(gt: torch.Tensor, strides: torch.Tensor, cells: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    return torch.cat([gt[:, :2] / strides[:, None] - cells, torch.log(gt[:, 2:4] / strides[:, None] + eps)], 1)


def yolox_loss(
    raw: torch.Tensor,
    labels: Sequence[torch.Tensor | None],
    anchors: AnchorGrid,
    *,
    use_l1: bool = False,
    reg_weight: float = REG_WEIGHT,
) -> dict[str, torch.Tensor]:
    """YOLOX losses of a batch of head outputs (RVT ``get_losses``).

    Args:
        raw: float [N, A, 5 + nc] pre-decode head outputs ``(t_x, t_y, t_w, t_h, obj logit, class logits)``
            (``RVTDetector.forward_raw_head``).
        labels: N entries, each float [K, 5] ``(class, cx, cy, w, h)`` in input px, K ≥ 0 (an image without
            objects trains objectness towards 0 everywhere).
        anchors: the anchor grid matching A.
        use_l1: add the L1 loss on raw offsets (YOLOX's last epochs; RVT keeps it off).
        reg_weight: weight of the IoU loss (5.0).

    Returns:
        ``{"loss", "iou_loss" (weighted), "conf_loss", "cls_loss", "l1_loss", "num_fg" (matched anchors per
        label)}``: scalar tensors; ``loss`` carries the gradient.

    Raises:
        ShapeError: ``raw`` does not match the anchors, or a label tensor is not [K, 5].
    """
    if raw.ndim != 3 or raw.shape[1] != anchors.num_anchors or raw.shape[2] < 6:
        raise ShapeError(f"yolox_loss: expected raw [N, {anchors.num_anchors}, 5 + nc], got {tuple(raw.shape)}")
    if len(labels) != raw.shape[0]:
        raise ShapeError(f"yolox_loss: {raw.shape[0]} images but {len(labels)} label entries")
    raw = raw.float()
    num_classes = raw.shape[2] - 5
    boxes = anchors.decode(raw[..., :4])
    obj = raw[..., 4]
    cls = raw[..., 5:]
    fg_masks, cls_targets, box_targets, l1_targets = [], [], [], []
    num_gts = 0
    for image, gt in enumerate(labels):
        fg = torch.zeros(anchors.num_anchors, dtype=torch.bool, device=raw.device)
        if gt is not None and gt.numel():
            if gt.ndim != 2 or gt.shape[1] != 5:
                raise ShapeError(f"labels[{image}]: expected [K, 5] (class, cx, cy, w, h), got {tuple(gt.shape)}")
            gt = gt.to(raw.device).float()
            num_gts += int(gt.shape[0])
            result = simota_assign(gt[:, 1:5], gt[:, 0].long(), boxes[image].detach(), cls[image].detach(),
                                   obj[image].detach(), anchors)
            fg = result.fg_mask
            cls_targets.append(F.one_hot(result.matched_classes, num_classes).float() * result.matched_ious[:, None])
            matched = gt[result.matched_gt, 1:5]
            box_targets.append(matched)
            if use_l1:
                l1_targets.append(_l1_target(matched, anchors.strides[fg], anchors.cells[fg]))
        fg_masks.append(fg)
    fg_all = torch.stack(fg_masks)  # [N, A]
    num_fg_total = int(fg_all.sum())
    denom = float(max(num_fg_total, 1))
    obj_loss = F.binary_cross_entropy_with_logits(obj, fg_all.float(), reduction="sum") / denom
    zero = raw.sum() * 0.0
    if num_fg_total:
        box_t = torch.cat(box_targets)
        iou_l = iou_loss(boxes[fg_all], box_t).sum() / denom
        cls_l = F.binary_cross_entropy_with_logits(cls[fg_all], torch.cat(cls_targets), reduction="sum") / denom
        l1_l = (F.l1_loss(raw[..., :4][fg_all], torch.cat(l1_targets), reduction="sum") / denom) if use_l1 else zero
    else:
        iou_l = cls_l = l1_l = zero
    loss = reg_weight * iou_l + obj_loss + cls_l + l1_l
    return {"loss": loss, "iou_loss": reg_weight * iou_l.detach(), "conf_loss": obj_loss.detach(),
            "cls_loss": cls_l.detach(), "l1_loss": l1_l.detach(),
            "num_fg": torch.tensor(num_fg_total / max(num_gts, 1))}


def init_head_biases(model, prior_prob: float = 0.01) -> None:
    """Set the class and objectness prediction biases to ``−log((1 − p) / p)`` (YOLOX / RVT initialisation).

    Args:
        model: an ``RVTDetector`` (its ``yolox_head.cls_preds`` / ``obj_preds`` are changed in place).
        prior_prob: the prior probability p.
    """
    value = -math.log((1 - prior_prob) / prior_prob)
    with torch.no_grad():
        for conv in list(model.yolox_head.cls_preds) + list(model.yolox_head.obj_preds):
            conv.bias.fill_(value)
