"""Physical evaluation (the paper's Table 3): session.h5 → 50 ms windows → RVT (ONNX) → AP and SeqASR per threshold.

Pipeline of one recording (:func:`score_session`, then :func:`compute_metrics`):

1. **Windows** (:mod:`davis_rig.evaluation.windows`). Window ends on a fixed grid ``t0 + k · 50 ms`` (k = 1, 2, …)
   from the session's ``t_offset`` (the first event's millisecond) to past the last event and the last label;
   each window holds the events with ``end − 50 ms ≤ t ≤ end`` (RVT's inclusive windows,
   :mod:`davis_rig.events.histogram`).
2. **Events.** Read chunk by chunk (``chunk_windows`` windows per read), cropped to 304×240 at the labels'
   crop origin (default: centred; the origin stored by ``davis-label`` is used so events and labels share one
   frame), timestamps made non-decreasing like RVT's reader, stacked histograms (10 bins, cutoff 10).
3. **RVT.** One ONNX step per window, the LSTM states carried from the first window of the recording (zero
   states there), the official post-processing (obj · class ≥ threshold, class-wise NMS 0.45) of each window's
   output at every threshold at once (exactly equal to one run per threshold; NMS work is shared where that is
   exact). Reading + histograms, the step (itself split into three parts that run on consecutive windows side by
   side: only its recurrent middle waits for the previous window) and post-processing overlap in threads.
4. **Labels → windows.** A label at time ``t`` (APS exposure middle) belongs to the window with
   ``end − 50 ms < t ≤ end`` (the first window ending at or after it). That window's detections are stamped with
   the label time, and label-time matching is exact by default (``time_tol_us = 0``, the right setting for these
   per-window detections: APS labels are 40 ms apart). A tolerance > 0 (Prophesee matching,
   :data:`davis_rig.metrics.ap.TIME_TOL_US`, meant for detections at sparse times) pools the copies stamped on
   neighbouring label times, which count as false positives (a perfect detector: AP 1.0 at 0, ≈ 0.37 at 50 ms).
5. **AP** (:mod:`davis_rig.metrics.ap`): Prophesee filter on labels and detections (``t > t0 + skip_first_us``
   with 0.5 s by default like RVT, diagonal ≥ 30 px, sides ≥ 10 px), one COCO image per label time, pedestrian
   COCO mAP@[.5:.95] with the class probability as ranking score.
6. **SeqASR** (:mod:`davis_rig.metrics.seqasr`): windows that hold a (filtered) pedestrian label, runs of them
   cut into sequences of ``seq_len`` windows (non-overlapping by default); ``paper`` = any pedestrian box in the
   sequence, ``strict`` = a pedestrian box with IoU ≥ 0.5 to a label of its window.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from davis_rig.errors import ConfigError, FormatError, ModelFormatError, SessionError, ShapeError
from davis_rig.evaluation.windows import event_chunks, label_windows, labelled_window_grid
from davis_rig.events.histogram import WINDOW_US
from davis_rig.metrics.ap import MIN_DIAG_PX, MIN_SIDE_PX, SKIP_FIRST_US
from davis_rig.types import BBOX_DTYPE, DAVIS346_HW, PAPER_THRESHOLDS, PEDESTRIAN_CLASS_ID, RVT_HW, RVT_NMS_IOU

__all__ = ["EvalSettings", "RecordingResult", "SessionScores", "PAPER_THRESHOLDS", "compute_metrics",
           "distinct_names", "evaluate_sessions", "is_labelled", "labels_provenance", "score_session",
           "scoring_crop_origin"]



@dataclass(frozen=True)
class EvalSettings:
    """Every setting of the physical evaluation (stored in the report).

    Attributes:
        thresholds: RVT post-processing confidence thresholds (obj · class prob).
        seq_len: windows per SeqASR sequence (paper, physical: 10).
        seq_stride: windows between sequence starts; ``None`` = ``seq_len`` (non-overlapping).
        window_us: window duration, µs (RVT Gen1: 50 000).
        crop_origin_xy: crop origin on the sensor; ``None`` = the labels' stored origin, else centred.
        skip_first_us: ignore labels/detections with ``t <= t0 + skip_first_us`` for AP and for the SeqASR
            sequences; ``None`` = keep all.
        time_tol_us: AP label-time matching tolerance, µs: a label image gets the detections stamped within
            ``±time_tol_us`` of its time. 0 (default, the right setting for per-window detections) = only its own
            window's; > 0 pools the detections of neighbouring windows, which count as false positives.
        min_diag_px, min_side_px: Prophesee box filter.
        nms_threshold: RVT NMS IoU threshold.
        strict_iou: IoU of the strict SeqASR variant.
        coco_backend: ``"faster_coco_eval"`` or ``"pycocotools"``.
        chunk_windows: windows per event read.
        intra_op_threads: onnxruntime threads of the recurrent part of the pipelined step (``None``: 2, or 1 on a
            one-core machine; its other two parts run on one thread each), or of the whole step when it is not
            pipelined (``None``: onnxruntime's default, the physical cores).
        pipeline: run the RVT step as three parts of consecutive windows side by side (:func:`score_session`)
            when the graph splits; ``False``: whole steps, one after the other (same results).
        gif_windows: keep the event images of the first this many windows for the annotated GIF (0: none).
    """

    thresholds: tuple[float, ...] = PAPER_THRESHOLDS
    seq_len: int = 10
    seq_stride: int | None = None
    window_us: int = WINDOW_US
    crop_origin_xy: tuple[int, int] | None = None
    skip_first_us: int | None = SKIP_FIRST_US
    time_tol_us: int = 0
    min_diag_px: float = float(MIN_DIAG_PX)
    min_side_px: float = float(MIN_SIDE_PX)
    nms_threshold: float = RVT_NMS_IOU
    strict_iou: float = 0.5
    coco_backend: str = "faster_coco_eval"
    chunk_windows: int = 20
    intra_op_threads: int | None = None
    gif_windows: int = 0
    pipeline: bool = True

    def __post_init__(self):
        if not self.thresholds or any(not 0.0 <= float(t) <= 1.0 for t in self.thresholds):
            raise ConfigError("thresholds", f"expected values in [0, 1], got {tuple(self.thresholds)}")
        if int(self.seq_len) < 1:
            raise ConfigError("seq_len", f"expected >= 1, got {self.seq_len}")
        if self.seq_stride is not None and int(self.seq_stride) < 1:
            raise ConfigError("seq_stride", f"expected >= 1, got {self.seq_stride}")
        if self.skip_first_us is not None and int(self.skip_first_us) < 0:
            raise ConfigError("skip_first_us", f"expected >= 0 or None, got {self.skip_first_us}")
        if int(self.time_tol_us) < 0:
            raise ConfigError("time_tol_us", f"expected >= 0, got {self.time_tol_us}")
        if int(self.window_us) <= 0:
            raise ConfigError("window_us", f"expected > 0, got {self.window_us}")
        if int(self.chunk_windows) < 1:
            raise ConfigError("chunk_windows", f"expected >= 1, got {self.chunk_windows}")
        if self.intra_op_threads is not None and int(self.intra_op_threads) < 1:
            raise ConfigError("intra_op_threads", f"expected >= 1 or None, got {self.intra_op_threads}")
        if int(self.gif_windows) < 0:
            raise ConfigError("gif_windows", f"expected >= 0, got {self.gif_windows}")


@dataclass
class SessionScores:
    """RVT output of one recording.

    Attributes:
        path: the session.
        t0_us: start of the window grid, device µs.
        window_end_us: int64 [T], device µs.
        detections: ``{threshold: [T entries: float32 [K, 7] or None]}`` (crop px).
        labels: BBOX_DTYPE [L] (crop px, device µs), as stored, sorted by time.
        crop_origin_xy: the crop used.
        num_events: events read (before the crop), each once.
        timings_s: busy seconds of the stages ``read``, ``histogram``, ``inference``, ``postprocess`` (they
            overlap) and ``wall``, the seconds :func:`score_session` took.
        event_images: int16 [G, 240, 304] ON − OFF counts of the first windows (for the GIF), maybe empty.
        labels_attrs: the ``/labels`` attributes (labeler provenance, see :func:`labels_provenance`).
    """

    path: Path
    t0_us: int
    window_end_us: np.ndarray
    detections: dict
    labels: np.ndarray
    crop_origin_xy: tuple[int, int]
    num_events: int
    timings_s: dict
    event_images: np.ndarray = field(default_factory=lambda: np.zeros((0, *RVT_HW), np.int16))
    labels_attrs: dict = field(default_factory=dict)


@dataclass
class RecordingResult:
    """Metrics of one recording: ``metrics[threshold]`` dicts (AP keys, SeqASR paper/strict, counts)."""

    name: str
    path: str
    metrics: dict
    info: dict

    def as_dict(self) -> dict:
        """JSON-ready dict (thresholds as string keys)."""
        return {"name": self.name, "path": self.path, "info": self.info,
                "metrics": {repr(float(t)): m for t, m in self.metrics.items()}}


def labels_provenance(attrs: dict) -> dict:
    """Who made the labels, for the report: the ``/labels`` attributes with ``settings`` decoded.

    Args:
        attrs: :meth:`~davis_rig.session.SessionReader.labels_attrs` (``davis-label`` stores ``labeler``,
            ``labeler_version``, ``created_utc``, ``source`` (model file name), ``settings`` (JSON text: model,
            layout, thresholds, classes, crop) and ``crop_origin_x/y``).

    Returns:
        A new dict: every attribute, ``settings`` parsed into a dict when it is JSON text (else kept as stored).
    """
    out = dict(attrs)
    if isinstance(out.get("settings"), str):
        try:
            out["settings"] = json.loads(out["settings"])
        except json.JSONDecodeError:
            pass  # labels written by another tool: keep its text
    return out


def _open_checked(path: Path):
    from davis_rig.session import SessionReader

    reader = SessionReader(path).open()
    try:
        if reader.num_events == 0:
            raise SessionError(f"{path}: the session has no events to score")
        hw = tuple(reader.frames.data.shape[1:]) if len(reader.frames) else DAVIS346_HW
        layout = reader.device_info.get("layout")
        layout = layout if isinstance(layout, dict) else {}  # missing, or damaged: the frames' size decides
        cols, rows = layout.get("dvs_size_columns", DAVIS346_HW[1]), layout.get("dvs_size_rows", DAVIS346_HW[0])
        if hw != DAVIS346_HW or (cols, rows) != (DAVIS346_HW[1], DAVIS346_HW[0]):
            raise SessionError(f"{path}: sensor {cols}x{rows}, frames {hw[1]}x{hw[0]} (w x h); expected a DAVIS346 "
                               f"recording ({DAVIS346_HW[1]}x{DAVIS346_HW[0]})")
        labels = reader.labels()
        if labels is None:
            raise SessionError(f"{path}: the session has no /labels: add --yolo MODEL.onnx to label it in this run "
                               f"(or run `davis-label {path} --yolo MODEL.onnx` first)")
        if len(labels) == 0:
            raise SessionError(f"{path}: /labels is empty (the labeler found no pedestrian); nothing to evaluate")
    except BaseException:
        reader.close()
        raise
    return reader, np.sort(labels, order="t", kind="stable")


def is_labelled(path: str | Path) -> bool:
    """Whether the session has a ``/labels`` group (possibly empty).

    Raises:
        SessionError: the file is missing or not a readable session.
    """
    from davis_rig.session import SessionReader

    with SessionReader(path) as reader:
        return reader.labels() is not None


def distinct_names(paths: Sequence[str | Path]) -> list[str]:
    """Column names of recordings: the file stem, with as many parent folders as it takes to tell equal stems apart.

    ``a.h5, d1/case.h5, d2/case.h5`` -> ``a, d1/case, d2/case``; the same file given twice keeps its full path and a
    ``#2`` suffix on the repeat.
    """
    parts = [Path(p).with_suffix("").parts or (str(p),) for p in paths]
    depth = [1] * len(parts)
    while True:
        names = ["/".join(pp[-d:]) for pp, d in zip(parts, depth)]
        clashing = [i for i, name in enumerate(names) if names.count(name) > 1 and depth[i] < len(parts[i])]
        if not clashing:
            break
        for i in clashing:
            depth[i] += 1
    seen: dict[str, int] = {}
    out = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        out.append(name if seen[name] == 1 else f"{name}#{seen[name]}")
    return out


def scoring_crop_origin(path, requested: tuple[int, int] | None, labels_attrs: dict) -> tuple[int, int]:
    """The crop origin to score ``path`` with: ``requested``, else the labels' stored one, else centred.

    Args:
        path: the session (named in the messages).
        requested: the caller's origin (``EvalSettings.crop_origin_xy``, ``davis-view --crop-origin``) or ``None``.
        labels_attrs: the session's ``/labels`` attributes; the stored origin is read with
            :func:`~davis_rig.session.labels.labels_crop_origin` (both spellings).

    Raises:
        SessionError: ``requested`` differs from the origin the labels were made for, or the stored origin is
            unreadable or does not fit the sensor.
        ShapeError: the 304x240 crop at the requested origin does not fit the DAVIS346 sensor.
    """
    from davis_rig.events.crop import center_crop_origin, crop_origin_error
    from davis_rig.session.labels import labels_crop_origin

    stored = labels_crop_origin(labels_attrs, path)
    if requested is not None and stored is not None and tuple(requested) != stored:
        raise SessionError(f"{path}: the labels were made for crop origin {stored}, not "
                           f"{tuple(requested)}; re-label with davis-label --crop-origin or drop "
                           "the crop origin")
    x0, y0 = (int(v) for v in (requested or stored or center_crop_origin()))
    if (reason := crop_origin_error((x0, y0))) is not None:
        if requested is None:  # the file's own origin: the file is damaged
            raise SessionError(f"{path}: the labels' stored crop origin ({x0}, {y0}): {reason}")
        raise ShapeError(f"{path}: crop origin ({x0}, {y0}): {reason}")
    return x0, y0


def _windows(chunks, runner, totals: dict, gif: list):
    """Generator over the chunks' windows: each padded float32 histogram [1, 20, H, W] in order.

    Adds each chunk's events read to ``totals["events"]`` and its GIF images to ``gif``.
    """
    for _, hists, gif_part, num_read in chunks:
        totals["events"] += num_read
        gif.extend(gif_part)
        for hist in hists:
            yield runner.prepare_histogram(hist[None])


def _pipelined_decoded(windows, split, initial_states, busy_s: dict):
    """Decoded outputs of consecutive windows, three model parts in three threads (see :func:`score_session`).

    ``pre`` runs in one background thread (which also pulls ``windows``), ``recur`` in a second one, ``head``
    in the caller's; at most two windows wait between two parts. Adds each part's busy seconds to
    ``busy_s["pre"]``, ``busy_s["recur"]``, ``busy_s["head"]`` (one thread writes each key).
    """
    from contextlib import closing

    from davis_rig.evaluation.prefetch import prefetch

    def timed(name, part, *args):
        tic = time.perf_counter()
        out = part(*args)
        busy_s[name] += time.perf_counter() - tic
        return out

    def pre():
        for x in windows:
            yield timed("pre", split.pre, x)

    def recur():
        states = initial_states
        with closing(prefetch(pre(), depth=2)) as x1s:
            for x1 in x1s:
                states = timed("recur", split.recur, x1, states)
                yield states

    with closing(prefetch(recur(), depth=2)) as all_states:
        for states in all_states:
            yield timed("head", split.head, states)


def score_session(path, runner, settings: EvalSettings, *, progress: Callable | None = None) -> SessionScores:
    """Run RVT over a labelled session window by window (states carried) and post-process per threshold.

    The stages overlap in threads (onnxruntime releases the GIL): one thread reads and histograms the next chunk
    of windows; with ``settings.pipeline`` and a graph that splits (:meth:`RVTOnnxRunner.split`), the RVT step
    runs as three parts — stage 1's non-recurrent front (``pre``) of window k+1, the recurrent part of window k
    and the PAFPN + head of window k−1 side by side, in two threads and the calling one (one onnxruntime thread
    each for ``pre`` and ``head``, ``settings.intra_op_threads`` (default 2) for the recurrent part, which alone
    waits for the previous window); otherwise the calling thread runs whole steps. A last thread post-processes
    each step's output at all thresholds at once (:func:`~davis_rig.models.rvt.postprocess.postprocess_thresholds`,
    exactly equal to one official post-processing per threshold). The results do not depend on the overlap: the
    split parts are the graph's own nodes, chained as in the whole graph.

    Args:
        path: session.h5 with ``/labels``.
        runner: a :class:`~davis_rig.models.rvt.ort_runner.RVTOnnxRunner`.
        settings: :class:`EvalSettings`.
        progress: ``progress(total=T, desc=...)`` returning an object with ``update(n)`` and ``close()``
            (e.g. ``tqdm``); ``None`` for silence.

    Returns:
        :class:`SessionScores`; ``timings_s`` holds each stage's busy seconds (``read``, ``histogram``,
        ``inference`` (all model parts), ``postprocess``) and ``wall`` (the stages overlap, so their sum
        exceeds it).

    Raises:
        SessionError: unreadable or empty (0-byte) session file, no events, no labels, not a DAVIS346 recording,
            ``settings.crop_origin_xy`` not the labels' crop origin.
        ShapeError: the crop at the origin does not fit the sensor.
        ModelFormatError: the detector's output is NaN or inf in every window.
    """
    from contextlib import closing

    from davis_rig.evaluation.prefetch import prefetch

    path = Path(path)
    wall = time.perf_counter()
    reader, labels = _open_checked(path)
    timings = {"read": 0.0, "histogram": 0.0, "inference": 0.0, "postprocess": 0.0}
    try:
        labels_attrs = reader.labels_attrs()
        origin = scoring_crop_origin(path, settings.crop_origin_xy, labels_attrs)
        t0 = int(reader.t_offset_us)
        labels, ends = labelled_window_grid(reader, labels, settings.window_us, path)
        thresholds = sorted({float(th) for th in settings.thresholds})
        split = _split_or_none(runner, settings)
        gif: list = []
        totals = {"events": 0}
        damage = {"outside_sensor": 0}
        busy = {"step": 0.0, "pre": 0.0, "recur": 0.0, "head": 0.0}
        bar = progress(total=len(ends), desc=path.name) if progress is not None else None
        chunks = event_chunks(reader, ends, origin, window_us=settings.window_us, chunk_windows=settings.chunk_windows,
                              gif_windows=settings.gif_windows, timings=timings, damage=damage)
        with closing(prefetch(chunks, depth=2)) as chunks:
            windows = _windows(chunks, runner, totals, gif)
            steps = (_whole_steps(windows, runner, busy) if split is None
                     else _pipelined_decoded(windows, split, runner.initial_states(1), busy))
            with closing(steps):
                detections = _postprocessed(steps, thresholds, settings.nms_threshold, settings.chunk_windows,
                                            timings, bar, totals)
        timings["inference"] = sum(busy.values())
        if bar is not None:
            bar.close()
    finally:
        reader.close()
    timings["wall"] = time.perf_counter() - wall
    if damage["outside_sensor"]:
        warnings.warn(f"{path.name}: {damage['outside_sensor']} events lie outside the {DAVIS346_HW[1]}x"
                      f"{DAVIS346_HW[0]} sensor (damaged coordinates) and are not scored", stacklevel=2)
    if totals["nonfinite_windows"] == len(ends):
        raise ModelFormatError(f"{path.name}: the detector's output holds NaN or inf in every one of the {len(ends)} "
                               "windows: the model is broken (scored, it would read as AP 0 and SeqASR 100 %)")
    if totals["nonfinite_windows"]:
        warnings.warn(f"{path.name}: the detector's output holds NaN or inf in {totals['nonfinite_windows']} of "
                      f"{len(ends)} windows (no box can come from those anchors): check the model", stacklevel=2)
    return SessionScores(path=path, t0_us=t0, window_end_us=ends, detections=detections, labels=labels,
                         crop_origin_xy=tuple(int(v) for v in origin), num_events=totals["events"],
                         timings_s=timings, event_images=np.asarray(gif, np.int16).reshape(-1, *RVT_HW),
                         labels_attrs=labels_attrs)


def _whole_steps(windows, runner, busy_s: dict):
    """Decoded outputs of consecutive windows, whole RVT steps in the caller's thread (states carried from zero);
    adds their busy seconds to ``busy_s["step"]``."""
    states = None
    for x in windows:
        tic = time.perf_counter()
        decoded, states = runner.step(x, states)
        busy_s["step"] += time.perf_counter() - tic
        yield decoded


def _postprocessed(steps, thresholds: list[float], nms_threshold: float, backlog: int, timings: dict,
                   bar, totals: dict) -> dict:
    """Post-process every decoded step at all ``thresholds`` at once in a background thread, at most ``backlog``
    steps behind the model.

    Returns:
        ``{threshold: [one entry per window, in order: float32 [K, 7] or None]}``. Adds the busy seconds to
        ``timings["postprocess"]``, counts the steps whose output holds NaN or ±inf in
        ``totals["nonfinite_windows"]`` (their anchors pass no threshold: a broken model would score AP 0 in
        silence) and advances ``bar`` (or ``None``) by one per step.
    """
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    from davis_rig.models.rvt.postprocess import postprocess_thresholds

    detections = {th: [] for th in thresholds}
    totals["nonfinite_windows"] = 0

    def post(decoded):
        tic = time.perf_counter()
        if not np.isfinite(decoded).all():
            totals["nonfinite_windows"] += 1
        out = postprocess_thresholds(decoded, thresholds, nms_threshold)
        timings["postprocess"] += time.perf_counter() - tic
        return out

    def collect(future) -> None:
        out = future.result()
        for th in thresholds:
            detections[th].append(out[th][0])

    pending = deque()
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="postprocess") as post_pool:
        for decoded in steps:
            pending.append(post_pool.submit(post, decoded))
            while len(pending) > backlog or (pending and pending[0].done()):
                collect(pending.popleft())
            if bar is not None:
                bar.update(1)
        while pending:
            collect(pending.popleft())
    return detections


def _split_or_none(runner, settings: EvalSettings):
    """``runner.split(...)`` when ``settings.pipeline`` asks for it and the graph splits, else ``None``."""
    if not settings.pipeline:
        return None
    try:
        return runner.split(1, settings.intra_op_threads or min(2, os.cpu_count() or 1), 1)
    except ModelFormatError:  # a graph of another layout: run it whole
        return None


def compute_metrics(scores: SessionScores, settings: EvalSettings) -> dict:
    """AP and SeqASR per threshold from :class:`SessionScores`.

    Returns:
        ``{threshold: {"AP", "AP_50", …, "seq_asr", "seq_asr_strict", "num_sequences", "num_detected",
        "num_detected_strict", "num_images", "num_labels", "num_detections", "windows_with_pedestrian_boxes",
        "longest_labelled_run"}}``; ``longest_labelled_run`` is the longest run of consecutive windows with a
        (filtered) label, in windows: with ``num_sequences == 0`` it is shorter than ``seq_len`` (SeqASR NaN).
    """
    from davis_rig.metrics.ap import coco_ap, detections_to_boxes, filter_boxes, match_times
    from davis_rig.metrics.seqasr import (label_sequences, longest_run, seq_asr, windows_detected,
                                          windows_with_labels)

    ends = scores.window_end_us
    skip = None if settings.skip_first_us is None else scores.t0_us + int(settings.skip_first_us)
    labels = filter_boxes(scores.labels[scores.labels["class_id"] == PEDESTRIAN_CLASS_ID], skip_until_us=skip,
                          min_diag_px=settings.min_diag_px, min_side_px=settings.min_side_px)
    label_win = label_windows(labels, ends, settings.window_us)
    labels = labels[label_win >= 0]
    label_win = label_win[label_win >= 0]
    label_times = np.unique(labels["t"].astype(np.int64))
    time_win = label_windows(np.array(label_times, dtype=[("t", "<i8")]), ends, settings.window_us)
    labelled = windows_with_labels(ends, labels["t"].astype(np.int64), settings.window_us)
    sequences = label_sequences(labelled, settings.seq_len, settings.seq_stride)
    xyxy = np.stack([labels["x"], labels["y"], labels["x"] + labels["w"], labels["y"] + labels["h"]], 1)
    per_window_labels = [xyxy[label_win == i] for i in range(len(ends))]
    results = {}
    for th, dets in scores.detections.items():
        dt_parts = [detections_to_boxes(dets[w], t) for t, w in zip(label_times.tolist(), time_win.tolist())]
        dt = np.concatenate(dt_parts) if dt_parts else np.zeros(0, BBOX_DTYPE)
        dt = filter_boxes(dt, skip_until_us=skip, min_diag_px=settings.min_diag_px,
                          min_side_px=settings.min_side_px)
        _, gts, dts = match_times(labels, dt, time_tol_us=settings.time_tol_us)
        ap = coco_ap(gts, dts, category=PEDESTRIAN_CLASS_ID, backend=settings.coco_backend)
        paper = seq_asr(windows_detected(dets, mode="paper"), sequences, "paper")
        strict = seq_asr(windows_detected(dets, mode="strict", labels_xyxy=per_window_labels,
                                          iou_threshold=settings.strict_iou), sequences, "strict")
        results[float(th)] = dict(ap) | {
            "seq_asr": paper.seq_asr, "seq_asr_strict": strict.seq_asr, "num_sequences": paper.num_sequences,
            "num_detected": paper.num_detected, "num_detected_strict": strict.num_detected,
            "num_images": len(gts), "num_labels": int(len(labels)), "num_detections": int(sum(len(d) for d in dts)),
            "windows_with_pedestrian_boxes": int(windows_detected(dets, mode="paper").sum()),
            "longest_labelled_run": longest_run(labelled),
        }
    return results


def evaluate_sessions(
    paths: Sequence[str | Path],
    model: str | Path | None = None,
    settings: EvalSettings = EvalSettings(),
    *,
    names: Sequence[str] | None = None,
    progress: Callable | None = None,
) -> tuple[list[RecordingResult], list[SessionScores]]:
    """Evaluate one or more labelled recordings with one RVT ONNX model.

    Args:
        paths: session files (each needs ``/labels``).
        model: RVT step ONNX; ``None`` = :func:`davis_rig.models.default_detector_path`.
        settings: :class:`EvalSettings`.
        names: column names (default: :func:`distinct_names` of the paths); must be distinct.
        progress: see :func:`score_session`.

    Returns:
        ``(results, scores)``, one each per recording.

    Raises:
        SessionError, ModelFormatError, MissingDependencyError: see :func:`score_session` and the runner.
        ShapeError: the crop at a recording's origin does not fit the sensor. Every session, its crop origin and
            the model are checked before the first recording is scored.
    """
    from davis_rig.models import default_detector_path
    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    paths = [Path(p) for p in paths]
    if not paths:
        raise ConfigError("paths", "no session given")
    if names is not None and len(names) != len(paths):
        raise ConfigError("names", f"{len(names)} names for {len(paths)} recordings")
    names = list(names) if names is not None else distinct_names(paths)
    if len(set(names)) != len(names):
        raise ConfigError("names", f"every recording needs its own name, got {', '.join(names)}")
    for p in paths:  # validate every file and its crop origin before the (slow) scoring starts
        reader, _ = _open_checked(p)
        try:
            scoring_crop_origin(p, settings.crop_origin_xy, reader.labels_attrs())
        finally:
            reader.close()
    model_path = Path(model) if model is not None else default_detector_path()
    if not model_path.is_file():
        raise FormatError(f"{model_path}: no such RVT ONNX model")
    runner = RVTOnnxRunner(model_path, intra_op_threads=settings.intra_op_threads)
    results, all_scores = [], []
    for i, p in enumerate(paths):
        scores = score_session(p, runner, settings, progress=progress)
        tic = time.perf_counter()
        metrics = compute_metrics(scores, settings)
        scores.timings_s["metrics"] = time.perf_counter() - tic
        info = {"model": str(model_path), "crop_origin_xy": list(scores.crop_origin_xy), "t0_us": scores.t0_us,
                "num_windows": int(len(scores.window_end_us)), "num_events": scores.num_events,
                "num_labels_stored": int(len(scores.labels)),
                "labels_provenance": labels_provenance(scores.labels_attrs),
                "duration_s": float(len(scores.window_end_us) * settings.window_us / 1e6),
                "timings_s": dict(scores.timings_s)}
        results.append(RecordingResult(name=names[i], path=str(p), metrics=metrics, info=info))
        all_scores.append(scores)
    return results, all_scores


def settings_dict(settings: EvalSettings) -> dict:
    """JSON-ready dict of the settings."""
    return json.loads(json.dumps(asdict(settings)))
