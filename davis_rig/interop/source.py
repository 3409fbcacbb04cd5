"""A session opened for export: its events chunk by chunk in the output's pixels, and its labels in the same pixels.

Every exporter reads through :class:`ExportSource`, so they agree on geometry:

- without a crop the output keeps the sensor's pixels (346x260 for a DAVIS346); the session's labels, stored in
  RVT-crop coordinates, are moved onto the sensor by their crop origin;
- with a crop (``crop=True``; always for RVT's Gen1 layout) the output is the 304x240 window at the crop origin:
  ``crop_origin_xy`` when given, else the origin stored with the labels, else the centred window — the same rule
  as ``davis-eval``. The labels then keep their coordinates exactly. A ``crop_origin_xy`` that differs from the
  labels' origin is refused (the labels were made for the other window).

Events are read in pieces of about :data:`CHUNK_EVENTS` (cut at whole milliseconds of ``ms_to_idx``, so a piece
can exceed it by one millisecond of events): memory stays bounded whatever the session's size.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Final

import numpy as np

from davis_rig.errors import ConfigError, FormatError, ShapeError
from davis_rig.events.crop import center_crop_origin, crop_events, crop_origin_error
from davis_rig.session import SessionReader
from davis_rig.session.info import dvs_hw_from_device_info
from davis_rig.session.labels import labels_crop_origin, shift_boxes
from davis_rig.types import RVT_HW

__all__ = ["CHUNK_EVENTS", "ExportSource"]

#: Events per read while exporting (13 bytes each in memory, plus the output's own buffer).
CHUNK_EVENTS: Final = 1 << 21


class ExportSource:
    """Read a session for export (a context manager; the file is opened read-only).

    Args:
        path: the session.h5.
        crop: write only the 304x240 RVT window (module docstring).
        crop_origin_xy: the window's top-left on the sensor, px; default the labels' origin, else centred.

    Attributes (after opening): ``reader`` (the :class:`~davis_rig.session.SessionReader`), ``sensor_hw`` (the
    session's pixel array, px), ``origin_xy`` (sensor pixel of the output's ``(0, 0)``), ``frame_hw`` (the output's
    (height, width), px), ``labels_origin_xy`` (the crop origin the session's labels are in, or ``None`` without
    labels), ``labels_attrs``.

    Raises (on open):
        SessionError: the session cannot be read.
        ConfigError: ``crop_origin_xy`` (field ``crop_origin_xy``) does not fit the sensor or differs from the
            labels' origin.
        FormatError: the sensor is smaller than the 304x240 window that ``crop`` asks for.
    """

    def __init__(self, path: str | os.PathLike, *, crop: bool = False, crop_origin_xy: tuple[int, int] | None = None):
        self.path = Path(path)
        self.crop = crop
        self.requested_origin = None if crop_origin_xy is None else tuple(int(v) for v in crop_origin_xy)
        self.reader: SessionReader | None = None

    def __enter__(self) -> "ExportSource":
        self.reader = SessionReader(self.path).open()
        try:
            self._resolve_geometry()
        except BaseException:
            self.reader.close()
            raise
        return self

    def __exit__(self, *exc_info) -> None:
        if self.reader is not None:
            self.reader.close()

    def _resolve_geometry(self) -> None:
        reader = self.reader
        self.sensor_hw = dvs_hw_from_device_info(reader.device_info)
        self._labels = reader.labels()
        self.labels_attrs = reader.labels_attrs()
        stored = labels_crop_origin(self.labels_attrs, self.path) if self._labels is not None else None
        try:
            centred = center_crop_origin(self.sensor_hw, RVT_HW)
        except ShapeError:
            centred = None
        self.labels_origin_xy = None if self._labels is None else (stored or centred or (0, 0))
        if not self.crop:
            self.origin_xy, self.frame_hw = (0, 0), tuple(self.sensor_hw)
            return
        if centred is None:
            raise FormatError(f"{self.path}: the {self.sensor_hw[1]}x{self.sensor_hw[0]} sensor is smaller than the "
                              f"{RVT_HW[1]}x{RVT_HW[0]} window the crop asks for")
        origin = self.requested_origin or stored or centred
        x0, y0 = origin
        if (reason := crop_origin_error(origin, sensor_hw=self.sensor_hw)) is not None:
            raise ConfigError("crop_origin_xy", reason)
        if self.requested_origin is not None and stored is not None and self.requested_origin != stored:
            raise ConfigError("crop_origin_xy", f"the labels were made for the crop at {stored}, not "
                                                f"{self.requested_origin}: leave the origin out or re-label")
        self.origin_xy, self.frame_hw = (int(x0), int(y0)), RVT_HW

    @property
    def t_offset_us(self) -> int:
        """Device µs of the session's first millisecond (``t_offset``)."""
        return self.reader.t_offset_us

    @property
    def num_events(self) -> int:
        """Events in the session (before any crop)."""
        return self.reader.num_events

    def event_chunks(self, max_events: int | None = None) -> Iterator[tuple[np.ndarray, int]]:
        """Yield ``(events, events_read)``: EVENT_DTYPE pieces in the output's pixels, in time order, and how many
        session events each piece was cut from (the crop drops some).

        Args:
            max_events: about how many session events to read per piece (module docstring); default
                :data:`CHUNK_EVENTS`.
        """
        max_events = CHUNK_EVENTS if max_events is None else int(max_events)
        reader = self.reader
        n = reader.num_events
        if n == 0:
            return
        ms = reader.ms_to_idx
        cuts = np.unique(np.searchsorted(ms, np.arange(0, n, max_events), side="right") - 1)
        t0 = reader.t_offset_us
        bounds = [t0 + 1000 * int(m) for m in np.maximum(cuts, 0)] + [None]
        read = 0
        for start, stop in zip(bounds[:-1], bounds[1:]):
            events = reader.events_between(start, stop if stop is not None else t0 + 1000 * (len(ms) + 1))
            read += len(events)
            if self.crop:
                yield crop_events(events, self.origin_xy, frame_hw=RVT_HW, sensor_hw=self.sensor_hw), len(events)
            else:
                yield events, len(events)
        if read != n:
            raise FormatError(f"{self.path}: read {read} events by their millisecond index, the file holds {n}")

    def labels(self) -> np.ndarray | None:
        """The session's labels in the output's pixels (BBOX_DTYPE [B], t device µs), or ``None`` without labels."""
        if self._labels is None:
            return None
        dx = self.labels_origin_xy[0] - self.origin_xy[0]
        dy = self.labels_origin_xy[1] - self.origin_xy[1]
        return shift_boxes(self._labels, dx, dy)
