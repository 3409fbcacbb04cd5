"""Scoring of the digital evaluation: event histograms of a video, the detector over the windows, AP and SeqASR.

- :func:`window_histograms`: RVT's stacked histograms of a video under an event model (:data:`EVENT_MODELS`: the
  exact simulator's quantized events, or the official code's relaxed counts);
- :func:`detect_windows` / :func:`detect_histograms`: the detector over the windows of one or several sequences,
  with its recurrent states (zero at the sequence start);
- :func:`score_detections`: COCO AP / AP50 / AP75 of the pedestrian class (one image per window, the Prophesee
  size filter on labels and detections) and SeqASR (``"paper"`` mode) per confidence threshold, after RVT's
  post-processing (class-wise NMS).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.errors import ShapeError
from davis_rig.events.histogram import WINDOW_US, stacked_histograms
from davis_rig.events.simulator import SimulatorConfig, simulate_events
from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID

with optional_dependency("the attack evaluation"):
    import torch

__all__ = [
    "EVENT_MODELS",
    "EVENT_MODEL_NAMES",
    "detect_histograms",
    "detect_windows",
    "score_detections",
    "relaxed_window_histograms",
    "window_histograms",
]

#: Event models of the evaluation: ``"exact"`` (quantized events of the exact simulator, what a camera delivers;
#: the default) and ``"official_relaxed"`` (the official code's continuous counts scaled by 10/27, the input its
#: evaluation scored; not events, for comparison with the paper's numbers only).
EVENT_MODELS = ("exact", "official_relaxed")
#: How tables name the event models.
EVENT_MODEL_NAMES = {"exact": "exact simulator", "official_relaxed": "official code's relaxed counts, not events"}


def relaxed_window_histograms(video: torch.Tensor, t_us, window_end_us, simulator: SimulatorConfig | None = None,
                              window_us: int = WINDOW_US) -> torch.Tensor:
    """The official code's continuous counts of a video: float32 [W, 20, H, W], differentiable in ``video``.

    The one definition of the ``"official_relaxed"`` event model: what :func:`window_histograms` scores (without
    the gradient) and what the free-appearance bound (:mod:`davis_rig.controls.bounds`) optimises, so the two
    cannot drift apart. :func:`~davis_rig.events.v2e_torch.v2e_histograms` in mode ``"official_relaxed"`` with the
    simulator's θ_on (= θ_off), intensity scale and lin-log knee.

    Args:
        video: float tensor [T, H, W], linear intensity in [0, 1] (on the device the counts are computed on).
        t_us: int64 [T] frame times (µs).
        window_end_us: int64 [W] window ends (µs).
        simulator: sensor settings (default the ideal sensor, θ = 0.2).
        window_us: window duration (µs; RVT: 50 ms).

    Raises:
        ValueError: θ_on ≠ θ_off (the official counts have one threshold).
    """
    from davis_rig.events.v2e_torch import v2e_histograms

    simulator = simulator or SimulatorConfig()
    return v2e_histograms(video, t_us, window_end_us, mode="official_relaxed", window_us=int(window_us),
                          threshold_on=float(simulator.threshold_on), threshold_off=float(simulator.threshold_off),
                          intensity_scale=simulator.intensity_scale, lin_log_threshold=simulator.lin_log_threshold)


def window_histograms(video, t_us, window_end_us, simulator: SimulatorConfig | None = None, events: str = "exact",
                      device=None, window_us: int = WINDOW_US) -> np.ndarray:
    """RVT's stacked histograms [W, 20, H, W] of a video under an event model (:data:`EVENT_MODELS`).

    Args:
        video: float tensor/array [T, H, W], linear intensity in [0, 1].
        t_us: int64 [T] frame times (µs).
        window_end_us: int64 [W] window ends (µs); window k is ``[window_end_us[k] - window_us, window_end_us[k]]``.
        simulator: simulator settings (default ideal sensor); ``"official_relaxed"`` uses its θ_on (= θ_off).
        events: ``"exact"``: quantized events of :func:`~davis_rig.events.simulator.simulate_events`, uint8
            counts; ``"official_relaxed"``: the official code's continuous counts
            (:func:`~davis_rig.events.v2e_torch.v2e_histograms`, mode ``"official_relaxed"``), float32.
        device: where the simulator runs.
        window_us: window duration (µs; RVT: 50 ms).

    Raises:
        ValueError: unknown ``events``, or unequal thresholds with ``"official_relaxed"``.
    """
    simulator = simulator or SimulatorConfig()
    video = video.detach() if isinstance(video, torch.Tensor) else torch.as_tensor(np.asarray(video))
    if events == "exact":
        stream = simulate_events(video, t_us, simulator, device=device)
        h, w = video.shape[-2:]
        return stacked_histograms(stream, window_end_us, window_us=int(window_us), height=int(h), width=int(w))
    if events != "official_relaxed":
        raise ValueError(f"events must be one of {EVENT_MODELS}, got {events!r}")
    with torch.no_grad():
        hist = relaxed_window_histograms(video.to(device=device, dtype=torch.float32), t_us, window_end_us,
                                         simulator, window_us=window_us)
    return hist.cpu().numpy()


def detect_windows(detector, video, t_us, window_end_us, simulator: SimulatorConfig | None = None,
                   device=None, events: str = "exact",
                   window_us: int = WINDOW_US) -> tuple[list[np.ndarray], np.ndarray]:
    """Events of a video -> stacked histograms -> the detector over the windows with states.

    Args:
        detector: :class:`~davis_rig.models.rvt.detector.RVTDetector` (eval mode).
        video: float tensor/array [T, H, W], linear intensity.
        t_us: int64 [T] frame times (µs).
        window_end_us: int64 [W] window ends (µs).
        simulator: exact simulator settings (default ideal sensor).
        device: torch device of the detector (default: its parameters').
        events: the event model (:func:`window_histograms`; default the exact simulator).
        window_us: window duration (µs).

    Returns:
        ``(decoded, hist)``: one float32 [A, 5 + nc] array per window (the head's decoded output) and the
        histograms [W, 20, H, W] (uint8 counts; float32 with ``"official_relaxed"``).
    """
    from davis_rig.models.rvt.detector import pad_to_input

    device = next(detector.parameters()).device if device is None else torch.device(device)
    # the simulator runs where the detector is
    hist = window_histograms(video, t_us, window_end_us, simulator, events, device=device, window_us=window_us)
    decoded, states = [], None
    with torch.no_grad():
        for k in range(hist.shape[0]):
            x = pad_to_input(torch.from_numpy(hist[k : k + 1]).to(device), detector.config.in_res_hw)
            out, states = detector(x, states)
            decoded.append(out[0].float().cpu().numpy())
    return decoded, hist


def detect_histograms(detector, hists: Sequence["torch.Tensor"], device=None) -> list[list[np.ndarray]]:
    """The detector over the windows of several sequences at once, recurrent states per sequence.

    Args:
        detector: :class:`~davis_rig.models.rvt.detector.RVTDetector` (eval mode).
        hists: per sequence a tensor [W, 20, H, W] of counts (all the same shape).
        device: torch device of the detector (default: its parameters').

    Returns:
        per sequence, per window: the head's decoded float32 [A, 5 + nc] array.
    """
    from davis_rig.models.rvt.detector import pad_to_input

    device = next(detector.parameters()).device if device is None else torch.device(device)
    batch = torch.stack([torch.as_tensor(h) for h in hists], dim=1).to(device=device, dtype=torch.float32)
    decoded, states = [[] for _ in hists], None
    with torch.no_grad():
        for k in range(batch.shape[0]):
            out, states = detector(pad_to_input(batch[k], detector.config.in_res_hw), states)
            out = out.float().cpu().numpy()
            for i in range(len(hists)):
                decoded[i].append(out[i])
    return decoded


def _label_boxes(box: np.ndarray, t_us: int) -> np.ndarray:
    out = np.zeros(0 if not np.isfinite(box).all() else 1, dtype=BBOX_DTYPE)
    if out.size:
        out["t"] = t_us
        out["x"], out["y"] = box[0], box[1]
        out["w"], out["h"] = box[2] - box[0], box[3] - box[1]
        out["class_id"] = PEDESTRIAN_CLASS_ID
        out["class_confidence"] = 1.0
    return out


def score_detections(decoded: Sequence[Sequence[np.ndarray]], boxes: Sequence[np.ndarray], window_end_us,
                     thresholds: Sequence[float], *, seq_len: int, nms_threshold: float = 0.45,
                     ap_backend: str = "faster_coco_eval") -> dict[float, dict]:
    """AP and SeqASR per threshold of the scored windows of several sequences.

    Args:
        decoded: per sequence, per scored window: the detector's decoded float [A, 5 + nc].
        boxes: per sequence: float32 [W, 4] label box per scored window (NaN: no person).
        window_end_us: per sequence: int64 [W] window ends (label and detection times).
        thresholds: confidence thresholds.
        seq_len: windows per sequence.
        nms_threshold: NMS IoU threshold.
        ap_backend: COCO backend of :func:`davis_rig.metrics.ap.coco_ap`.

    Returns:
        ``{threshold: {"AP", "AP_50", "AP_75", ..., "SeqASR", "num_sequences", "num_detected", "num_windows"}}``.
    """
    from davis_rig.metrics.ap import coco_ap, detections_to_boxes, filter_boxes
    from davis_rig.metrics.seqasr import label_sequences, seq_asr, windows_detected
    from davis_rig.models.rvt.postprocess import postprocess

    if not (len(decoded) == len(boxes) == len(window_end_us)):
        raise ShapeError(f"decoded, boxes and window_end_us must have one entry per sequence, got "
                         f"{len(decoded)}, {len(boxes)}, {len(window_end_us)}")
    results = {}
    for thr in thresholds:
        gts, dts, detected_all, seqs_all = [], [], [], []
        offset = 0
        for seq_decoded, seq_boxes, ends in zip(decoded, boxes, window_end_us):
            dets = postprocess(np.stack(seq_decoded), float(thr), nms_threshold)
            labelled = np.isfinite(np.asarray(seq_boxes)).all(axis=1)
            detected_all.append(windows_detected(dets, mode="paper"))
            seqs_all.append(label_sequences(labelled, seq_len) + offset)
            offset += len(dets)
            for k, det in enumerate(dets):
                t = int(ends[k])
                gts.append(filter_boxes(_label_boxes(np.asarray(seq_boxes[k]), t)))
                dt = detections_to_boxes(det, t)
                dts.append(filter_boxes(dt[dt["class_id"] == PEDESTRIAN_CLASS_ID]))
        ap = coco_ap(gts, dts, backend=ap_backend)
        sa = seq_asr(np.concatenate(detected_all), np.concatenate(seqs_all, axis=0))
        results[float(thr)] = {**ap, "SeqASR": sa.seq_asr, "num_sequences": sa.num_sequences,
                               "num_detected": sa.num_detected, "num_windows": offset}
    return results
