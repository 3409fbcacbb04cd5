"""Crop DAVIS346 events to the RVT frame (346x260 -> 304x240), dropping the events outside.

The paper crops the DAVIS346's 346x260 output to RVT's 304x240 input; the offset is not stated, so the
default is the centred crop (origin x=21, y=10) and any other origin can be passed.
"""

from __future__ import annotations

import numpy as np

from davis_rig.errors import FormatError, ShapeError
from davis_rig.types import DAVIS346_HW, EVENT_DTYPE, RVT_HW

__all__ = ["center_crop_origin", "crop_events", "crop_origin_error"]


def center_crop_origin(sensor_hw: tuple[int, int] = DAVIS346_HW, frame_hw: tuple[int, int] = RVT_HW) -> tuple[int, int]:
    """Top-left ``(x0, y0)`` of the centred ``frame_hw`` window inside ``sensor_hw``, pixels.

    Args:
        sensor_hw: sensor (height, width), px.
        frame_hw: crop (height, width), px.

    Returns:
        ``(x0, y0)``; ``(21, 10)`` for DAVIS346 → RVT.

    Raises:
        ShapeError: the crop is larger than the sensor.
    """
    if frame_hw[0] > sensor_hw[0] or frame_hw[1] > sensor_hw[1]:
        raise ShapeError(f"crop {frame_hw} (h, w) does not fit the sensor {sensor_hw}")
    return (sensor_hw[1] - frame_hw[1]) // 2, (sensor_hw[0] - frame_hw[0]) // 2


def crop_origin_error(
    origin_xy, *, frame_hw: tuple[int, int] = RVT_HW, sensor_hw: tuple[int, int] = DAVIS346_HW
) -> str | None:
    """Why the ``frame_hw`` crop at ``origin_xy`` leaves the sensor, or ``None`` when it fits.

    The one check of a crop origin: the commands, the labeler, the evaluation, the viewer and the exports all ask it
    and raise their own error type with this text.

    Args:
        origin_xy: crop top-left ``(x0, y0)`` on the sensor, px.
        frame_hw: crop (height, width), px; default the RVT frame (240, 304).
        sensor_hw: sensor (height, width), px; default the DAVIS346 (260, 346).

    Returns:
        ``None`` when ``0 <= x0 <= W - w`` and ``0 <= y0 <= H - h``, else a sentence naming the crop, the sensor and
        the origins that fit.
    """
    x0, y0 = (int(v) for v in origin_xy)
    (height, width), (sensor_h, sensor_w) = frame_hw, sensor_hw
    if 0 <= x0 <= sensor_w - width and 0 <= y0 <= sensor_h - height:
        return None
    return (f"the {width}x{height} crop at ({x0}, {y0}) leaves the {sensor_w}x{sensor_h} sensor; X must be in "
            f"[0, {sensor_w - width}] and Y in [0, {sensor_h - height}]")


def crop_events(
    events: np.ndarray,
    origin_xy: tuple[int, int] | None = None,
    *,
    frame_hw: tuple[int, int] = RVT_HW,
    sensor_hw: tuple[int, int] = DAVIS346_HW,
) -> np.ndarray:
    """Keep the events inside a ``frame_hw`` window and shift them to its origin (a new array).

    Args:
        events: structured array [N] with :data:`~davis_rig.types.EVENT_DTYPE` fields ``t, x, y, p``.
        origin_xy: window top-left ``(x0, y0)`` on the sensor, px; default :func:`center_crop_origin`.
        frame_hw: window (height, width), px; default the RVT frame (240, 304).
        sensor_hw: sensor (height, width), px, used for the default origin and the bounds check.

    Returns:
        EVENT_DTYPE array [M ≤ N] with ``x - x0``, ``y - y0``, same order; the input is not modified.

    Raises:
        FormatError: ``events`` is not a structured array with ``t, x, y, p``.
        ShapeError: the window does not fit the sensor.
    """
    if not isinstance(events, np.ndarray) or events.dtype.names is None or not {"t", "x", "y", "p"} <= set(
        events.dtype.names
    ):
        raise FormatError(f"events: expected a structured EVENT_DTYPE array, got {getattr(events, 'dtype', type(events))}")
    if origin_xy is None:
        origin_xy = center_crop_origin(sensor_hw, frame_hw)
    x0, y0 = (int(v) for v in origin_xy)
    if (reason := crop_origin_error((x0, y0), frame_hw=frame_hw, sensor_hw=sensor_hw)) is not None:
        raise ShapeError(reason)
    x = events["x"].astype(np.int64)
    y = events["y"].astype(np.int64)
    inside = (x >= x0) & (x < x0 + frame_hw[1]) & (y >= y0) & (y < y0 + frame_hw[0])
    out = np.empty(int(inside.sum()), dtype=EVENT_DTYPE)
    out["t"] = events["t"][inside]
    out["x"] = x[inside] - x0
    out["y"] = y[inside] - y0
    out["p"] = events["p"][inside]
    return out
