"""Canonical data types shared by every layer: the event dtype, sensor geometry and the Gen1 protocol's numbers.

Conventions used throughout the toolkit:

- time is int64 microseconds (``t_us``) inside the library;
- sensor sizes are ``(height, width)`` in pixels;
- polarity is stored as ``{0, 1}`` (0 = OFF / brightness decrease, 1 = ON / increase);
- axis orders are fixed: ``(H, W)``, ``(B, C, H, W)``, ``(T, C, H, W)``.
"""

from __future__ import annotations

from typing import Final

import numpy as np

#: One DVS event: timestamp (µs, int64), column x, row y (pixels, origin upper-left), polarity {0,1}.
EVENT_DTYPE: Final = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])

#: DAVIS346 pixel array (DVS and APS share it), (height, width) in pixels.
DAVIS346_HW: Final = (260, 346)

#: The RVT / Gen1 input frame, (height, width) in pixels; DAVIS346 recordings are cropped to it.
RVT_HW: Final = (240, 304)

#: Prophesee / RVT bounding-box label dtype (t in µs, box in pixels of the 304x240 frame).
BBOX_DTYPE: Final = np.dtype(
    [
        ("t", "<u8"),
        ("x", "<f4"),
        ("y", "<f4"),
        ("w", "<f4"),
        ("h", "<f4"),
        ("class_id", "u1"),
        ("class_confidence", "<f4"),
        ("track_id", "<u4"),
    ]
)

#: Gen1 class ids used by RVT.
GEN1_CLASSES: Final = {0: "car", 1: "pedestrian"}
PEDESTRIAN_CLASS_ID: Final = 1
CAR_CLASS_ID: Final = 0

#: IoU above which RVT's post-processing suppresses a box of the same class (class-wise NMS, RVT's ``nms_thre``),
#: in evaluation, training validation, the attack and the viewer alike.
RVT_NMS_IOU: Final = 0.45

#: The paper's confidence thresholds (its Tables 1-3): the physical and the digital evaluation score at these.
PAPER_THRESHOLDS: Final = (0.001, 0.01, 0.1, 0.25)


def empty_events(n: int = 0) -> np.ndarray:
    """Return a zero-filled event array of length ``n`` with :data:`EVENT_DTYPE`."""
    return np.zeros(n, dtype=EVENT_DTYPE)


def make_events(t_us, x, y, p) -> np.ndarray:
    """Pack column arrays into one :data:`EVENT_DTYPE` array (copies; inputs are not modified).

    Args:
        t_us: timestamps, µs, shape [N].
        x: columns, pixels, shape [N].
        y: rows, pixels, shape [N].
        p: polarities in {0, 1} (negative values are clipped to 0), shape [N].

    Returns:
        Structured array [N] with :data:`EVENT_DTYPE`.
    """
    t_us = np.asarray(t_us)
    n = t_us.shape[0]
    for name, column in (("x", x), ("y", y), ("p", p)):
        if np.shape(column) != (n,):
            from davis_rig.errors import ShapeError

            raise ShapeError(f"{name}: expected shape ({n},), got {np.shape(column)}")
    events = np.empty(n, dtype=EVENT_DTYPE)
    events["t"] = t_us
    events["x"] = x
    events["y"] = y
    events["p"] = np.clip(np.asarray(p), 0, 1)
    return events
