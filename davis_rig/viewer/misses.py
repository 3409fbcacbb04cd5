"""Where the detector missed the person: the windows and SeqASR sequences the attack won, exactly as ``davis-eval``
counts them (:func:`davis_rig.evaluation.physical.compute_metrics`).

A window *needs* a detection when it holds a pedestrian label that passes the evaluation's filter (Prophesee
box filter, the first ``skip_first_us`` after ``t0`` left out); it is *missed* when it needs one and the detector
found no pedestrian in it (``paper`` mode: any pedestrian box; ``strict``: none with IoU ≥ ``strict_iou`` to a
label of the window). An *attack success* is a SeqASR sequence (``seq_len`` consecutive labelled windows) in
which every window is missed — the sequences counted in SeqASR's numerator ``M − N``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from davis_rig.types import PEDESTRIAN_CLASS_ID

__all__ = ["Misses", "find_misses", "labelled_windows"]


@dataclass(frozen=True)
class Misses:
    """Missed windows and successful attack sequences of the scored part of a recording.

    Attributes:
        windows: int64 [M] indices of the missed windows, increasing.
        sequences: int64 [S, seq_len] window indices of the sequences with every window missed.
        num_labelled: windows (scored) that need a detection.
        num_sequences: SeqASR sequences (scored).
        num_scored: windows the answer covers (windows ``0 .. num_scored - 1``).
    """

    windows: np.ndarray
    sequences: np.ndarray
    num_labelled: int
    num_sequences: int
    num_scored: int

    def as_dict(self) -> dict:
        """JSON-ready dict."""
        return {"windows": self.windows.tolist(), "sequences": self.sequences.tolist(),
                "num_labelled": self.num_labelled, "num_sequences": self.num_sequences, "num_scored": self.num_scored}


def labelled_windows(labels: np.ndarray, window_end_us: np.ndarray, window_us: int, t0_us: int,
                     settings) -> tuple[np.ndarray, list[np.ndarray]]:
    """Which windows need a detection, and their (filtered) label boxes.

    Args:
        labels: BBOX_DTYPE [L] (crop px, device µs).
        window_end_us: int64 [T] window ends, device µs.
        window_us: window length, µs.
        t0_us: start of the window grid, device µs.
        settings: :class:`~davis_rig.evaluation.physical.EvalSettings` (filter and skip settings).

    Returns:
        ``(bool [T], T float64 arrays [L_i, 4] of x1, y1, x2, y2)``.
    """
    from davis_rig.evaluation.physical import label_windows
    from davis_rig.metrics.ap import filter_boxes
    from davis_rig.metrics.seqasr import windows_with_labels

    ends = np.asarray(window_end_us, np.int64)
    skip = None if settings.skip_first_us is None else int(t0_us) + int(settings.skip_first_us)
    kept = filter_boxes(labels[labels["class_id"] == PEDESTRIAN_CLASS_ID], skip_until_us=skip,
                        min_diag_px=settings.min_diag_px, min_side_px=settings.min_side_px)
    index = label_windows(kept, ends, window_us)
    kept, index = kept[index >= 0], index[index >= 0]
    xyxy = np.stack([kept["x"], kept["y"], kept["x"] + kept["w"], kept["y"] + kept["h"]], 1).astype(np.float64)
    labelled = windows_with_labels(ends, kept["t"].astype(np.int64), window_us)
    return labelled, [xyxy[index == i] for i in range(len(ends))]


def find_misses(labels: np.ndarray, window_end_us: np.ndarray, detections: list, window_us: int, t0_us: int,
                settings, mode: str = "paper") -> Misses:
    """The missed windows and the attack's successful sequences among the first ``len(detections)`` windows.

    Args:
        labels: BBOX_DTYPE [L] (crop px, device µs).
        window_end_us: int64 [T] every window end of the recording, device µs.
        detections: the detections of windows ``0 .. S - 1`` (``S <= T``, the scored part): float32 [K, 7] or
            ``None`` each.
        window_us: window length, µs.
        t0_us: start of the window grid, device µs.
        settings: :class:`~davis_rig.evaluation.physical.EvalSettings` (filter, ``seq_len``, ``seq_stride``,
            ``strict_iou``).
        mode: ``"paper"`` or ``"strict"`` (see the module docstring).

    Returns:
        :class:`Misses`. Sequences are those of the scored windows only; every one of them is also a sequence
        of the whole recording (a run is cut into sequences from its start).

    Raises:
        ValueError: unknown mode, or more detections than windows.
    """
    from davis_rig.metrics.seqasr import SeqAsrMode, label_sequences, windows_detected

    if mode not in tuple(SeqAsrMode):
        raise ValueError(f"mode: expected {' or '.join(repr(m.value) for m in SeqAsrMode)}, got {mode!r}")
    scored = len(detections)
    if scored > len(window_end_us):
        raise ValueError(f"{scored} windows of detections for {len(window_end_us)} windows")
    labelled, boxes = labelled_windows(labels, window_end_us, window_us, t0_us, settings)
    labelled, boxes = labelled[:scored], boxes[:scored]
    detected = windows_detected(detections, mode=mode, labels_xyxy=boxes if mode == SeqAsrMode.STRICT else None,
                                iou_threshold=settings.strict_iou)
    missed = labelled & ~detected
    sequences = label_sequences(labelled, settings.seq_len, settings.seq_stride)
    won = sequences[missed[sequences].all(axis=1)]
    return Misses(windows=np.flatnonzero(missed).astype(np.int64), sequences=won.astype(np.int64),
                  num_labelled=int(labelled.sum()), num_sequences=int(len(sequences)), num_scored=scored)
