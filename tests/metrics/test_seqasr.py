"""SeqASR: sequences of labelled windows, paper (any box) and strict (IoU >= 0.5) detection, known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from davis_rig.errors import FormatError, ShapeError
from davis_rig.metrics.seqasr import (
    box_iou,
    label_sequences,
    seq_asr,
    windows_detected,
    windows_with_labels,
)


def det(x1, y1, x2, y2, obj=0.9, cls=0.9, class_id=1):
    return np.array([[x1, y1, x2, y2, obj, cls, class_id]], np.float32)


def test_windows_with_labels_half_open_on_the_left():
    ends = np.array([50_000, 100_000, 150_000])
    assert windows_with_labels(ends, [50_000, 100_001], 50_000).tolist() == [True, False, True]
    assert windows_with_labels(ends, [], 50_000).tolist() == [False, False, False]


def test_label_sequences_cut_runs_non_overlapping_and_sliding():
    labelled = [1, 1, 1, 0, 1, 1, 1, 1, 1, 0, 1]
    assert label_sequences(labelled, 3).tolist() == [[0, 1, 2], [4, 5, 6]]  # remainders (7, 8) and (10) dropped
    assert label_sequences(labelled, 3, stride=1).tolist() == [[0, 1, 2], [4, 5, 6], [5, 6, 7], [6, 7, 8]]
    assert label_sequences([0, 0], 3).shape == (0, 3)
    with pytest.raises(ValueError):
        label_sequences(labelled, 0)


def test_perfect_detector_gives_zero_and_no_detections_give_one():
    sequences = label_sequences([True] * 20, 10)
    assert seq_asr(np.ones(20, bool), sequences).seq_asr == 0.0
    result = seq_asr(np.zeros(20, bool), sequences)
    assert (result.seq_asr, result.num_sequences, result.num_detected) == (1.0, 2, 0)
    assert math.isnan(seq_asr(np.ones(3, bool), np.zeros((0, 10), np.int64)).seq_asr)


def test_one_detected_window_is_enough_for_its_sequence():
    detected = np.zeros(30, bool)
    detected[[3, 25]] = True
    result = seq_asr(detected, label_sequences([True] * 30, 10))
    assert (result.num_sequences, result.num_detected) == (3, 2)
    assert result.seq_asr == pytest.approx(1 / 3)


def test_paper_mode_counts_any_pedestrian_box_strict_needs_iou():
    labels = [np.array([[100, 50, 180, 210]], np.float32)] * 3
    detections = [det(100, 50, 180, 210), det(0, 0, 40, 80), det(110, 50, 190, 210, class_id=0)]
    assert windows_detected(detections).tolist() == [True, True, False]  # a car is no pedestrian
    strict = windows_detected(detections, mode="strict", labels_xyxy=labels)
    assert strict.tolist() == [True, False, False]
    shifted = [det(140, 50, 220, 210)]  # IoU 40/120 = 1/3
    assert windows_detected(shifted, mode="strict", labels_xyxy=labels[:1]).tolist() == [False]
    assert windows_detected(shifted, mode="strict", labels_xyxy=labels[:1], iou_threshold=0.3).tolist() == [True]
    with pytest.raises(ShapeError):
        windows_detected(detections, mode="strict")
    with pytest.raises(ValueError):
        windows_detected(detections, mode="loose")


def _windows_detected_one_by_one(detections, mode, labels_xyxy, min_score, iou_threshold, class_id=1):
    """The definition window by window: a kept pedestrian box, and in strict mode IoU >= threshold with a label."""
    out = []
    for i, rows in enumerate(detections):
        found = False
        for row in [] if rows is None else rows:
            if int(row[6]) != class_id or (min_score is not None and row[4] * row[5] < np.float32(min_score)):
                continue
            if mode == "paper":
                found = True
            else:
                labels = np.asarray(labels_xyxy[i], np.float64).reshape(-1, 4)
                found |= bool(len(labels)) and bool((box_iou(row[None, :4], labels) >= iou_threshold).any())
        out.append(found)
    return out


@pytest.mark.parametrize("seed", range(4))
def test_windows_detected_equals_the_window_by_window_definition(seed):
    """Random windows (none, empty, several boxes of both classes; 0-3 labels each, some overlapping a box) give
    what the window-by-window definition gives, in both modes, with and without ``min_score``."""
    rng = np.random.default_rng(seed)
    detections, labels = [], []
    for _ in range(80):
        k = int(rng.integers(0, 5))
        corner = rng.uniform(0, 200, (k, 2))
        rows = np.concatenate([corner, corner + rng.uniform(5, 80, (k, 2)), rng.uniform(0, 1, (k, 2)),
                               rng.integers(0, 2, (k, 1))], axis=1).astype(np.float32)
        detections.append(None if k == 0 and rng.random() < 0.5 else rows)
        n_labels = int(rng.integers(0, 4))
        boxes = rng.uniform(0, 200, (n_labels, 4))
        boxes[:, 2:] = boxes[:, :2] + rng.uniform(5, 80, (n_labels, 2))
        if k and n_labels:  # one label near one box: IoU around the threshold
            boxes[rng.integers(n_labels)] = rows[rng.integers(k), :4] + rng.normal(0, 4, 4)
        labels.append(boxes.astype(np.float32))
    for mode in ("paper", "strict"):
        for min_score in (None, 0.3):
            got = windows_detected(detections, mode=mode, labels_xyxy=labels, min_score=min_score)
            want = _windows_detected_one_by_one(detections, mode, labels, min_score, 0.5)
            assert got.tolist() == want
    assert any(_windows_detected_one_by_one(detections, "strict", labels, None, 0.5))  # the strict case is exercised


def test_min_score_is_judged_in_each_windows_own_dtype():
    # obj * class_conf of this pair is >= 0.25 in float32 and < 0.25 in float64: a float64 window beside it must not
    # promote the float32 window's product
    obj, cls = np.float32(0.57982713), np.float32(0.43116298)
    assert obj * cls >= np.float32(0.25) and np.float64(obj) * np.float64(cls) < 0.25
    row32 = np.array([[0, 0, 10, 10, obj, cls, 1]], np.float32)
    row64 = np.array([[0, 0, 10, 10, 0.9, 0.9, 1]], np.float64)
    for detections in ([row32], [row32, row64], [row64, row32]):
        got = windows_detected(detections, min_score=0.25).tolist()
        assert got == _windows_detected_one_by_one(detections, "paper", None, 0.25, 0.5) and all(got)


def test_strict_mode_matches_any_label_of_the_window_not_the_first():
    detections = [det(100, 50, 180, 210), det(100, 50, 180, 210)]
    labels = [np.array([[0, 0, 20, 20], [100, 50, 180, 210]], np.float32), np.zeros((0, 4), np.float32)]
    assert windows_detected(detections, mode="strict", labels_xyxy=labels).tolist() == [True, False]


def test_windows_detected_refuses_a_malformed_entry():
    with pytest.raises(FormatError):
        windows_detected([det(0, 0, 10, 10), np.zeros((2, 5), np.float32)])


def test_seqasr_never_decreases_with_the_threshold():
    rng = np.random.default_rng(3)
    detections = []
    for _ in range(60):
        k = int(rng.integers(0, 4))
        rows = np.zeros((k, 7), np.float32)
        rows[:, :4] = [10, 10, 60, 120]
        rows[:, 4] = rng.random(k)
        rows[:, 5] = rng.random(k)
        rows[:, 6] = rng.integers(0, 2, k)
        detections.append(rows if k else None)
    sequences = label_sequences(rng.random(60) < 0.9, 3)
    values = [seq_asr(windows_detected(detections, min_score=t), sequences).seq_asr for t in (0.001, 0.01, 0.1, 0.25,
                                                                                               0.5, 0.9)]
    assert values == sorted(values) and values[0] < values[-1]


def test_box_iou_known_values():
    iou = box_iou([[0, 0, 10, 10]], [[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30], [0, 0, 0, 0]])
    assert iou.tolist() == [[1.0, pytest.approx(1 / 3), 0.0, 0.0]]


def test_longest_run_is_the_longest_stretch_of_labelled_windows():
    from davis_rig.metrics.seqasr import longest_run

    labelled = np.array([1, 1, 0, 1, 1, 1, 0, 1], bool)
    assert longest_run(labelled) == 3 and len(label_sequences(labelled, 4)) == 0
    assert longest_run(np.zeros(4, bool)) == 0 and longest_run(np.zeros(0, bool)) == 0
