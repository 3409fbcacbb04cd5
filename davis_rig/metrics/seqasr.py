"""SeqASR, the paper's sequence attack success rate: ``1 − N / M`` over sequences of consecutive windows.

``M`` = the number of evaluated sequences, ``N`` = the sequences in which the pedestrian counts as detected.

Sequences (:func:`label_sequences`): the recording's 50 ms windows that contain a pedestrian label form runs of
consecutive windows; each run is cut into sequences of ``seq_len`` windows, non-overlapping by default
(``stride = seq_len``; the paper's digital validation clips are disjoint) or sliding with a smaller stride; a
run's remainder shorter than ``seq_len`` is not evaluated.

Detection in a sequence:

* ``"paper"`` (default, the official code): the sequence is detected when **any** pedestrian box that passed
  the confidence threshold appears in any of its windows — no matching to the labels;
* ``"strict"``: the sequence is detected only when, in at least one of its windows, a pedestrian box overlaps a
  label of that window with IoU ≥ ``iou_threshold`` (0.5).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from davis_rig.errors import FormatError, ShapeError
from davis_rig.types import PEDESTRIAN_CLASS_ID

__all__ = ["SeqAsrMode", "SeqAsrResult", "box_iou", "label_sequences", "longest_run", "seq_asr",
           "windows_detected", "windows_with_labels"]


class SeqAsrMode(StrEnum):
    """When a window counts as detected: ``paper`` = any pedestrian box; ``strict`` = a pedestrian box with IoU at
    or above the threshold with one of the window's labels."""

    PAPER = "paper"
    STRICT = "strict"


@dataclass(frozen=True)
class SeqAsrResult:
    """One SeqASR figure.

    Attributes:
        seq_asr: ``1 − num_detected / num_sequences`` in [0, 1]; NaN when there is no sequence.
        num_sequences: M.
        num_detected: N.
        mode: ``"paper"`` or ``"strict"``.
    """

    seq_asr: float
    num_sequences: int
    num_detected: int
    mode: str

    def as_dict(self) -> dict:
        """JSON-ready dict of the fields."""
        return {"seq_asr": self.seq_asr, "num_sequences": self.num_sequences, "num_detected": self.num_detected,
                "mode": self.mode}


def windows_with_labels(window_end_us, label_t_us, window_us: int) -> np.ndarray:
    """Which windows ``(end − window_us, end]`` contain at least one label time.

    Args:
        window_end_us: window ends, int µs [T], increasing.
        label_t_us: label timestamps, int µs [L] (any order).
        window_us: window duration, µs.

    Returns:
        bool [T].
    """
    ends = np.asarray(window_end_us, dtype=np.int64)
    t = np.sort(np.asarray(label_t_us, dtype=np.int64))
    lo = np.searchsorted(t, ends - int(window_us), side="right")
    hi = np.searchsorted(t, ends, side="right")
    return hi > lo


def label_sequences(labelled, seq_len: int, stride: int | None = None) -> np.ndarray:
    """Cut runs of consecutive labelled windows into sequences of ``seq_len`` windows.

    Args:
        labelled: bool [T], window has a pedestrian label.
        seq_len: windows per sequence (the paper: 10 physical, 3 digital).
        stride: windows between sequence starts within a run; default ``seq_len`` (non-overlapping).

    Returns:
        int64 [S, seq_len] window indices of each sequence, in time order.

    Raises:
        ValueError: ``seq_len`` or ``stride`` < 1.
    """
    if seq_len < 1:
        raise ValueError(f"seq_len: expected >= 1, got {seq_len}")
    stride = seq_len if stride is None else int(stride)
    if stride < 1:
        raise ValueError(f"stride: expected >= 1, got {stride}")
    labelled = np.asarray(labelled, dtype=bool)
    padded = np.concatenate([[False], labelled, [False]])
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    starts, stops = edges[0::2], edges[1::2]  # runs [start, stop)
    firsts = [np.arange(a, b - seq_len + 1, stride) for a, b in zip(starts.tolist(), stops.tolist()) if b - a >= seq_len]
    if not firsts:
        return np.zeros((0, seq_len), dtype=np.int64)
    first = np.concatenate(firsts).astype(np.int64)
    return first[:, None] + np.arange(seq_len, dtype=np.int64)[None, :]


def longest_run(labelled) -> int:
    """Length, in windows, of the longest run of consecutive labelled windows (0 when none is labelled).

    A run shorter than ``seq_len`` gives no sequence in :func:`label_sequences`; this says how long it may be.
    """
    labelled = np.asarray(labelled, dtype=bool)
    padded = np.concatenate([[False], labelled, [False]])
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return int((edges[1::2] - edges[0::2]).max()) if len(edges) else 0


def box_iou(a, b) -> np.ndarray:
    """IoU matrix of two ``(x1, y1, x2, y2)`` box sets (float64, no +1), shape [A, B]."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    return _paired_iou(np.repeat(a, len(b), axis=0), np.tile(b, (len(a), 1))).reshape(len(a), len(b))


def windows_detected(
    detections,
    *,
    mode: str = "paper",
    labels_xyxy=None,
    class_id: int = PEDESTRIAN_CLASS_ID,
    min_score: float | None = None,
    iou_threshold: float = 0.5,
) -> np.ndarray:
    """Which windows count as "pedestrian detected".

    Args:
        detections: one entry per window: RVT post-processed float32 [K, 7] ``(x1, y1, x2, y2, obj,
            class_conf, class_id)`` or ``None``.
        mode: ``"paper"`` (any pedestrian box) or ``"strict"`` (a pedestrian box with IoU ≥ ``iou_threshold``
            with one of the window's labels).
        labels_xyxy: for ``"strict"``: one float [L, 4] array of the window's label boxes per window.
        class_id: the pedestrian class id (Gen1: 1).
        min_score: also require ``obj · class_conf ≥ min_score`` (``None``: the detections are already
            thresholded by the post-processing).
        iou_threshold: strict-mode IoU threshold.

    Returns:
        bool [T].

    Raises:
        ValueError: unknown mode; ShapeError: ``labels_xyxy`` missing or of the wrong length in strict mode;
        FormatError: an entry that is neither ``None`` nor [K, ≥ 7].
    """
    if mode not in tuple(SeqAsrMode):
        raise ValueError(f"mode: expected one of {tuple(m.value for m in SeqAsrMode)}, got {mode!r}")
    if mode == SeqAsrMode.STRICT and (labels_xyxy is None or len(labels_xyxy) != len(detections)):
        raise ShapeError(f"strict SeqASR needs one label array per window ({len(detections)} windows), got "
                         f"{None if labels_xyxy is None else len(labels_xyxy)}")
    rows, window, score = _stacked(detections)
    keep = rows[:, 6].astype(np.int64) == class_id
    if min_score is not None:
        keep &= score >= np.float32(min_score)
    rows, window = rows[keep], window[keep]
    out = np.zeros(len(detections), dtype=bool)
    if mode == SeqAsrMode.PAPER:
        out[window] = True
        return out
    labels = [np.asarray(boxes, dtype=np.float64).reshape(-1, 4) for boxes in labels_xyxy]
    label_counts = np.array([len(boxes) for boxes in labels], dtype=np.int64)
    label_rows = np.concatenate(labels) if labels else np.zeros((0, 4))
    label_start = np.concatenate([[0], np.cumsum(label_counts)[:-1]]).astype(np.int64)
    # every (detection, label) pair of one window: detection d meets the label_counts[window[d]] labels of its window
    pairs = label_counts[window]
    det_index = np.repeat(np.arange(len(rows)), pairs)
    offset = np.arange(int(pairs.sum())) - np.repeat(np.cumsum(pairs) - pairs, pairs)
    label_index = label_start[window[det_index]] + offset
    iou = _paired_iou(rows[det_index, :4].astype(np.float64), label_rows[label_index])
    out[window[det_index[iou >= iou_threshold]]] = True
    return out


def _stacked(detections) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All windows' detection rows in one [N, 7] array (their dtype, as postprocess gives: float32), the window of
    each row, int64 [N], and each row's score ``obj * class_conf`` computed in its own window's dtype (as the window
    alone would give it, even where windows of float32 and float64 rows are mixed), float64 [N].

    Raises:
        FormatError: an entry that is not ``None`` nor [K, ≥ 7].
    """
    parts, windows, scores = [], [], []
    for i, det in enumerate(detections):
        if det is None or len(det) == 0:
            continue
        det = np.asarray(det)
        if det.ndim != 2 or det.shape[1] < 7:
            raise FormatError(f"detections[{i}]: expected [K, 7], got {det.shape}")
        parts.append(det[:, :7])
        windows.append(np.full(len(det), i, dtype=np.int64))
        scores.append((det[:, 4] * det[:, 5]).astype(np.float64))
    if not parts:
        return np.zeros((0, 7), np.float32), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(parts), np.concatenate(windows), np.concatenate(scores)


def _paired_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of box ``a[i]`` with box ``b[i]`` (float64 [N, 4] ``(x1, y1, x2, y2)`` each, no +1): float64 [N]."""
    lt = np.maximum(a[:, :2], b[:, :2])
    rb = np.minimum(a[:, 2:], b[:, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=1)
    area_a = np.prod(np.clip(a[:, 2:] - a[:, :2], 0, None), axis=1)
    area_b = np.prod(np.clip(b[:, 2:] - b[:, :2], 0, None), axis=1)
    union = area_a + area_b - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def seq_asr(detected, sequences, mode: str = "paper") -> SeqAsrResult:
    """SeqASR = 1 − N / M.

    Args:
        detected: bool [T], window counts as detected (:func:`windows_detected`).
        sequences: int [S, seq_len] window indices (:func:`label_sequences`).
        mode: recorded in the result.

    Returns:
        :class:`SeqAsrResult` (NaN SeqASR when S = 0).
    """
    detected = np.asarray(detected, dtype=bool)
    sequences = np.asarray(sequences, dtype=np.int64)
    if sequences.ndim != 2:
        raise ShapeError(f"sequences: expected [S, seq_len], got {sequences.shape}")
    if sequences.size and (sequences.min() < 0 or sequences.max() >= len(detected)):
        raise ShapeError(f"sequences: window indices outside [0, {len(detected)})")
    m = int(sequences.shape[0])
    n = int(detected[sequences].any(axis=1).sum()) if m else 0
    return SeqAsrResult(seq_asr=1.0 - n / m if m else float("nan"), num_sequences=m, num_detected=n, mode=mode)
