"""The RVT detections of every window of a scored recording, as one ``.npz`` file beside a ``davis-eval`` report.

``davis-eval --out DIR`` writes ``DIR/<name>.detections.npz`` per recording (:func:`write_detections`), so
the detections can be looked at later (``davis-view session.h5 --detections DIR``) without scoring again.
Layout (numpy ``.npz``, no pickled objects)::

    format          str      "davis_rig.window_detections"
    format_version  int64    1
    session         str      the session file the windows were read from (as given to davis-eval)
    name            str      the recording's column name in the report
    t0_us           int64    start of the window grid, device µs
    window_us       int64    window length, µs
    window_end_us   int64 [T] window ends, device µs (window i: end_i - window_us <= t <= end_i)
    crop_origin_xy  int64 [2] the 304x240 crop's top-left on the sensor, px
    thresholds      float64 [K] confidence thresholds, increasing
    boxes_<k>       float32 [M_k, 7] RVT rows (x1, y1, x2, y2, obj, class_conf, class_id), crop px, of threshold k
    window_<k>      int64 [M_k]  the window of each row (rows of one window in the post-processing's order)
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from davis_rig.errors import FormatError

__all__ = ["FORMAT_NAME", "WindowDetections", "read_detections", "write_detections"]

FORMAT_NAME = "davis_rig.window_detections"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class WindowDetections:
    """Per-window detections of one recording at one or more thresholds.

    Attributes:
        session: the session file the windows came from.
        name: the recording's name in the report.
        t0_us: start of the window grid, device µs.
        window_us: window length, µs.
        window_end_us: int64 [T], device µs.
        crop_origin_xy: the crop used, px.
        detections: ``{threshold: [T entries: float32 [K, 7] or None]}`` (crop px).
    """

    session: str
    name: str
    t0_us: int
    window_us: int
    window_end_us: np.ndarray
    crop_origin_xy: tuple[int, int]
    detections: dict

    @property
    def thresholds(self) -> list[float]:
        """The thresholds, increasing."""
        return sorted(self.detections)


def write_detections(scores, name: str, window_us: int, path: Path) -> Path:
    """Write the detections of a :class:`~davis_rig.evaluation.physical.SessionScores` to ``path`` (.npz).

    Args:
        scores: the scored recording.
        name: its name in the report.
        window_us: the window length it was scored with, µs.
        path: the file to write (its folder is created).

    Returns:
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    thresholds = sorted(float(t) for t in scores.detections)
    arrays = {
        "format": np.array(FORMAT_NAME), "format_version": np.int64(FORMAT_VERSION),
        "session": np.array(str(scores.path)), "name": np.array(str(name)),
        "t0_us": np.int64(scores.t0_us), "window_us": np.int64(window_us),
        "window_end_us": np.asarray(scores.window_end_us, np.int64),
        "crop_origin_xy": np.asarray(scores.crop_origin_xy, np.int64), "thresholds": np.array(thresholds, np.float64),
    }
    for k, threshold in enumerate(thresholds):
        per_window = scores.detections[threshold]
        rows = [np.asarray(d, np.float32).reshape(-1, 7) for d in per_window if d is not None]
        arrays[f"boxes_{k}"] = np.concatenate(rows) if rows else np.zeros((0, 7), np.float32)
        arrays[f"window_{k}"] = np.repeat(np.arange(len(per_window), dtype=np.int64),
                                          [0 if d is None else len(d) for d in per_window])
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


#: The first bytes of an .npz file (a zip archive).
_NPZ_MAGIC = b"PK\x03\x04"


def read_detections(path: Path) -> WindowDetections:
    """Read a file written by :func:`write_detections`.

    Raises:
        FormatError: the file is missing, not an ``.npz`` of this format, or inconsistent.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(len(_NPZ_MAGIC))
    except OSError as exc:
        raise FormatError(f"{path}: cannot read as a detections .npz ({exc.strerror or exc})") from exc
    if head != _NPZ_MAGIC:
        raise FormatError(f"{path}: not an .npz file (it starts with {head!r}); davis-eval --out writes "
                          "<name>.detections.npz files")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: cannot read as a detections .npz ({exc})") from exc
    if str(arrays.get("format", "")) != FORMAT_NAME:
        raise FormatError(f"{path}: not a {FORMAT_NAME} file (written by davis-eval --out)")
    try:
        if int(arrays["format_version"]) > FORMAT_VERSION:
            raise FormatError(f"{path}: format version {int(arrays['format_version'])} is newer than this "
                              f"toolkit's {FORMAT_VERSION}; upgrade davis_rig")
        ends = np.asarray(arrays["window_end_us"], np.int64)
        detections = {}
        for k, threshold in enumerate(np.asarray(arrays["thresholds"], np.float64).tolist()):
            boxes = np.asarray(arrays[f"boxes_{k}"], np.float32)
            windows = np.asarray(arrays[f"window_{k}"], np.int64)
            if boxes.ndim != 2 or boxes.shape[1] != 7 or windows.shape != (len(boxes),) or (
                    len(windows) and (windows.min() < 0 or windows.max() >= len(ends) or np.any(np.diff(windows) < 0))):
                raise FormatError(f"{path}: boxes_{k} / window_{k} are inconsistent with {len(ends)} windows")
            bounds = np.searchsorted(windows, np.arange(len(ends) + 1))
            detections[float(threshold)] = [boxes[a:b] if b > a else None
                                            for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist())]
        return WindowDetections(session=str(arrays["session"]), name=str(arrays["name"]),
                                t0_us=int(arrays["t0_us"]), window_us=int(arrays["window_us"]), window_end_us=ends,
                                crop_origin_xy=tuple(int(v) for v in arrays["crop_origin_xy"]), detections=detections)
    except KeyError as exc:
        raise FormatError(f"{path}: missing array {exc} of the {FORMAT_NAME} layout") from exc
