"""COCO AP with the RVT/Prophesee protocol: known answers, filters, time matching, pycocotools identity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.metrics.ap import (
    AP_KEYS,
    coco_ap,
    detections_to_boxes,
    evaluate_detection,
    filter_boxes,
    match_times,
)
from davis_rig.types import BBOX_DTYPE


def boxes(rows, t=0, class_id=1):
    """BBOX_DTYPE from (x, y, w, h[, score]) rows."""
    out = np.zeros(len(rows), BBOX_DTYPE)
    for i, row in enumerate(rows):
        out[i]["t"] = t
        out[i]["x"], out[i]["y"], out[i]["w"], out[i]["h"] = row[:4]
        out[i]["class_confidence"] = row[4] if len(row) > 4 else 1.0
        out[i]["class_id"] = class_id
    return out


GT = [boxes([(50, 50, 100, 100)], t=i) for i in range(5)]


def test_perfect_detector_has_ap_one():
    dts = [boxes([(50, 50, 100, 100, 0.9)], t=i) for i in range(5)]
    ap = coco_ap(GT, dts)
    assert ap["AP"] == pytest.approx(1.0) and ap["AP_50"] == pytest.approx(1.0) and ap["AP_75"] == pytest.approx(1.0)
    assert ap["AP_L"] == pytest.approx(1.0) and math.isnan(ap["AP_S"])  # no small labels: undefined, not 0


def test_no_detections_or_no_labels_give_ap_zero_like_the_official_code():
    assert coco_ap(GT, [np.zeros(0, BBOX_DTYPE)] * 5) == {key: 0.0 for key in AP_KEYS}
    assert coco_ap([np.zeros(0, BBOX_DTYPE)], [boxes([(0, 0, 50, 50)])]) == {key: 0.0 for key in AP_KEYS}
    assert coco_ap([], []) == {key: 0.0 for key in AP_KEYS}


@pytest.mark.parametrize("shift_px, ap, ap50, ap75", [(10, 0.7, 1.0, 1.0), (30, 0.1, 1.0, 0.0), (70, 0.0, 0.0, 0.0)])
def test_shifted_boxes_match_only_below_their_iou(shift_px, ap, ap50, ap75):
    # Same-size boxes shifted by d: IoU = (100 - d) / (100 + d): 0.818 (7 of 10 thresholds), 0.538 (1), 0.176 (0).
    dts = [boxes([(50 + shift_px, 50, 100, 100, 0.9)], t=i) for i in range(5)]
    result = coco_ap(GT, dts)
    assert result["AP"] == pytest.approx(ap) and result["AP_50"] == pytest.approx(ap50)
    assert result["AP_75"] == pytest.approx(ap75)


def test_false_positive_ranked_above_the_true_one_halves_precision():
    # One image: a wrong box scored 0.9 above the right one scored 0.5 -> precision 1/2 at recall 1.
    dts = [boxes([(200, 150, 60, 60, 0.9), (50, 50, 100, 100, 0.5)])]
    assert coco_ap(GT[:1], dts)["AP"] == pytest.approx(0.5)
    dts = [boxes([(200, 150, 60, 60, 0.4), (50, 50, 100, 100, 0.5)])]  # ranked below: no effect
    assert coco_ap(GT[:1], dts)["AP"] == pytest.approx(1.0)


def test_category_restricts_to_pedestrians_and_none_averages_over_labelled_classes():
    gts = [np.concatenate([boxes([(50, 50, 100, 100)]), boxes([(10, 10, 40, 40)], class_id=0)])]
    dts = [np.concatenate([boxes([(50, 50, 100, 100, 0.9)]), boxes([(150, 150, 40, 40, 0.9)], class_id=0)])]
    assert coco_ap(gts, dts)["AP"] == pytest.approx(1.0)  # pedestrian only
    assert coco_ap(gts, dts, category=None)["AP"] == pytest.approx(0.5)  # car AP 0, pedestrian 1


def random_case(rng, n_images=30):
    gts, dts = [], []
    for i in range(n_images):
        n = int(rng.integers(0, 5))
        g = np.zeros(n, BBOX_DTYPE)
        g["t"] = i
        g["x"], g["y"] = rng.uniform(0, 250, n), rng.uniform(0, 190, n)
        g["w"], g["h"] = rng.uniform(5, 120, n), rng.uniform(5, 120, n)
        g["class_id"] = rng.integers(0, 2, n)
        d = np.concatenate([g[rng.random(n) < 0.8], g[:0]])
        d = d.copy()
        d["x"] += rng.normal(0, 6, len(d))
        d["w"] *= rng.uniform(0.8, 1.2, len(d))
        extra = np.zeros(int(rng.integers(0, 6)), BBOX_DTYPE)
        extra["t"] = i
        extra["x"], extra["y"] = rng.uniform(0, 250, len(extra)), rng.uniform(0, 190, len(extra))
        extra["w"], extra["h"] = rng.uniform(5, 120, len(extra)), rng.uniform(5, 120, len(extra))
        extra["class_id"] = rng.integers(0, 2, len(extra))
        d = np.concatenate([d, extra])
        d["class_confidence"] = rng.random(len(d)).astype(np.float32)
        gts.append(g)
        dts.append(d)
    return gts, dts


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("category", [1, None])
def test_faster_coco_eval_equals_pycocotools_on_random_data(seed, category):
    pytest.importorskip("pycocotools", reason="pycocotools (test extra) is the reference for the cross-check")
    gts, dts = random_case(np.random.default_rng(seed))
    fast = coco_ap(gts, dts, category=category)
    reference = coco_ap(gts, dts, category=category, backend="pycocotools")
    assert fast.keys() == reference.keys()
    for key in AP_KEYS:
        assert (math.isnan(fast[key]) and math.isnan(reference[key])) or fast[key] == pytest.approx(
            reference[key], abs=1e-12), key
    assert 0 < fast["AP"] < 1


def test_filter_boxes_prophesee_bounds():
    b = boxes([(0, 0, 10, 30), (0, 0, 9.9, 40), (0, 0, 21.2, 21.2), (0, 0, 21.22, 21.22), (0, 0, 30, 9)])
    kept = filter_boxes(b)
    assert kept["w"].tolist() == pytest.approx([10, 21.22])  # diag >= 30 and sides >= 10
    timed = boxes([(0, 0, 40, 40)] * 3)
    timed["t"] = [500_000, 500_001, 900_000]
    assert filter_boxes(timed, skip_until_us=500_000)["t"].tolist() == [500_001, 900_000]  # strictly after


def test_match_times_tolerance_is_inclusive_and_images_follow_label_times():
    gt = boxes([(0, 0, 40, 40)] * 3)
    gt["t"] = [100_000, 100_000, 300_000]
    dt = boxes([(0, 0, 40, 40)] * 5)
    dt["t"] = [49_999, 50_000, 150_000, 150_001, 300_000]
    times, gts, dts = match_times(gt, dt, time_tol_us=50_000)
    assert times.tolist() == [100_000, 300_000]
    assert [len(g) for g in gts] == [2, 1]
    assert [d["t"].tolist() for d in dts] == [[50_000, 150_000], [300_000]]
    with pytest.raises(FormatError, match="sorted"):
        match_times(gt[::-1].copy(), dt)
    with pytest.raises(FormatError, match="BBOX_DTYPE"):
        match_times(np.zeros((3, 4)), dt)


def test_detections_to_boxes_uses_class_probability_as_score():
    det = np.array([[10, 20, 50, 100, 0.5, 0.8, 1]], np.float32)
    b = detections_to_boxes(det, 1234)
    assert b.tolist() == [(1234, 10.0, 20.0, 40.0, 80.0, 1, pytest.approx(0.8), 0)]
    assert len(detections_to_boxes(None, 0)) == 0
    with pytest.raises(FormatError):
        detections_to_boxes(np.zeros((2, 6)), 0)


def test_evaluate_detection_skips_the_first_half_second_and_counts():
    gt = np.concatenate([boxes([(50, 50, 100, 100)], t=t) for t in (100_000, 600_000, 700_000)])
    dt = np.concatenate([boxes([(50, 50, 100, 100, 0.9)], t=600_000), boxes([(50, 50, 100, 100, 0.9)], t=700_000)])
    result = evaluate_detection(gt, dt, t_start_us=0, time_tol_us=0)
    assert result["AP"] == pytest.approx(1.0) and result["num_images"] == 2 and result["num_labels"] == 2
    kept_all = evaluate_detection(gt, dt, skip_first_us=None, time_tol_us=0)
    assert kept_all["num_images"] == 3 and kept_all["AP"] == pytest.approx(2 / 3, abs=0.01)  # one label missed
