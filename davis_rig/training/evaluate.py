"""Score a detector on a split of a preprocessed dataset: pedestrian AP, AP50 and SeqASR per held-out subset.

The synthetic test split (``davis-make-dataset``) tags every sequence with its subset ``"clothing/scale"``
(white, black, random 60×60 pattern × large, middle, small); this module streams each sequence through the
detector from zero LSTM states, one 50 ms window per step, and scores

* **AP** (COCO mAP@[.5:.95]) and **AP50** of the pedestrian class with the RVT/Prophesee Gen1 protocol
  (detections at confidence ≥ 0.001, class-wise NMS 0.45, Prophesee box filter, labels and detections of the
  first ``skip_first_us`` of a sequence ignored, :mod:`davis_rig.metrics.ap`); detections are stamped with
  their window's label time and matched to it exactly (Prophesee's ±50 ms tolerance would also give every image
  the neighbouring windows' detections, as the synthetic labels are 50 ms apart: duplicates counted as false
  positives, which caps AP near 0.7 for a perfect detector);
* **SeqASR** at each given threshold (:mod:`davis_rig.metrics.seqasr`, ``"paper"`` mode): the windows after
  ``skip_first_us`` whose labels hold a pedestrian form runs, cut into non-overlapping sequences of ``seq_len``
  windows; a sequence counts as detected when any window of it has a pedestrian box.

Groups: ``"all"``, every clothing (``"white"``, …) and every subset (``"white/large"``, …); sequences without a
subset tag fall in ``"other"``. A dataset with no tags (a train split, preprocessed Gen1) is scored as ``"all"``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from davis_rig.errors import ConfigError, FormatError, ShapeError
from davis_rig.events.histogram import WINDOW_US
from davis_rig.metrics.ap import SKIP_FIRST_US, coco_ap, detections_to_boxes, filter_boxes, match_times
from davis_rig.metrics.seqasr import label_sequences, windows_detected
from davis_rig.training.batches import labels_to_tensor
from davis_rig.training.dataset import SequenceData, list_sequences
from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID, RVT_NMS_IOU

__all__ = ["SplitScoreConfig", "SequenceDetections", "detect_sequences", "evaluate_split", "format_scores",
           "score_sequences"]

#: Confidence threshold of the AP detections (RVT's reported evaluation).
AP_THRESHOLD = 0.001


@dataclass(frozen=True)
class SplitScoreConfig:
    """How a split is scored.

    Attributes:
        split: the split folder (``test``, ``val``, ``train``).
        seqasr_thresholds: confidence thresholds (obj · class) of the SeqASR figures.
        seq_len: windows per SeqASR sequence (the paper's digital protocol: 3).
        skip_first_us: labels, detections and SeqASR windows within this time of a sequence's first window
            start are ignored (RVT protocol 500 ms: the recurrent states warm up), µs.
        lanes: sequences of equal length streamed side by side as one batch.
        nms_threshold: class-wise NMS IoU.
    """

    split: str = "test"
    seqasr_thresholds: tuple[float, ...] = (0.25,)
    seq_len: int = 3
    skip_first_us: int = SKIP_FIRST_US
    lanes: int = 8
    nms_threshold: float = RVT_NMS_IOU

    def __post_init__(self):
        for name in ("seq_len", "lanes"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(name, f"expected >= 1, got {getattr(self, name)}")
        if int(self.skip_first_us) < 0:
            raise ConfigError("skip_first_us", f"expected >= 0, got {self.skip_first_us}")
        if not self.seqasr_thresholds or not all(0 < t < 1 for t in self.seqasr_thresholds):
            raise ConfigError("seqasr_thresholds", f"expected values in (0, 1), got {tuple(self.seqasr_thresholds)}")


@dataclass
class SequenceDetections:
    """One sequence's labels and detections.

    Attributes:
        name: the sequence folder name.
        subset: held-out subset tag (``"white/large"``) or ``""``.
        window_end_us: int64 [T] window ends, µs.
        labels: per window: BBOX_DTYPE [K] clipped label boxes (``t`` = window end), or ``None`` if unlabelled.
        detections: ``{threshold: [T entries: float32 [K, 7] or None]}`` post-processed outputs.
    """

    name: str
    subset: str
    window_end_us: np.ndarray
    labels: list[np.ndarray | None]
    detections: dict[float, list[np.ndarray | None]]


def _clipped_labels(boxes: np.ndarray | None, t_us: int) -> np.ndarray | None:
    """Labels clipped to the 304×240 frame like training (``labels_to_tensor``), as BBOX_DTYPE stamped ``t_us``."""
    if boxes is None:
        return None
    rows = labels_to_tensor(boxes).numpy()
    out = np.zeros(rows.shape[0], BBOX_DTYPE)
    out["t"] = t_us
    out["class_id"] = rows[:, 0].astype(np.uint8)
    out["x"], out["y"], out["w"], out["h"] = rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4]
    out["class_confidence"] = 1.0
    return out


def _subset_of(path: Path) -> str:
    meta = path / "meta.json"
    if not meta.is_file():
        return ""
    try:
        return str(json.loads(meta.read_text(encoding="utf-8")).get("subset", ""))
    except (OSError, ValueError) as exc:
        raise FormatError(f"{meta}: unreadable sequence metadata ({exc})") from exc


def detect_sequences(model, paths: Sequence[Path], thresholds: Sequence[float], *, lanes: int = 8,
                     nms_threshold: float = RVT_NMS_IOU, device: str = "cpu",
                     progress: Callable | None = None) -> list[SequenceDetections]:
    """Stream sequences through an RVT detector (zero states at each sequence start) and post-process.

    Args:
        model: :class:`~davis_rig.models.rvt.detector.RVTDetector` (put in eval mode, moved to ``device``), or an
            :class:`~davis_rig.models.rvt.ort_runner.RVTOnnxRunner` (an exported step graph, fp32 or int8;
            ``device`` is then ignored).
        paths: sequence folders.
        thresholds: confidence thresholds to post-process at (all from one NMS pass, ``postprocess_thresholds``).
        lanes: sequences of equal length run side by side as one batch.
        nms_threshold: class-wise NMS IoU.
        device: torch device.
        progress: ``progress(total=windows, desc=...)`` returning an object with ``update(n)`` and ``close()``
            (e.g. ``tqdm``), advanced by the windows of all sequences; ``None`` for silence.

    Returns:
        One :class:`SequenceDetections` per path, in order.
    """
    import torch

    from davis_rig.models.rvt.postprocess import postprocess_thresholds

    step = _step_function(model, device)
    data = [SequenceData(p) for p in paths]
    results: list[SequenceDetections | None] = [None] * len(data)
    by_length: dict[int, list[int]] = {}
    for i, seq in enumerate(data):
        by_length.setdefault(len(seq), []).append(i)
    bar = progress(total=sum(len(seq) for seq in data), desc="windows") if progress is not None else None
    try:
        for length, members in by_length.items():
            for start in range(0, len(members), lanes):
                group = members[start:start + lanes]
                per_window: list[dict[float, list]] = []
                states = None
                with torch.no_grad():
                    for w in range(length):
                        hist = np.concatenate([data[i].histograms(w, w + 1) for i in group])
                        decoded, states = step(hist, states)
                        per_window.append(postprocess_thresholds(decoded, thresholds, nms_threshold))
                        if bar is not None:
                            bar.update(len(group))
                for lane, i in enumerate(group):
                    seq = data[i]
                    ends = seq.window_end_us
                    results[i] = SequenceDetections(
                        name=seq.path.name, subset=_subset_of(seq.path), window_end_us=ends,
                        labels=[_clipped_labels(seq.labels_at(w), int(ends[w])) for w in range(length)],
                        detections={float(t): [per_window[w][float(t)][lane] for w in range(length)]
                                    for t in thresholds})
    finally:
        if bar is not None:
            bar.close()
        for seq in data:
            seq.close()
    return results  # type: ignore[return-value]


def _step_function(model, device: str) -> Callable:
    """``step(uint8 histograms [B, 20, H, W], states or None) -> (decoded float32 tensor [B, A, 5 + C] on the
    CPU, new states)`` of a torch RVT or an onnxruntime step graph."""
    import torch

    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    if isinstance(model, RVTOnnxRunner):
        def step(hist, states):
            decoded, new_states = model.step(hist, states)
            return torch.from_numpy(decoded), new_states

        return step
    from davis_rig.models.rvt.detector import pad_to_input

    model = model.to(device).eval()

    def step(hist, states):
        x = pad_to_input(torch.from_numpy(hist).to(device).float(), model.config.in_res_hw)
        features, new_states = model.forward_backbone(x, states)
        return model.forward_detect(features).float().cpu(), new_states

    return step


def score_sequences(records: Sequence[SequenceDetections], config: SplitScoreConfig,
                    *, coco_backend: str = "faster_coco_eval") -> dict[str, Any]:
    """Pedestrian AP/AP50/AP75 and SeqASR per threshold over a group of sequences.

    Args:
        records: :func:`detect_sequences` output, with detections at :data:`AP_THRESHOLD` and every
            ``config.seqasr_thresholds``.
        config: the scoring settings.
        coco_backend: ``faster_coco_eval`` or ``pycocotools``.

    Returns:
        ``{"AP", "AP_50", "AP_75", "num_labels", "sequences", "seqasr": {threshold: {"seq_asr",
        "num_sequences", "num_detected"}}}``.
    """
    gts_all, dts_all = [], []
    m = {t: 0 for t in config.seqasr_thresholds}
    n = {t: 0 for t in config.seqasr_thresholds}
    for rec in records:
        skip_until = int(rec.window_end_us[0]) - WINDOW_US + config.skip_first_us
        labelled = [w for w, lab in enumerate(rec.labels) if lab is not None]
        if labelled:
            gt = filter_boxes(np.concatenate([rec.labels[w] for w in labelled]), skip_until_us=skip_until)
            dt = filter_boxes(np.concatenate([detections_to_boxes(rec.detections[AP_THRESHOLD][w],
                                                                  int(rec.window_end_us[w])) for w in labelled]),
                              skip_until_us=skip_until)
            _, g_list, d_list = match_times(gt, dt, time_tol_us=0)  # exact label times (see module doc)
            gts_all.extend(g_list)
            dts_all.extend(d_list)
        with_person = np.array([lab is not None and bool((lab["class_id"] == PEDESTRIAN_CLASS_ID).any())
                                for lab in rec.labels], dtype=bool) & (rec.window_end_us > skip_until)
        sequences = label_sequences(with_person, config.seq_len)
        for t in config.seqasr_thresholds:
            detected = windows_detected(rec.detections[t])
            m[t] += int(sequences.shape[0])
            n[t] += int(detected[sequences].any(axis=1).sum()) if sequences.size else 0
    ap = coco_ap(gts_all, dts_all, category=PEDESTRIAN_CLASS_ID, backend=coco_backend) if gts_all else {}
    return {"AP": ap.get("AP", float("nan")), "AP_50": ap.get("AP_50", float("nan")),
            "AP_75": ap.get("AP_75", float("nan")), "num_labels": int(sum(len(g) for g in gts_all)),
            "sequences": len(records),
            "seqasr": {t: {"seq_asr": 1.0 - n[t] / m[t] if m[t] else float("nan"), "num_sequences": m[t],
                           "num_detected": n[t]} for t in config.seqasr_thresholds}}


def _groups(records: Sequence[SequenceDetections]) -> dict[str, list[SequenceDetections]]:
    groups: dict[str, list[SequenceDetections]] = {"all": list(records)}
    for rec in records:
        if not rec.subset:
            continue
        clothing = rec.subset.split("/")[0]
        groups.setdefault(clothing, []).append(rec)
        groups.setdefault(rec.subset, []).append(rec)
    if any(not rec.subset for rec in records) and len(groups) > 1:
        groups["other"] = [rec for rec in records if not rec.subset]
    return groups


def evaluate_split(data_dir: str | Path, weights: str | Path | None = None, *,
                   config: SplitScoreConfig = SplitScoreConfig(), device: str = "cpu",
                   coco_backend: str = "faster_coco_eval", progress: Callable | None = None,
                   threads: int | None = None) -> dict[str, Any]:
    """Score a detector on a dataset split, per group (``all``, clothing, ``clothing/scale``).

    Args:
        data_dir: dataset folder (``davis-make-dataset`` output or RVT's preprocessed layout).
        weights: RVT checkpoint (``.safetensors``, ``.ckpt``, ``.pt``) or exported step graph (``.onnx``, run by
            onnxruntime on the CPU); default: the bundled detector's weights.
        config: the scoring settings.
        device: torch device (a checkpoint's).
        coco_backend: COCO evaluation backend.
        progress: see :func:`detect_sequences`.
        threads: onnxruntime intra-op threads of an ``.onnx`` graph (``None``: onnxruntime's choice).

    Returns:
        ``{"weights", "split", "config", "time_s", "groups": {group: score_sequences(...)}}``.

    Raises:
        FormatError: the split has no sequences. MissingDependencyError: no weights given and none bundled.
        CheckpointError: unusable weights. ModelFormatError: an unusable ``.onnx`` graph.
    """
    from davis_rig.models import default_detector_weights_path
    from davis_rig.models.rvt.checkpoint import load_detector
    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    weights = Path(weights) if weights is not None else default_detector_weights_path()
    paths = list_sequences(data_dir, config.split)
    if not paths:
        raise FormatError(f"{Path(data_dir) / config.split}: no sequences")
    start = time.perf_counter()
    model = RVTOnnxRunner(weights, intra_op_threads=threads) if weights.suffix.lower() == ".onnx" else load_detector(weights)
    thresholds = sorted({AP_THRESHOLD, *config.seqasr_thresholds})
    records = detect_sequences(model, paths, thresholds, lanes=config.lanes, nms_threshold=config.nms_threshold,
                               device=device, progress=progress)
    groups = {name: score_sequences(members, config, coco_backend=coco_backend)
              for name, members in _groups(records).items()}
    return {"weights": str(weights), "split": config.split,
            "config": {"seqasr_thresholds": list(config.seqasr_thresholds), "seq_len": config.seq_len,
                       "skip_first_us": config.skip_first_us, "nms_threshold": config.nms_threshold},
            "time_s": round(time.perf_counter() - start, 2), "groups": groups}


def format_scores(result: dict[str, Any]) -> str:
    """Markdown table of :func:`evaluate_split`'s groups: AP, AP50, and SeqASR (%) per threshold."""
    if "groups" not in result:
        raise ShapeError("format_scores: expected evaluate_split's result")
    thresholds = result["config"]["seqasr_thresholds"]
    head = ["group", "sequences", "labels", "AP", "AP50"] + [f"SeqASR@{t:g} (%)" for t in thresholds]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, g in result["groups"].items():
        cells = [name, str(g["sequences"]), str(g["num_labels"]), f"{g['AP']:.3f}", f"{g['AP_50']:.3f}"]
        for t in thresholds:
            s = g["seqasr"][t]
            cells.append(f"{100 * s['seq_asr']:.1f} ({s['num_sequences'] - s['num_detected']}/"
                         f"{s['num_sequences']})")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
