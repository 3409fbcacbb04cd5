"""davis-eval's window grid: the window ends and the window of each label (shared by the viewer and the RVT export)."""

from __future__ import annotations

import numpy as np

from davis_rig.evaluation.windows import label_windows, window_grid
from davis_rig.types import BBOX_DTYPE


def test_window_grid_covers_the_last_time():
    np.testing.assert_array_equal(window_grid(1000, 101_000, 50_000), [51_000, 101_000])
    np.testing.assert_array_equal(window_grid(1000, 101_001, 50_000), [51_000, 101_000, 151_000])
    np.testing.assert_array_equal(window_grid(1000, 1000, 50_000), [51_000])
    assert window_grid(0, 1, 50_000).dtype == np.int64


def test_label_windows_assignment():
    labels = np.zeros(4, BBOX_DTYPE)
    labels["t"] = [1, 50_000, 50_001, 400_000]
    assert label_windows(labels, np.array([50_000, 100_000]), 50_000).tolist() == [0, 0, 1, -1]
