"""COCO AP with the RVT / Prophesee Gen1 evaluation protocol (box filters, label-time matching, COCOeval).

Reproduces ``utils/evaluation/prophesee`` of RVT (``evaluation.py::evaluate_list``, ``io/box_filtering.py``,
``metrics/coco_eval.py``):

* the same filter on labels **and** detections: keep boxes with ``t > skip_first_us`` (relative to the start of
  the sequence; RVT: 0.5 s), ``w² + h² ≥ 30²``, ``w ≥ 10``, ``h ≥ 10`` (px), computed in float32 on the
  boxes' float32 fields like the official numpy code (a box on a float32 rounding boundary is kept or dropped
  exactly as there);
* one COCO "image" per distinct label timestamp; the detections of an image are those with
  ``|t_det − t_label| ≤ time_tol_us`` (50 ms); frames without labels are not images (their detections are ignored);
* categories ``id = class_id + 1``; label and detection areas ``w · h`` as float32 products (the official code
  multiplies the float32 fields; the area decides the small/medium/large ranges); ``iscrowd`` false; the
  ranking score is the box's ``class_confidence`` (RVT writes the class probability alone, not obj · class);
* the standard COCOeval 'bbox' (IoU .50:.05:.95, 101 recall points, 100 detections per image and class, area
  ranges small/medium/large) computed by ``faster-coco-eval`` (same numbers as ``pycocotools``, several times
  faster; ``backend="pycocotools"`` runs the original, used by the tests to cross-check).

* no detection at all, or no label left after the filter (then there are no images, so no detections either):
  0.0 for every key, the official early return.

Differences to the official code, on purpose: ``category`` restricts the evaluation to one class (the physical
evaluation reports the pedestrian AP; with pedestrian-only labels this equals the official all-class mean,
because COCOeval leaves classes without labels out of the mean); an area range without any label (COCOeval's
-1, e.g. ``AP_S`` when no label is small) is NaN here, so that it can never be averaged as a score; timestamps
must be sorted like the official code asserts (checked here, not asserted).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence
from enum import StrEnum
from typing import Final

import numpy as np

from davis_rig.errors import FormatError, MissingDependencyError
from davis_rig.types import BBOX_DTYPE, GEN1_CLASSES, PEDESTRIAN_CLASS_ID, RVT_HW

__all__ = [
    "AP_KEYS",
    "CocoBackend",
    "MIN_DIAG_PX",
    "MIN_SIDE_PX",
    "SKIP_FIRST_US",
    "TIME_TOL_US",
    "coco_ap",
    "detections_to_boxes",
    "evaluate_detection",
    "filter_boxes",
    "match_times",
]

#: Prophesee box filter (``io/box_filtering.py``): minimum diagonal and minimum side, px.
MIN_DIAG_PX: Final = 30
MIN_SIDE_PX: Final = 10
#: RVT's ``evaluate_list`` skips boxes with ``t <= 500 000 µs`` (the first 0.5 s of every sequence).
SKIP_FIRST_US: Final = 500_000
#: Detections within ±50 ms of a label timestamp belong to that label's image (``time_tol``).
TIME_TOL_US: Final = 50_000
#: Keys of the result, in COCOeval's ``stats`` order.
AP_KEYS: Final = ("AP", "AP_50", "AP_75", "AP_S", "AP_M", "AP_L")


class CocoBackend(StrEnum):
    """The COCO evaluation code that computes AP: ``faster_coco_eval`` (C++, the default) or the original
    ``pycocotools``."""

    FASTER_COCO_EVAL = "faster_coco_eval"
    PYCOCOTOOLS = "pycocotools"


def _check_boxes(name: str, boxes) -> np.ndarray:
    if not isinstance(boxes, np.ndarray) or boxes.dtype.names is None:
        raise FormatError(f"{name}: expected a structured BBOX_DTYPE array, got {type(boxes).__name__}")
    missing = {"t", "x", "y", "w", "h", "class_id", "class_confidence"} - set(boxes.dtype.names)
    if missing:
        raise FormatError(f"{name}: missing fields {sorted(missing)} (expected BBOX_DTYPE {BBOX_DTYPE.names})")
    if boxes.ndim != 1:
        raise FormatError(f"{name}: expected shape [B], got {boxes.shape}")
    return boxes


def detections_to_boxes(detections, t_us: int, track_id: int = 0) -> np.ndarray:
    """Turn RVT post-processed detections into Prophesee boxes (RVT's ``to_prophesee``).

    Args:
        detections: float32 [K, 7] rows ``(x1, y1, x2, y2, obj, class_conf, class_id)`` (RVT postprocess
            output), or ``None`` (no detections).
        t_us: timestamp given to every box, µs (the label time the detections are evaluated at).
        track_id: value of the ``track_id`` field.

    Returns:
        BBOX_DTYPE [K]: ``x = x1, y = y1, w = x2 − x1, h = y2 − y1`` (not clipped), ``class_confidence =
        class_conf`` (column 5, not obj · class_conf, as RVT does).

    Raises:
        FormatError: ``detections`` is not [K, 7].
    """
    if detections is None:
        return np.zeros(0, BBOX_DTYPE)
    det = np.asarray(detections, dtype=np.float32)
    if det.ndim != 2 or det.shape[1] < 7:
        raise FormatError(f"detections: expected [K, 7] (x1, y1, x2, y2, obj, class_conf, class_id), got {det.shape}")
    out = np.zeros(det.shape[0], BBOX_DTYPE)
    out["t"] = int(t_us)
    out["x"] = det[:, 0]
    out["y"] = det[:, 1]
    out["w"] = det[:, 2] - det[:, 0]
    out["h"] = det[:, 3] - det[:, 1]
    out["class_id"] = det[:, 6].astype(np.uint8)
    out["class_confidence"] = det[:, 5]
    out["track_id"] = track_id
    return out


def filter_boxes(
    boxes: np.ndarray,
    *,
    skip_until_us: int | None = None,
    min_diag_px: float = MIN_DIAG_PX,
    min_side_px: float = MIN_SIDE_PX,
) -> np.ndarray:
    """The Prophesee box filter (``filter_boxes`` of RVT's evaluation), as a new array.

    Args:
        boxes: BBOX_DTYPE [B].
        skip_until_us: drop boxes with ``t <= skip_until_us`` (device µs); ``None`` keeps all times.
        min_diag_px: keep ``w² + h² ≥ min_diag_px²``, the left side in float32 arithmetic (as the official code
            computes it on the float32 fields), the bound ``min_diag_px²`` rounded to float32.
        min_side_px: keep ``w ≥ min_side_px`` and ``h ≥ min_side_px`` (float32 comparison).

    Returns:
        The kept boxes, same order (BBOX_DTYPE [B' ≤ B]).

    Raises:
        FormatError: ``boxes`` is not a box array.
    """
    boxes = _check_boxes("boxes", boxes)
    w = boxes["w"].astype(np.float32)
    h = boxes["h"].astype(np.float32)
    side = np.float32(min_side_px)
    keep = (w * w + h * h >= np.float32(float(min_diag_px) ** 2)) & (w >= side) & (h >= side)
    if skip_until_us is not None:
        keep &= boxes["t"].astype(np.int64) > int(skip_until_us)
    return boxes[keep].copy()


def _sorted_times(name: str, boxes: np.ndarray) -> np.ndarray:
    t = boxes["t"].astype(np.int64)
    if t.size > 1 and np.any(t[1:] < t[:-1]):
        raise FormatError(f"{name}: timestamps must be sorted (non-decreasing) like RVT's evaluation asserts")
    return t


def match_times(gt_boxes: np.ndarray, dt_boxes: np.ndarray, time_tol_us: int = TIME_TOL_US):
    """Group labels and detections per label timestamp (Prophesee ``_match_times``, vectorised).

    Args:
        gt_boxes: labels, BBOX_DTYPE [G], sorted by ``t``.
        dt_boxes: detections, BBOX_DTYPE [D], sorted by ``t``.
        time_tol_us: detections with ``t_label − tol ≤ t ≤ t_label + tol`` belong to the label's image, µs.

    Returns:
        ``(timestamps int64 [I], gt list of I arrays, dt list of I arrays)``, one entry per distinct label time.

    Raises:
        FormatError: unsorted timestamps or non-box arrays.
    """
    gt_t = _sorted_times("labels", _check_boxes("labels", gt_boxes))
    dt_t = _sorted_times("detections", _check_boxes("detections", dt_boxes))
    all_ts = np.unique(gt_t)
    gt_lo = np.searchsorted(gt_t, all_ts, side="left")
    gt_hi = np.searchsorted(gt_t, all_ts, side="right")
    dt_lo = np.searchsorted(dt_t, all_ts - int(time_tol_us), side="left")
    dt_hi = np.searchsorted(dt_t, all_ts + int(time_tol_us), side="right")
    gts = [gt_boxes[a:b] for a, b in zip(gt_lo.tolist(), gt_hi.tolist())]
    dts = [dt_boxes[a:b] for a, b in zip(dt_lo.tolist(), dt_hi.tolist())]
    return all_ts, gts, dts


def _coco_classes(backend: str):
    if backend == CocoBackend.FASTER_COCO_EVAL:
        try:
            from faster_coco_eval import COCO, COCOeval_faster
        except ImportError as exc:
            raise MissingDependencyError(
                "AP needs faster-coco-eval: pip install faster-coco-eval (a davis_rig dependency)"
            ) from exc
        return COCO, COCOeval_faster
    if backend == CocoBackend.PYCOCOTOOLS:
        try:
            from pycocotools.coco import COCO
            from pycocotools.cocoeval import COCOeval
        except ImportError as exc:
            raise MissingDependencyError("backend='pycocotools' needs pycocotools: pip install pycocotools") from exc
        return COCO, COCOeval
    raise ValueError(f"backend: expected {' or '.join(repr(b.value) for b in CocoBackend)}, got {backend!r}")


def coco_ap(
    gt_per_image: Sequence[np.ndarray],
    dt_per_image: Sequence[np.ndarray],
    *,
    classes: Sequence[str] = tuple(GEN1_CLASSES.values()),
    category: int | None = PEDESTRIAN_CLASS_ID,
    frame_hw: tuple[int, int] = RVT_HW,
    backend: str = CocoBackend.FASTER_COCO_EVAL,
) -> dict[str, float]:
    """COCO 'bbox' AP of per-image labels and detections (RVT's ``_coco_eval``).

    Args:
        gt_per_image: one BBOX_DTYPE array per image (labels).
        dt_per_image: one BBOX_DTYPE array per image (detections; ``class_confidence`` is the ranking score).
        classes: class names; COCO category id = index + 1.
        category: evaluate only this class id (default pedestrian); ``None`` = mean over classes like RVT.
        frame_hw: image (height, width), px (metadata only).
        backend: ``"faster_coco_eval"`` or ``"pycocotools"``.

    Returns:
        ``{"AP", "AP_50", "AP_75", "AP_S", "AP_M", "AP_L"}`` as floats in [0, 1]: 0.0 everywhere when there is
        no detection or no label at all (RVT's early return: without labels the official evaluation has no
        image, hence no detection), NaN for an area range without labels (COCOeval's -1).

    Raises:
        MissingDependencyError: the chosen backend is not installed.
        FormatError: different numbers of label and detection images, or non-box arrays.
    """
    if len(gt_per_image) != len(dt_per_image):
        raise FormatError(f"coco_ap: {len(gt_per_image)} label images but {len(dt_per_image)} detection images")
    num_gt = sum(len(_check_boxes("labels", g)) for g in gt_per_image)
    num_dt = sum(len(_check_boxes("detections", d)) for d in dt_per_image)
    if num_gt == 0 or num_dt == 0:
        return {key: 0.0 for key in AP_KEYS}
    COCO, COCOeval = _coco_classes(backend)
    height, width = frame_hw
    images, annotations, results = [], [], []
    for index, (gt, dt) in enumerate(zip(gt_per_image, dt_per_image), start=1):
        images.append({"id": index, "height": int(height), "width": int(width), "file_name": "n.a",
                       "date_captured": "2019", "license": 1, "url": ""})
        areas = _areas_float32(gt)
        for box, area in zip(gt.tolist(), areas.tolist()):  # tolist: Python scalars, in BBOX_DTYPE field order
            _, x, y, w, h, class_id = box[:6]
            annotations.append({"area": area, "iscrowd": False, "image_id": index,
                                "bbox": [float(x), float(y), float(w), float(h)],
                                "category_id": int(class_id) + 1, "id": len(annotations) + 1})
        for box in dt.tolist():
            _, x, y, w, h, class_id, score = box[:7]
            results.append({"image_id": index, "category_id": int(class_id) + 1, "score": float(score),
                            "bbox": [float(x), float(y), float(w), float(h)]})
    dataset = {"info": {}, "licenses": [], "type": "instances", "images": images, "annotations": annotations,
               "categories": [{"id": i + 1, "name": name, "supercategory": "none"} for i, name in enumerate(classes)]}
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = dataset
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(results)
        for ann in coco_dt.dataset["annotations"]:  # loadRes multiplies our float64 w, h; the official code's are
            _, _, w, h = ann["bbox"]  # float32 fields, so its detection areas are float32 products
            ann["area"] = float(np.float32(w) * np.float32(h))
        coco_dt.createIndex()  # index the patched areas (an index may hold copies)
        evaluator = COCOeval(coco_gt, coco_dt, "bbox")
        evaluator.params.imgIds = np.arange(1, len(images) + 1, dtype=int)
        if category is not None:
            evaluator.params.catIds = [int(category) + 1]
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    stats = np.asarray(evaluator.stats[: len(AP_KEYS)], dtype=np.float64)
    return {key: (float(v) if v >= 0 else float("nan")) for key, v in zip(AP_KEYS, stats)}


def _areas_float32(boxes: np.ndarray) -> np.ndarray:
    """``w · h`` of BBOX_DTYPE boxes as a float32 product (the official code multiplies the float32 fields)."""
    return boxes["w"].astype(np.float32) * boxes["h"].astype(np.float32)


def evaluate_detection(
    gt_boxes: np.ndarray,
    dt_boxes: np.ndarray,
    *,
    t_start_us: int = 0,
    skip_first_us: int | None = SKIP_FIRST_US,
    min_diag_px: float = MIN_DIAG_PX,
    min_side_px: float = MIN_SIDE_PX,
    time_tol_us: int = TIME_TOL_US,
    category: int | None = PEDESTRIAN_CLASS_ID,
    frame_hw: tuple[int, int] = RVT_HW,
    backend: str = CocoBackend.FASTER_COCO_EVAL,
) -> dict[str, float]:
    """RVT's ``evaluate_list`` for one sequence: filter labels and detections, match times, COCO AP.

    Args:
        gt_boxes: labels, BBOX_DTYPE [G], sorted by ``t`` (device µs).
        dt_boxes: detections, BBOX_DTYPE [D], sorted by ``t``.
        t_start_us: start of the sequence, device µs (the skip is relative to it).
        skip_first_us: drop boxes with ``t − t_start_us <= skip_first_us``; ``None`` keeps everything.
        min_diag_px, min_side_px: the size filter (see :func:`filter_boxes`).
        time_tol_us: label-time matching tolerance, µs.
        category, frame_hw, backend: see :func:`coco_ap`.

    Returns:
        The AP dict of :func:`coco_ap` plus ``num_images``, ``num_labels``, ``num_detections`` (after filters).
    """
    skip = None if skip_first_us is None else int(t_start_us) + int(skip_first_us)
    gt = filter_boxes(gt_boxes, skip_until_us=skip, min_diag_px=min_diag_px, min_side_px=min_side_px)
    dt = filter_boxes(dt_boxes, skip_until_us=skip, min_diag_px=min_diag_px, min_side_px=min_side_px)
    _, gts, dts = match_times(gt, dt, time_tol_us)
    result: dict[str, float] = dict(coco_ap(gts, dts, category=category, frame_hw=frame_hw, backend=backend))
    result.update(num_images=len(gts), num_labels=int(sum(len(g) for g in gts)),
                  num_detections=int(sum(len(d) for d in dts)))
    return result
