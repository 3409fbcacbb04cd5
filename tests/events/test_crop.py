"""Tests for cropping DAVIS346 events to the RVT frame and the monotonic-time correction."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import FormatError, ShapeError
from davis_rig.events import (center_crop_origin, crop_events, crop_origin_error, monotonic_timestamps,
                              stacked_histogram)
from davis_rig.types import EVENT_DTYPE, make_events


def test_center_crop_origin_for_davis346_to_rvt():
    assert center_crop_origin() == (21, 10)
    assert center_crop_origin((260, 346), (260, 346)) == (0, 0)
    with pytest.raises(ShapeError, match="does not fit"):
        center_crop_origin((100, 100), (240, 304))


def test_crop_keeps_inside_events_shifted_in_order():
    events = make_events(
        t_us=[0, 1, 2, 3, 4, 5],
        x=[21, 20, 324, 325, 100, 345],
        y=[10, 10, 249, 100, 9, 259],
        p=[1, 0, 1, 0, 1, 1],
    )
    before = events.copy()
    out = crop_events(events)
    assert out.dtype == EVENT_DTYPE
    np.testing.assert_array_equal(out["t"], [0, 2])
    np.testing.assert_array_equal(out["x"], [0, 303])
    np.testing.assert_array_equal(out["y"], [0, 239])
    np.testing.assert_array_equal(out["p"], [1, 1])
    np.testing.assert_array_equal(events, before)
    hist = stacked_histogram(out["x"], out["y"], out["t"], out["p"])  # fits the RVT frame
    assert int(hist.sum()) == 2


def test_crop_with_explicit_origin_and_errors():
    events = make_events([0, 1], [0, 303], [0, 239], [0, 1])
    out = crop_events(events, (0, 0))
    assert len(out) == 2
    with pytest.raises(ShapeError, match=r"the 304x240 crop at \(50, 0\) leaves the 346x260 sensor"):
        crop_events(events, (50, 0))
    with pytest.raises(FormatError, match="structured"):
        crop_events(np.zeros(3))


def test_crop_origin_error_bounds_are_inclusive():
    assert crop_origin_error((0, 0)) is None and crop_origin_error((42, 20)) is None  # 346 - 304, 260 - 240
    assert crop_origin_error((43, 0)) == ("the 304x240 crop at (43, 0) leaves the 346x260 sensor; X must be in "
                                          "[0, 42] and Y in [0, 20]")
    for origin in ((-1, 0), (0, -1), (0, 21)):
        assert crop_origin_error(origin) is not None
    assert crop_origin_error((1, 1), frame_hw=(2, 2), sensor_hw=(3, 3)) is None
    assert crop_origin_error((2, 1), frame_hw=(2, 2), sensor_hw=(3, 3)) is not None


def test_monotonic_timestamps_like_rvt_reader():
    t_us = np.array([5, 3, 7, 6, 6, 10], np.int64)
    np.testing.assert_array_equal(monotonic_timestamps(t_us), [5, 5, 7, 7, 7, 10])
    np.testing.assert_array_equal(t_us, [5, 3, 7, 6, 6, 10])
    assert monotonic_timestamps([]).shape == (0,)
