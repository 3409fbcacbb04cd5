"""The paper's adversarial loss on the detector's decoded (pre-NMS) output.

``L_adv = lambda_1 * L_obj + lambda_2 * L_cls`` with ``L_obj`` the mean objectness and ``L_cls`` the mean
pedestrian-class probability over **all anchors of all windows** of the attacked sequence (official code:
``predict.view(-1, 7)[:, 4].mean()`` and ``[:, 5 + 1].mean()``; ``lambda_1 = lambda_2 = 10^4``). No boxes are
needed; optionally the means can be restricted to the anchors whose predicted centre lies near the person's
box (``boxes=``), or to the anchors whose cell overlaps the person's box (``anchor_mask=`` from
:func:`anchors_on_boxes`; the attack's ``loss_anchors="person"``), which concentrates the gradient on the person
instead of on background anchors (the background anchors' ``p_ped`` is > 98 % of the paper's loss on the
detectors trained here).

``reduction="top"`` (not in the paper) scores, per window and clip, only the anchor with the highest detection
confidence ``obj * p_class`` (what postprocess thresholds), and averages those over windows and clips. On a
detector whose background anchors carry a non-negligible ``p_class`` the all-anchor mean is dominated by
background terms the texture cannot change (measured on the bundled detector: mean ``p_ped`` 0.10 against mean
objectness 0.004, docs/attack.md), whereas the top anchor is the person's detection itself.

The input is what :class:`davis_rig.models.rvt.detector.RVTDetector` returns per recurrent step:
``decoded [B, A, 5 + nc] = (cx, cy, w, h, obj, p_car, p_ped)`` (Gen1), objectness and class scores already
probabilities. Pure function, no state; differentiable w.r.t. ``decoded``.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

from davis_rig._lazy import optional_dependency
from davis_rig.errors import ShapeError
from davis_rig.types import PEDESTRIAN_CLASS_ID

with optional_dependency("the adversarial loss"):
    import torch

__all__ = [
    "DEFAULT_LAMBDA",
    "LOSS_ANCHORS",
    "LOSS_REDUCTIONS",
    "AdversarialLoss",
    "adversarial_loss",
    "anchor_cells",
    "anchors_near_boxes",
    "anchors_on_boxes",
]

#: The paper's weights lambda_1 = lambda_2.
DEFAULT_LAMBDA = 1e4
#: ``"mean"``: all (kept) anchors, the paper; ``"top"``: the highest-confidence (kept) anchor per window and clip.
LOSS_REDUCTIONS = ("mean", "top")
#: Anchors the loss scores: ``"all"`` (the paper) or ``"person"``: those whose cell overlaps the person's box
#: (:func:`anchors_on_boxes`).
LOSS_ANCHORS = ("all", "person")
_OBJ = 4
_CLS0 = 5


class AdversarialLoss(NamedTuple):
    """Loss and its components (0-dim tensors; call ``.item()`` to log).

    Attributes:
        total: ``lambda_obj * obj + lambda_cls * cls`` (differentiable; backpropagate this).
        obj: mean objectness ``L_obj`` over the scored anchors.
        cls: mean target-class probability ``L_cls`` over the scored anchors.
        num_anchors: number of scored anchors (all of them unless ``boxes`` restricts it; with
            ``reduction="top"`` the number of windows x clips that had a kept anchor), int64 0-dim tensor.
    """

    total: "torch.Tensor"
    obj: "torch.Tensor"
    cls: "torch.Tensor"
    num_anchors: "torch.Tensor"


def _stack_windows(decoded) -> "torch.Tensor":
    if isinstance(decoded, torch.Tensor):
        if decoded.ndim < 2:
            raise ShapeError(f"decoded must be [..., A, 5 + nc], got {tuple(decoded.shape)}")
        return decoded
    windows = list(decoded)
    if not windows:
        raise ShapeError("decoded is an empty sequence of windows")
    shapes = {tuple(w.shape) for w in windows}
    if len(shapes) != 1:
        raise ShapeError(f"all windows must have the same [B, A, 5 + nc] shape, got {sorted(shapes)}")
    return torch.stack(windows, dim=0)


def anchors_near_boxes(decoded: "torch.Tensor", boxes, margin_px: float = 0.0) -> "torch.Tensor":
    """Anchors whose predicted centre lies inside the (grown) person box of their window and batch item.

    Args:
        decoded: float tensor [..., A, 5 + nc], (cx, cy) in input pixels; leading dims ``[...]`` e.g. [W, B].
        boxes: float [..., 4] ``(x0, y0, x1, y1)`` in input pixels, broadcastable to ``decoded.shape[:-2]``
            (e.g. [B, 4] for one box per clip, [W, B, 4] per window); NaN rows = no person (no anchor kept).
        margin_px: grow each box by this many pixels on every side.

    Returns:
        bool tensor [..., A] (no gradient).

    Raises:
        ShapeError: boxes do not broadcast; ValueError: margin_px < 0.
    """
    if margin_px < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    boxes = torch.as_tensor(boxes, dtype=decoded.dtype, device=decoded.device).detach()
    if boxes.shape[-1] != 4:
        raise ShapeError(f"boxes must be [..., 4] (x0, y0, x1, y1), got {tuple(boxes.shape)}")
    lead = decoded.shape[:-2]
    try:
        boxes = torch.broadcast_to(boxes, tuple(lead) + (4,))
    except RuntimeError:
        raise ShapeError(f"boxes {tuple(boxes.shape)} do not broadcast to {tuple(lead) + (4,)}") from None
    cx = decoded[..., 0].detach()
    cy = decoded[..., 1].detach()
    x0, y0, x1, y1 = (boxes[..., k, None] for k in range(4))
    m = float(margin_px)
    return (cx >= x0 - m) & (cx <= x1 + m) & (cy >= y0 - m) & (cy <= y1 + m)  # NaN compares False


def anchor_cells(in_hw: tuple[int, int], strides: Sequence[int], device=None) -> "torch.Tensor":
    """The image cell of every anchor of the detector's decoded output, in its order.

    YOLOX (RVT's head) has one anchor per cell of each FPN level: level ``s`` covers the (padded) input with
    ``(H / s) x (W / s)`` cells of ``s x s`` px, levels in stride order, cells row-major
    (:class:`~davis_rig.models.rvt.head.YOLOXHead`).

    Args:
        in_hw: the network input (height, width), px (``detector.config.in_res_hw``).
        strides: FPN strides (``detector.config.head_strides``, e.g. 8, 16, 32).
        device: torch device of the result.

    Returns:
        float32 tensor [A, 4] ``(x0, y0, x1, y1)`` px, A = sum over levels of ``(H // s) * (W // s)``.
    """
    cells = []
    for s in strides:
        rows, cols = int(in_hw[0]) // int(s), int(in_hw[1]) // int(s)
        y, x = torch.meshgrid(torch.arange(rows, device=device), torch.arange(cols, device=device), indexing="ij")
        x0, y0 = x.reshape(-1).float() * s, y.reshape(-1).float() * s
        cells.append(torch.stack([x0, y0, x0 + s, y0 + s], dim=1))
    return torch.cat(cells, dim=0)


def anchors_on_boxes(cells: "torch.Tensor", boxes) -> "torch.Tensor":
    """Anchors whose cell overlaps the person's box (a shared area > 0).

    Args:
        cells: float tensor [A, 4] anchor cells ``(x0, y0, x1, y1)`` px (:func:`anchor_cells`).
        boxes: float [..., 4] person boxes ``(x0, y0, x1, y1)`` px (e.g. [W, B, 4]); NaN rows = no person.

    Returns:
        bool tensor [..., A] (no anchor for a NaN box).
    """
    boxes = torch.as_tensor(boxes, dtype=cells.dtype, device=cells.device)
    if boxes.shape[-1] != 4 or cells.ndim != 2 or cells.shape[-1] != 4:
        raise ShapeError(f"need cells [A, 4] and boxes [..., 4], got {tuple(cells.shape)} and {tuple(boxes.shape)}")
    b = boxes[..., None, :]
    return (cells[:, 0] < b[..., 2]) & (cells[:, 2] > b[..., 0]) & (cells[:, 1] < b[..., 3]) & (cells[:, 3] > b[..., 1])


def adversarial_loss(
    decoded: "torch.Tensor | Sequence[torch.Tensor]",
    lambda_obj: float = DEFAULT_LAMBDA,
    lambda_cls: float = DEFAULT_LAMBDA,
    class_id: int = PEDESTRIAN_CLASS_ID,
    boxes=None,
    box_margin_px: float = 0.0,
    reduction: str = "mean",
    anchor_mask=None,
) -> AdversarialLoss:
    """``L_adv = lambda_obj * mean(obj) + lambda_cls * mean(p_class)`` over all anchors of all windows.

    Args:
        decoded: the detector's decoded output of every window of the sequence: a list of float tensors
            [B, A, 5 + nc] (one per window) or one tensor [..., A, 5 + nc] (e.g. [W, B, A, 5 + nc]).
            Columns: cx, cy, w, h (input px), objectness probability, class probabilities.
        lambda_obj: weight lambda_1 of the objectness term (paper 1e4).
        lambda_cls: weight lambda_2 of the class term (paper 1e4).
        class_id: attacked class (Gen1: 1 = pedestrian).
        boxes: optional person boxes ``(x0, y0, x1, y1)`` in input px, broadcastable to the leading dims of
            the stacked decoded tensor ([W, B] for a list of windows): only anchors whose predicted centre lies
            inside the box grown by ``box_margin_px`` are scored (see :func:`anchors_near_boxes`). ``None``
            (paper): every anchor.
        box_margin_px: margin added around each box (px).
        reduction: ``"mean"`` (paper): means over all scored anchors. ``"top"``: per leading index (window,
            clip) the scored anchor with the largest ``obj * p_class``; ``L_obj`` and ``L_cls`` are the means of
            that anchor's objectness and class probability over the windows and clips that have one.
        anchor_mask: optional bool [..., A] (the leading dims of the stacked decoded tensor): score only these
            anchors (e.g. :func:`anchors_on_boxes`); combined with ``boxes`` when both are given.

    Returns:
        :class:`AdversarialLoss`; with ``boxes`` (or ``anchor_mask``) and no anchor kept, obj = cls = total = 0 (still a
        differentiable tensor, zero gradient).

    Raises:
        ShapeError: decoded has too few columns or windows of different shapes; ValueError: unknown reduction.
    """
    if reduction not in LOSS_REDUCTIONS:
        raise ValueError(f"reduction must be one of {LOSS_REDUCTIONS}, got {reduction!r}")
    x = _stack_windows(decoded)
    if not torch.is_floating_point(x):
        raise ShapeError(f"decoded must be a floating-point tensor, got {x.dtype}")
    if int(class_id) < 0 or x.shape[-1] < _CLS0 + int(class_id) + 1:
        raise ShapeError(f"decoded must have >= {_CLS0 + int(class_id) + 1} columns for class {class_id}, "
                         f"got shape {tuple(x.shape)}")
    obj = x[..., _OBJ]
    cls = x[..., _CLS0 + int(class_id)]
    keep = None if boxes is None else anchors_near_boxes(x, boxes, box_margin_px)
    if anchor_mask is not None:
        mask = torch.as_tensor(anchor_mask, dtype=torch.bool, device=x.device)
        if mask.shape != obj.shape:
            raise ShapeError(f"anchor_mask must be {tuple(obj.shape)}, got {tuple(mask.shape)}")
        keep = mask if keep is None else keep & mask
    if reduction == "top":
        keep = torch.ones_like(obj, dtype=torch.bool) if keep is None else keep
        score = torch.where(keep, (obj * cls).detach(), x.new_full((), -1.0))  # a fill: no host copy (CUDA graphs)
        top = score.argmax(dim=-1, keepdim=True)  # [..., 1]
        has_anchor = keep.any(dim=-1).to(x.dtype)  # [...]
        count = has_anchor.sum()
        n = count.to(torch.int64)
        denominator = count.clamp(min=1.0)
        obj_mean = (obj.gather(-1, top).squeeze(-1) * has_anchor).sum() / denominator
        cls_mean = (cls.gather(-1, top).squeeze(-1) * has_anchor).sum() / denominator
    elif keep is None:
        n = torch.full((), obj.numel(), dtype=torch.int64, device=x.device)  # a fill: no host copy (CUDA graphs)
        obj_mean = obj.mean()
        cls_mean = cls.mean()
    else:
        keep = keep.to(x.dtype)
        count = keep.sum()
        n = count.to(torch.int64)
        denominator = count.clamp(min=1.0)
        obj_mean = (obj * keep).sum() / denominator
        cls_mean = (cls * keep).sum() / denominator
    total = float(lambda_obj) * obj_mean + float(lambda_cls) * cls_mean
    return AdversarialLoss(total=total, obj=obj_mean, cls=cls_mean, num_anchors=n)
