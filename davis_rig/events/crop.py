"""Crop DAVIS346 events to the RVT frame (346x260 -> 304x240), dropping the events outside.

The paper crops the DAVIS346's 346x260 output to RVT's 304x240 input; the offset is not stated, so the
default is the centred crop (origin x=21, y=10) and any other origin can be passed.
"""

from __future__ import annotations

import numpy as np

from davis_rig.errors import FormatError, ShapeError
from davis_rig.types import DAVIS346_HW, EVENT_DTYPE, RVT_HW

__all__ = ["center_crop_origin", "crop_events"]


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
    if x0 < 0 or y0 < 0 or x0 + frame_hw[1] > sensor_hw[1] or y0 + frame_hw[0] > sensor_hw[0]:
        raise ShapeError(
            f"crop window x in [{x0}, {x0 + frame_hw[1]}), y in [{y0}, {y0 + frame_hw[0]}) does not fit the "
            f"sensor {sensor_hw[1]}x{sensor_hw[0]} (w x h)"
        )
    x = events["x"].astype(np.int64)
    y = events["y"].astype(np.int64)
    inside = (x >= x0) & (x < x0 + frame_hw[1]) & (y >= y0) & (y < y0 + frame_hw[0])
    out = np.empty(int(inside.sum()), dtype=EVENT_DTYPE)
    out["t"] = events["t"][inside]
    out["x"] = x[inside] - x0
    out["y"] = y[inside] - y0
    out["p"] = events["p"][inside]
    return out
