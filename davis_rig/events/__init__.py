"""Event-stream kernels: crop, RVT input histograms and time windows (numpy); simulators (torch, lazy).

- :mod:`~davis_rig.events.crop`: centre crop of the DAVIS346 stream to RVT's 304 x 240 frame.
- :mod:`~davis_rig.events.histogram`: RVT's stacked histograms, numpy, bit-exact with the official pre-processing.
- :mod:`~davis_rig.events.histogram_torch`: the differentiable float version of those histograms.
- :mod:`~davis_rig.events.intensity`: what both simulators see of a frame: luma, v2e's lin-log, the threshold θ.
- :mod:`~davis_rig.events.simulator`: the exact DVS event simulator (video -> events, v2e non-idealities).
- :mod:`~davis_rig.events.v2e_torch`: the paper's differentiable V2E, video -> stacked histograms.

Importing this package does not import torch: the names of the torch modules (histogram_torch, simulator,
v2e_torch) are loaded on first access.
"""

from __future__ import annotations

from davis_rig._lazy import lazy_exports
from davis_rig.events.crop import center_crop_origin, crop_events
from davis_rig.events.histogram import (
    COUNT_CUTOFF,
    NUM_BINS,
    WINDOW_US,
    event_columns,
    monotonic_timestamps,
    regular_window_ends,
    stacked_histogram,
    stacked_histograms,
    time_bins,
    window_indices,
)
from davis_rig.events.intensity import (
    DEFAULT_THRESHOLD,
    INTENSITY_SCALE,
    LIN_LOG_THRESHOLD,
    LUMA_WEIGHTS,
    lin_log,
    rgb_to_luma,
)

_LAZY = {
    "davis_rig.events.histogram_torch": (
        "StackedHistogramTorch",
        "stacked_histogram_torch",
        "stacked_histograms_torch",
        "time_bins_torch",
    ),
    "davis_rig.events.simulator": (
        "EventSimulator",
        "SimulatorConfig",
        "simulate_events",
    ),
    "davis_rig.events.v2e_torch": (
        "BINNINGS",
        "MODES",
        "OFFICIAL_RELAXED_SCALE",
        "DifferentiableV2E",
        "floor_ste",
        "log_histograms",
        "log_intensity",
        "pair_bins",
        "v2e_counts",
        "v2e_histograms",
    ),
}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = [
    "COUNT_CUTOFF",
    "DEFAULT_THRESHOLD",
    "INTENSITY_SCALE",
    "LIN_LOG_THRESHOLD",
    "LUMA_WEIGHTS",
    "NUM_BINS",
    "WINDOW_US",
    "center_crop_origin",
    "crop_events",
    "event_columns",
    "lin_log",
    "monotonic_timestamps",
    "regular_window_ends",
    "rgb_to_luma",
    "stacked_histogram",
    "stacked_histograms",
    "time_bins",
    "window_indices",
]
__all__ += [name for names in _LAZY.values() for name in names]
