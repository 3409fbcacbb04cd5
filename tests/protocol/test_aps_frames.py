"""ApsFrame container: validation, equality, libcaer frame timestamp."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import ShapeError
from davis_rig.protocol import ApsFrame


def test_exposure_midpoint_uses_integer_division():
    frame = ApsFrame(np.zeros((2, 2), np.uint16), 10, 20, 100, 210, 3000, 3100)
    assert frame.t_exposure_mid_us == 1605  # V12's libcaer_frame_timestamp
    assert (frame.height, frame.width) == (2, 2)


def test_equality_compares_pixels_and_times():
    pixels = np.arange(6, dtype=np.uint16).reshape(2, 3) << 6
    a = ApsFrame(pixels, 1, 2, 3, 4, 5, 6)
    assert a == ApsFrame(pixels.copy(), 1, 2, 3, 4, 5, 6)
    assert a != ApsFrame(pixels + 64, 1, 2, 3, 4, 5, 6)
    assert a != ApsFrame(pixels, 1, 2, 3, 4, 5, 7)
    assert a.pixels_10bit.tolist() == [[0, 1, 2], [3, 4, 5]]


@pytest.mark.parametrize("pixels", [np.zeros((2, 2), np.float32), np.zeros(4, np.uint16)])
def test_pixels_must_be_2d_uint16(pixels):
    with pytest.raises(ShapeError, match="uint16"):
        ApsFrame(pixels)
