"""AP equals the official RVT / Prophesee evaluation on the same inputs, float32 rounding boundaries included.

The reference below follows the official pipeline step by step (RVT ``utils/evaluation/prophesee``:
``evaluation.py::evaluate_list`` -> ``io/box_filtering.py::filter_boxes`` -> ``metrics/coco_eval.py``), written
here in plain numpy + pycocotools: the size filter is evaluated on the boxes' float32 fields with numpy's own
promotion, label areas are ``float(w * h)`` of float32 scalars, detections go to ``loadRes`` as float32 scalars
(so COCO's result areas are float32 products), COCOeval over all classes, and the early return of 0.0 when there
is no detection.
"""

from __future__ import annotations

import contextlib
import io
import math

import numpy as np
import pytest

from davis_rig.metrics.ap import AP_KEYS, evaluate_detection, filter_boxes
from davis_rig.types import BBOX_DTYPE

pytest.importorskip("pycocotools", reason="pycocotools (test extra) runs the reference evaluation")

#: float32 side whose squared diagonal is >= 30² in float32 but < 30² in float64 (w = h = 21.2132034...).
BOUNDARY_SIDE = np.float32(21.21320343017578)
#: float32 sides whose product rounds to exactly 32² = 1024 in float32 (a small box) but is > 1024 in float64.
SMALL_BOUNDARY_WH = (np.float32(39.10885238647461), np.float32(26.183330535888672))


def _official_filter(boxes, skip_ts=500_000, min_box_diag=30, min_box_side=10):
    ts, width, height = boxes["t"], boxes["w"], boxes["h"]
    diag_square = width ** 2 + height ** 2
    mask = (ts > skip_ts) * (diag_square >= min_box_diag ** 2) * (width >= min_box_side) * (height >= min_box_side)
    return boxes[mask]


def _official_windows(gt, dt, time_tol):
    all_ts = np.unique(gt["t"])
    windows_gt, windows_dt = [], []
    for ts in all_ts:
        windows_gt.append(gt[gt["t"] == ts])
        windows_dt.append(dt[(dt["t"] >= ts - time_tol) & (dt["t"] <= ts + time_tol)])
    return windows_gt, windows_dt


def official_ap(gt, dt, time_tol=50_000) -> dict[str, float]:
    """The official evaluation of one sequence (labels, detections: BBOX_DTYPE sorted by t)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    gts, dts = _official_windows(_official_filter(gt), _official_filter(dt), time_tol)
    if sum(d.size for d in dts) == 0:
        return {key: 0.0 for key in AP_KEYS}
    images, annotations, results = [], [], []
    for image_id, (g, d) in enumerate(zip(gts, dts), start=1):
        images.append({"date_captured": "2019", "file_name": "n.a", "id": image_id, "license": 1, "url": "",
                       "height": 240, "width": 304})
        for box in g:
            annotations.append({"area": float(box["w"] * box["h"]), "iscrowd": False, "image_id": image_id,
                                "bbox": [box["x"], box["y"], box["w"], box["h"]],
                                "category_id": int(box["class_id"]) + 1, "id": len(annotations) + 1})
        for box in d:
            results.append({"image_id": image_id, "category_id": int(box["class_id"]) + 1,
                            "score": float(box["class_confidence"]),
                            "bbox": [box["x"], box["y"], box["w"], box["h"]]})
    categories = [{"id": i + 1, "name": name, "supercategory": "none"} for i, name in enumerate(("car", "pedestrian"))]
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = {"info": {}, "licenses": [], "type": "instances", "images": images,
                           "annotations": annotations, "categories": categories}
        coco_gt.createIndex()
        evaluator = COCOeval(coco_gt, coco_gt.loadRes(results), "bbox")
        evaluator.params.imgIds = np.arange(1, len(gts) + 1, dtype=int)
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    return {key: float(v) for key, v in zip(AP_KEYS, evaluator.stats)}


def _boxes(rows) -> np.ndarray:
    """BBOX_DTYPE from (t, x, y, w, h, score) rows, pedestrians, sorted by t."""
    out = np.zeros(len(rows), BBOX_DTYPE)
    for i, (t, x, y, w, h, score) in enumerate(rows):
        out[i] = (t, x, y, w, h, 1, score, 0)
    return out[np.argsort(out["t"], kind="stable")]


def boundary_case() -> tuple[np.ndarray, np.ndarray]:
    """Labels and detections on the float32 boundaries of the size filter and of the small-area range.

    Ten label times 0.6..1.5 s: a 60x80 person found by a 0.9 detection at each; at the first six a boundary
    label (w = h = 21.2132034, kept by float32, dropped by float64) found only by a 0.95 detection of 21.5 px (a
    false positive when the label is dropped); at the last four a label of float32 area exactly 1024 (small)
    with a matching detection.
    """
    side = float(BOUNDARY_SIDE)
    w_small, h_small = (float(v) for v in SMALL_BOUNDARY_WH)
    gt, dt = [], []
    for k in range(10):
        t = 600_000 + 100_000 * k
        gt.append((t, 20, 30, 60, 80, 1.0))
        dt.append((t, 21, 30, 60, 80, 0.9))
        if k < 6:
            gt.append((t, 200, 100, side, side, 1.0))
            dt.append((t, 200, 100, 21.5, 21.5, 0.95))
        else:
            gt.append((t, 150, 150, w_small, h_small, 1.0))
            dt.append((t, 151, 150, w_small, h_small, 0.5 + 0.01 * k))
    return _boxes(gt), _boxes(dt)


def _same(ours: dict, official: dict) -> None:
    for key in AP_KEYS:
        if official[key] == -1:  # COCOeval: no label in this area range
            assert math.isnan(ours[key]), key
        else:
            assert ours[key] == pytest.approx(official[key], abs=1e-12), key


def test_the_boundaries_are_float32_boundaries():
    w = BOUNDARY_SIDE
    assert w * w + w * w >= np.float32(900) and float(w) ** 2 * 2 < 900
    w_small, h_small = SMALL_BOUNDARY_WH
    assert float(w_small * h_small) == 1024.0 and float(w_small) * float(h_small) > 1024.0


@pytest.mark.parametrize("backend", ["faster_coco_eval", "pycocotools"])
def test_boundary_boxes_score_exactly_as_the_official_evaluation(backend):
    gt, dt = boundary_case()
    official = official_ap(gt, dt)
    ours = evaluate_detection(gt, dt, time_tol_us=50_000, category=None, backend=backend)
    _same(ours, official)
    assert ours["num_labels"] == 20  # every boundary label kept, as in float32

    # the case bites: filtering in float64 (as before) drops the six boundary labels, and AP moves a lot
    wide = gt["w"].astype(np.float64) ** 2 + gt["h"].astype(np.float64) ** 2 >= 900
    wide_dt = dt["w"].astype(np.float64) ** 2 + dt["h"].astype(np.float64) ** 2 >= 900
    float64 = evaluate_detection(gt[wide], dt[wide_dt], time_tol_us=50_000, category=None, backend=backend)
    assert float64["num_labels"] == 14 and abs(float64["AP"] - ours["AP"]) > 0.05


def test_small_area_boundary_counts_as_small_like_the_official_evaluation():
    gt, dt = boundary_case()
    official = official_ap(gt, dt)
    ours = evaluate_detection(gt, dt, time_tol_us=50_000, category=None)
    assert official["AP_S"] != -1 and ours["AP_S"] == pytest.approx(official["AP_S"], abs=1e-12)
    assert float(np.float32(SMALL_BOUNDARY_WH[0]) * np.float32(SMALL_BOUNDARY_WH[1])) <= 32 ** 2


@pytest.mark.parametrize("seed", range(4))
def test_random_sequences_with_boundary_boxes_equal_the_official_evaluation(seed):
    rng = np.random.default_rng(seed)
    gt_rows, dt_rows = [], []
    side, (w_small, h_small) = float(BOUNDARY_SIDE), (float(v) for v in SMALL_BOUNDARY_WH)
    for t in range(50_000, 2_000_000, 50_000):
        for _ in range(int(rng.integers(0, 4))):
            kind = rng.integers(0, 4)
            w, h = ((side, side) if kind == 0 else (w_small, h_small) if kind == 1
                    else tuple(rng.uniform(5, 120, 2)))
            x, y = rng.uniform(0, 200), rng.uniform(0, 150)
            gt_rows.append((t, x, y, w, h, 1.0))
            if rng.random() < 0.7:
                dt_rows.append((t + int(rng.integers(-20_000, 20_000)), x + rng.normal(0, 3), y + rng.normal(0, 3),
                                w * rng.uniform(0.9, 1.1), h * rng.uniform(0.9, 1.1), rng.random()))
        for _ in range(int(rng.integers(0, 2))):
            dt_rows.append((t, *rng.uniform(0, 150, 2), *rng.uniform(8, 90, 2), rng.random()))
    gt, dt = _boxes(gt_rows), _boxes(dt_rows)
    _same(evaluate_detection(gt, dt, time_tol_us=50_000, category=None), official_ap(gt, dt))


def test_no_label_left_after_the_filter_gives_zero_like_the_official_evaluation():
    gt = _boxes([(100_000, 10, 10, 50, 50, 1.0), (700_000, 10, 10, 9, 40, 1.0)])  # too early / too thin
    dt = _boxes([(100_000, 10, 10, 50, 50, 0.9), (700_000, 10, 10, 50, 50, 0.9)])
    official = official_ap(gt, dt)
    ours = evaluate_detection(gt, dt, time_tol_us=50_000)
    assert official == {key: 0.0 for key in AP_KEYS}
    assert {key: ours[key] for key in AP_KEYS} == official and ours["num_labels"] == 0


def test_filter_keeps_the_float32_boundary_box():
    b = np.zeros(2, BBOX_DTYPE)
    b["w"] = b["h"] = [BOUNDARY_SIDE, np.nextafter(BOUNDARY_SIDE, np.float32(0))]
    assert filter_boxes(b)["w"].tolist() == [float(BOUNDARY_SIDE)]
    assert filter_boxes(b).tolist() == _official_filter(b, skip_ts=-1).tolist()
