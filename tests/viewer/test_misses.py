"""Missed windows and attack successes: exact on a hand-made case, and SeqASR's own count on random cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.evaluation.physical import EvalSettings, SessionScores, compute_metrics
from davis_rig.types import BBOX_DTYPE, CAR_CLASS_ID, PEDESTRIAN_CLASS_ID
from davis_rig.viewer.misses import find_misses, labelled_windows

WINDOW_US = 50_000
ENDS = WINDOW_US * np.arange(1, 13, dtype=np.int64)  # 12 windows from t0 = 0


def labels_at(times, w=40.0, h=90.0, class_id=PEDESTRIAN_CLASS_ID) -> np.ndarray:
    out = np.zeros(len(times), BBOX_DTYPE)
    out["t"], out["x"], out["y"], out["w"], out["h"], out["class_id"] = times, 10, 20, w, h, class_id
    return out


def box(x1=10, y1=20, x2=50, y2=110, score=0.9, class_id=PEDESTRIAN_CLASS_ID):
    return np.array([[x1, y1, x2, y2, score, 1.0, class_id]], np.float32)


SETTINGS = EvalSettings(seq_len=2, skip_first_us=100_000)


def test_labelled_windows_apply_the_evaluation_filters():
    labels = np.concatenate([labels_at([25_000, 125_000, 175_000, 225_000]),     # 25 ms: inside the skipped 0.1 s
                             labels_at([275_000], w=5.0),                          # too narrow
                             labels_at([325_000], class_id=CAR_CLASS_ID)])         # not a pedestrian
    labelled, boxes = labelled_windows(labels, ENDS, WINDOW_US, 0, SETTINGS)
    np.testing.assert_array_equal(np.flatnonzero(labelled), [2, 3, 4])
    np.testing.assert_array_equal(boxes[2], [[10, 20, 50, 110]])
    assert all(len(b) == 0 for i, b in enumerate(boxes) if i not in (2, 3, 4))


def test_find_misses_paper_and_strict_and_only_the_scored_windows():
    labels = labels_at([125_000, 175_000, 225_000, 275_000, 325_000, 375_000])  # windows 2..7
    detections = [None] * 12
    detections[2] = box()                   # hit
    detections[3] = box(x1=300, x2=340)     # a pedestrian box elsewhere: paper hit, strict miss
    detections[6] = box(class_id=CAR_CLASS_ID)  # a car: a miss in both modes
    paper = find_misses(labels, ENDS, detections, WINDOW_US, 0, SETTINGS, "paper")
    np.testing.assert_array_equal(paper.windows, [4, 5, 6, 7])
    np.testing.assert_array_equal(paper.sequences, [[4, 5], [6, 7]])  # sequences [2,3], [4,5], [6,7]
    assert (paper.num_labelled, paper.num_sequences, paper.num_scored) == (6, 3, 12)
    strict = find_misses(labels, ENDS, detections, WINDOW_US, 0, SETTINGS, "strict")
    np.testing.assert_array_equal(strict.windows, [3, 4, 5, 6, 7])
    np.testing.assert_array_equal(strict.sequences, [[4, 5], [6, 7]])
    partial = find_misses(labels, ENDS, detections[:5], WINDOW_US, 0, SETTINGS, "paper")  # scored so far: 0..4
    np.testing.assert_array_equal(partial.windows, [4])
    assert partial.num_sequences == 1 and len(partial.sequences) == 0 and partial.num_scored == 5
    assert paper.as_dict()["sequences"] == [[4, 5], [6, 7]]
    with pytest.raises(ValueError, match="mode"):
        find_misses(labels, ENDS, detections, WINDOW_US, 0, SETTINGS, "loose")


@settings(max_examples=25, deadline=None)
@given(label_windows=st.lists(st.booleans(), min_size=12, max_size=12),
       hits=st.lists(st.booleans(), min_size=12, max_size=12), seq_len=st.integers(1, 4))
def test_attack_successes_are_what_seqasr_counts(label_windows, hits, seq_len):
    labels = labels_at([int(end) - 10_000 for end, on in zip(ENDS, label_windows) if on])
    detections = [box() if hit else None for hit in hits]
    settings_ = EvalSettings(seq_len=seq_len, skip_first_us=None, thresholds=(0.25,))
    misses = find_misses(labels, ENDS, detections, WINDOW_US, 0, settings_, "paper")
    scores = SessionScores(path=Path("x.h5"), t0_us=0, window_end_us=ENDS, detections={0.25: detections},
                           labels=labels, crop_origin_xy=(21, 10), num_events=0, timings_s={})
    metrics = compute_metrics(scores, settings_)[0.25]
    assert misses.num_sequences == metrics["num_sequences"]
    assert len(misses.sequences) == metrics["num_sequences"] - metrics["num_detected"]
    if metrics["num_sequences"]:
        assert len(misses.sequences) / misses.num_sequences == pytest.approx(metrics["seq_asr"])
