"""Event-stream kernels: RVT input histograms, time windows, crop (numpy; the torch variant is lazy).

``davis_rig.events.histogram`` is numpy-only and bit-exact with the official RVT pre-processing;
``davis_rig.events.histogram_torch`` is the differentiable float version (imports torch when called).
"""

from davis_rig.events.crop import center_crop_origin, crop_events, monotonic_timestamps
from davis_rig.events.histogram import (
    COUNT_CUTOFF,
    NUM_BINS,
    WINDOW_US,
    event_columns,
    regular_window_ends,
    stacked_histogram,
    stacked_histograms,
    time_bins,
    window_indices,
)

__all__ = [
    "COUNT_CUTOFF",
    "NUM_BINS",
    "WINDOW_US",
    "center_crop_origin",
    "crop_events",
    "event_columns",
    "monotonic_timestamps",
    "regular_window_ends",
    "stacked_histogram",
    "stacked_histograms",
    "time_bins",
    "window_indices",
]
