"""One recording opened for viewing: its window grid, and what each window shows (events, APS, labels, boxes).

The viewer steps through a recording on ``davis-eval``'s window grid (:mod:`davis_rig.evaluation.windows`):
window ``k`` ends at ``t0 + (k + 1) · window_us`` (``t0`` = the session's ``t_offset``) and holds the events with
``end − window_us ≤ t ≤ end``; the grid runs past the last event and the last label. So a displayed frame is
exactly one RVT input window, its boxes are that window's detections and its labels those with
``end − window_us < t ≤ end``. The APS panel shows the latest frame whose exposure middle is ``≤ end``.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from davis_rig.errors import SessionError
from davis_rig.evaluation.windows import label_windows, labels_in_span, window_grid
from davis_rig.events.histogram import WINDOW_US
from davis_rig.types import BBOX_DTYPE, DAVIS346_HW
from davis_rig.viewer.render import LAYERS, ViewContent, event_counts, render_view

__all__ = ["RecordingView"]


class RecordingView:
    """A session opened read-only for the viewer (a context manager; the file stays open until :meth:`close`).

    Args:
        path: the session.h5.
        window_us: window length, µs (``davis-eval``'s default 50 ms).
        crop_origin_xy: the 304x240 crop; ``None`` = the labels' stored origin, else centred (as ``davis-eval``).

    Attributes:
        window_end_us: int64 [T], device µs. labels: BBOX_DTYPE [L] sorted by time (crop px).
        crop_origin_xy: the crop, px. detections: a detection source (:mod:`davis_rig.viewer.detections`) or
        ``None``; set by the caller.

    Raises:
        SessionError: unreadable session, or one with neither events nor APS frames.
        ShapeError: the crop does not fit the sensor.
    """

    def __init__(self, path, *, window_us: int = WINDOW_US, crop_origin_xy: tuple[int, int] | None = None):
        from davis_rig.evaluation.physical import scoring_crop_origin
        from davis_rig.session import SessionReader

        self.path = Path(path)
        self.window_us = int(window_us)
        self._lock = threading.Lock()  # one h5py file handle, used by the server's threads one at a time
        self._reader = SessionReader(self.path).open()
        try:
            reader = self._reader
            labels = reader.labels()
            self.labels = np.sort(labels, order="t", kind="stable") if labels is not None else np.zeros(0, BBOX_DTYPE)
            self.has_labels = labels is not None
            self.labels_attrs = reader.labels_attrs()
            frames = reader.frames
            self.frame_mid_us = np.zeros(0, np.int64)
            if len(frames):
                start, end = frames.times_us("t_start_exposure_us"), frames.times_us("t_end_exposure_us")
                self.frame_mid_us = start + (end - start) // 2
            if reader.num_events == 0 and not len(frames):
                raise SessionError(f"{self.path}: the session has neither events nor APS frames")
            if reader.num_events:
                t0 = int(reader.t_offset_us)
                t_last = t0 + reader.indexed_span_us()
            else:
                t0 = int(frames.times_us("t_start_of_frame_us")[0]) // 1000 * 1000
                t_last = int(frames.times_us("t_end_of_frame_us")[-1])
            if len(self.labels):
                self.labels = labels_in_span(self.labels, t0, t_last, self.path, refuse_none=False)
            if len(self.labels):
                t_last = max(t_last, int(self.labels["t"].max()))
            self.t0_us = t0
            self.window_end_us = window_grid(t0, t_last, self.window_us)
            self.crop_origin_xy = scoring_crop_origin(self.path, crop_origin_xy, self.labels_attrs)
            self._label_window = label_windows(self.labels, self.window_end_us, self.window_us)
            self.sensor_hw = tuple(reader.frames.data.shape[1:]) if len(frames) else DAVIS346_HW
        except BaseException:
            self._reader.close()
            raise
        self.detections = None

    # --- life cycle ---------------------------------------------------------------------------
    def close(self) -> None:
        """Close the session file."""
        with self._lock:
            self._reader.close()

    def __enter__(self) -> "RecordingView":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # --- per window ---------------------------------------------------------------------------
    @property
    def num_windows(self) -> int:
        """Windows in the grid."""
        return len(self.window_end_us)

    def _check(self, k: int) -> int:
        if not 0 <= int(k) < self.num_windows:
            raise IndexError(f"window {k} out of range 0..{self.num_windows - 1}")
        return int(k)

    def events(self, k: int) -> np.ndarray:
        """Events of window ``k`` (``end − window_us ≤ t ≤ end``), EVENT_DTYPE [N], sensor px, device µs."""
        end = int(self.window_end_us[self._check(k)])
        with self._lock:
            return self._reader.events_between(end - self.window_us, end + 1)

    def aps_index(self, k: int) -> int | None:
        """Index of the APS frame shown with window ``k`` (latest exposure middle ``≤`` its end), or ``None``."""
        end = int(self.window_end_us[self._check(k)])
        i = int(np.searchsorted(self.frame_mid_us, end, side="right")) - 1
        return i if i >= 0 else None

    def aps(self, k: int) -> tuple[np.ndarray, tuple[int, int]] | None:
        """``(pixels uint16 [h, w], (x0, y0))`` of the APS frame shown with window ``k``, or ``None``."""
        i = self.aps_index(k)
        if i is None:
            return None
        with self._lock:
            frame = self._reader.frames[i]
        return np.asarray(frame.pixels), (int(frame.position_x), int(frame.position_y))

    def labels_of(self, k: int) -> np.ndarray:
        """Labels of window ``k`` (``end − window_us < t ≤ end``), BBOX_DTYPE, crop px."""
        return self.labels[self._label_window == self._check(k)]

    def detections_of(self, k: int, threshold: float) -> np.ndarray | None:
        """Detections of window ``k`` (float32 [K, 7], crop px); ``None`` without a source or while unscored."""
        if self.detections is None:
            return None
        return self.detections.get(self._check(k), threshold)

    def content(self, k: int, *, layers=LAYERS, threshold: float | None = None, caption: str = "") -> ViewContent:
        """Everything window ``k`` shows (see :class:`~davis_rig.viewer.render.ViewContent`)."""
        layers = frozenset(layers)
        events = self.events(k) if "events" in layers else None
        counts = event_counts(events["x"], events["y"], events["p"], self.sensor_hw) if events is not None else None
        labels = self.labels_of(k)
        xyxy = np.stack([labels["x"], labels["y"], labels["x"] + labels["w"], labels["y"] + labels["h"]], 1)
        detections = self.detections_of(k, threshold) if threshold is not None else None
        return ViewContent(counts=counts, aps=self.aps(k) if "aps" in layers else None, labels_xyxy=xyxy,
                           detections=np.zeros((0, 7), np.float32) if detections is None else detections,
                           crop_origin_xy=self.crop_origin_xy, layers=layers, caption=caption,
                           sensor_hw=self.sensor_hw)

    def render(self, k: int, *, layers=LAYERS, threshold: float | None = None, caption: bool = False) -> np.ndarray:
        """Render window ``k`` (:func:`~davis_rig.viewer.render.render_view`); uint8 RGB [H, 2 W + gap, 3].

        Args:
            k: window index.
            layers: overlay layers to draw.
            threshold: which threshold's detections to draw (``None``: none).
            caption: write the recording name, time and window on the event panel (for exports).
        """
        text = ""
        if caption:
            end = int(self.window_end_us[self._check(k)])
            text = f"{self.path.name}  {(end - self.t0_us) / 1e6:.2f} s  #{k}"
        return render_view(self.content(k, layers=layers, threshold=threshold, caption=text))

    # --- summary ------------------------------------------------------------------------------
    def info(self) -> dict:
        """JSON-ready summary for the page."""
        with self._lock:
            num_events, num_frames = int(self._reader.num_events), len(self._reader.frames)
        return {
            "name": self.path.name, "num_windows": self.num_windows, "window_us": self.window_us,
            "t0_us": self.t0_us, "duration_s": self.num_windows * self.window_us / 1e6,
            "num_events": num_events, "num_frames": num_frames, "num_labels": int(len(self.labels)),
            "has_labels": self.has_labels, "crop_origin_xy": list(self.crop_origin_xy),
            "sensor_hw": list(self.sensor_hw),
            "detections": self.detections.describe() if self.detections is not None else None,
        }
