"""Validation of a detector during training: a split streamed through the recurrent model, COCO AP (RVT protocol).

:func:`validate_detector` streams every sequence of a split in chunks over parallel lanes
(:class:`~davis_rig.training.batches.StreamingBatches`, the recurrent states carried between a lane's chunks and
reset at sequence starts, :func:`reset_states`), detects on every labelled window, and scores the detections with
:mod:`davis_rig.metrics.ap` (labels and detections within ``skip_first_us`` of a sequence's start ignored).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.events.histogram import WINDOW_US
from davis_rig.metrics.ap import SKIP_FIRST_US
from davis_rig.models.rvt.detector import pad_to_input
from davis_rig.training.batches import StreamingBatches
from davis_rig.training.dataset import list_sequences
from davis_rig.types import BBOX_DTYPE, RVT_NMS_IOU

with optional_dependency("training"):
    import torch

__all__ = ["reset_states", "validate_detector"]


def reset_states(states, is_first: torch.Tensor):
    """The recurrent states ``[(h, c)]`` (per stage, batch first) with the lanes that start a sequence zeroed;
    ``None`` (a fresh start) when there are none yet or every lane starts one.

    Args:
        states: list of ``(h, c)`` tensors [B, ...] or ``None``.
        is_first: bool tensor [B].
    """
    if states is None or bool(is_first.all()):
        return None
    keep = (~is_first).to(states[0][0].device, dtype=states[0][0].dtype).view(-1, 1, 1, 1)
    return [(h * keep, c * keep) for h, c in states]


def _boxes_to_bbox(boxes: torch.Tensor, t_us: int) -> np.ndarray:
    """Training labels float [K, 5] ``(class, x, y, w, h)`` (px, top-left) as BBOX_DTYPE [K] stamped ``t_us``."""
    b = boxes.detach().cpu().numpy()
    out = np.zeros(b.shape[0], BBOX_DTYPE)
    out["t"] = int(t_us)
    out["x"], out["y"], out["w"], out["h"] = b[:, 1], b[:, 2], b[:, 3], b[:, 4]
    out["class_id"] = b[:, 0].astype(np.uint8)
    out["class_confidence"] = 1.0
    return out


def _stream_detections(model, stream: StreamingBatches, conf_threshold: float, amp_dtype):
    """Labels and detections of every labelled window of the stream, per sequence index: ``(gt, dt)``, each
    ``{sequence: [BBOX_DTYPE arrays]}``."""
    from davis_rig.metrics.ap import detections_to_boxes
    from davis_rig.models.rvt.postprocess import postprocess

    device = next(model.parameters()).device
    gt: dict[int, list[np.ndarray]] = {}
    dt: dict[int, list[np.ndarray]] = {}
    states = None
    autocast = torch.autocast(device.type, dtype=amp_dtype, enabled=amp_dtype is not None)
    for batch in stream:
        states = reset_states(states, batch.is_first)
        hist = batch.histograms.to(device).float()
        for t in range(hist.shape[0]):
            with autocast:
                features, states = model.forward_backbone(pad_to_input(hist[t], model.config.in_res_hw), states)
            lanes = [b for b, lab in enumerate(batch.labels[t]) if lab is not None and bool(batch.valid[t, b])]
            if not lanes:
                continue
            index = torch.tensor(lanes, device=device)
            with autocast:
                decoded = model.forward_detect({k: v.index_select(0, index) for k, v in features.items()})
            detections = postprocess(decoded.float().cpu(), conf_threshold, RVT_NMS_IOU)
            for det, b in zip(detections, lanes):
                seq, t_us = batch.sequence[b], int(batch.window_end_us[t, b])
                gt.setdefault(seq, []).append(_boxes_to_bbox(batch.labels[t][b], t_us))
                dt.setdefault(seq, []).append(detections_to_boxes(det, t_us))
    return gt, dt


@torch.no_grad()
def validate_detector(model, data_dir: str | Path, split: str = "val", *, seq_len: int = 21, batch_size: int = 8,
                      conf_threshold: float = 0.001, skip_first_us: int | None = SKIP_FIRST_US,
                      max_sequences: int | None = None, amp_dtype=None) -> dict[str, Any]:
    """Stream a split through ``model`` and compute COCO AP with the RVT protocol.

    Args:
        model: an :class:`~davis_rig.models.rvt.detector.RVTDetector` (left in its training mode on return).
        data_dir: dataset folder in RVT's layout; split: its split to stream.
        seq_len, batch_size: chunk length L (windows) and parallel lanes B of the stream.
        conf_threshold: postprocess threshold (RVT's reported evaluation: 0.001).
        skip_first_us: labels and detections within this time from a sequence's start are ignored (µs).
        max_sequences: only the first N sequences (``None`` = all).
        amp_dtype: autocast dtype (``None``: no autocast).

    Returns:
        ``{"AP", "AP_50", "AP_75", "AP_S", "AP_M", "AP_L", "num_images", "num_labels", "num_detections",
        "sequences", "time_s"}``; an empty dict when the split does not exist.
    """
    from davis_rig.metrics.ap import coco_ap, filter_boxes, match_times

    data_dir = Path(data_dir)
    if not (data_dir / split).is_dir() or not list_sequences(data_dir, split):
        return {}
    start_time = time.perf_counter()
    was_training = model.training
    model.eval()
    stream = StreamingBatches(data_dir, split, seq_len, batch_size)
    if max_sequences is not None:
        stream.sequences = stream.sequences[:max_sequences]
    gt, dt = _stream_detections(model, stream, conf_threshold, amp_dtype)
    gts_all, dts_all = [], []
    for seq_index in sorted(gt):
        seq_start = int(stream.sequences[seq_index].window_end_us[0]) - WINDOW_US
        skip = seq_start + skip_first_us if skip_first_us is not None else None
        g = filter_boxes(np.concatenate(gt[seq_index]), skip_until_us=skip)
        d = filter_boxes(np.concatenate(dt[seq_index]), skip_until_us=skip)
        # detections carry their label's exact time; Prophesee's ±50 ms would also hand every image the
        # neighbouring windows' detections when labels are 50 ms apart (synthetic data: every window)
        _, g_list, d_list = match_times(g, d, time_tol_us=0)
        gts_all.extend(g_list)
        dts_all.extend(d_list)
    result: dict[str, Any] = dict(coco_ap(gts_all, dts_all, category=None))
    result.update(num_images=len(gts_all), num_labels=int(sum(len(g) for g in gts_all)),
                  num_detections=int(sum(len(d) for d in dts_all)), sequences=len(stream.sequences),
                  time_s=round(time.perf_counter() - start_time, 3))
    for seq in stream.sequences:
        seq.close()
    model.train(was_training)
    return result
