"""RVT's windows of a live event stream, each window's stacked histogram built while its events arrive.

The live view's detector needs, for the newest complete 50 ms window, the official stacked histogram of the
304x240 crop (:func:`~davis_rig.events.histogram.stacked_histogram`). Built from the whole window once it is
complete, cropping and counting its ~600k events (12 M ev/s) take tens of ms on the detector's path. Here each
pushed chunk is cropped, binned and counted into the open window at once, so that the window's end only clips
the counts (~1 ms): its boxes wait for the RVT step alone.

Binning before the window is complete: the official time bins are normalized by the window's first and last
event (not its bounds). The first is known when it arrives; the last is taken to be the window's end — true
whenever an event of the crop falls on the window's last µs, i.e. always at the rates where the cost matters
(at 12 M ev/s, ~10 crop events per µs). When the window's last event is earlier, its histogram is recomputed
from the window's kept columns with the true last event. Either way the result equals the batch histogram
exactly (tested), at any rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from davis_rig.events.histogram import COUNT_CUTOFF, NUM_BINS, WINDOW_US, stacked_histogram, time_bins
from davis_rig.types import RVT_HW

__all__ = ["LiveWindow", "WindowHistograms", "crop_parts"]


@dataclass(frozen=True)
class LiveWindow:
    """One complete window of a live stream.

    Attributes:
        end_us: its end, µs (events ``end − window_us ≤ t ≤ end``, both ends inclusive as the official code).
        histogram: uint8 [2 · B, 240, 304], the official stacked histogram of its events in the crop.
        starts_sequence: the first window after the stream started or its time went back (RVT states reset).
        completed_at: index, in the array pushed last, of the first event after ``end_us`` (the one that
            completed the window).
        events: events of the window in the crop.
    """

    end_us: int
    histogram: np.ndarray
    starts_sequence: bool
    completed_at: int
    events: int


def crop_parts(events: np.ndarray, origin_xy: tuple[int, int]):
    """The events of ``events`` (EVENT_DTYPE [N]) inside the 304x240 crop at ``origin_xy``, as columns
    ``(x, y, t, p)`` in crop px: x, y int32, t int64 µs, p uint8 (the same events and order as
    :func:`~davis_rig.events.crop.crop_events`)."""
    x0, y0 = (int(v) for v in origin_xy)
    x = events["x"].astype(np.int32)
    x -= x0
    y = events["y"].astype(np.int32)
    y -= y0
    keep = (x >= 0) & (x < RVT_HW[1]) & (y >= 0) & (y < RVT_HW[0])
    return x[keep], y[keep], events["t"][keep], events["p"][keep]


def _between(events: np.ndarray, t0_us: int, t1_us: int | None) -> np.ndarray:
    """The view of time-sorted ``events`` with ``t0_us <= t <= t1_us`` (no upper bound for ``None``); a binary
    search only where the bounds cut the array (a field of a structured array is strided: searching it copies)."""
    first, last = int(events["t"][0]), int(events["t"][-1])
    if first >= t0_us and (t1_us is None or last <= t1_us):
        return events
    if last < t0_us or (t1_us is not None and first > t1_us):
        return events[:0]
    t = events["t"]
    lo = 0 if first >= t0_us else int(np.searchsorted(t, t0_us, side="left"))
    hi = len(events) if t1_us is None or last <= t1_us else int(np.searchsorted(t, t1_us, side="right"))
    return events[lo:hi]


class _OpenWindow:
    """The counts of the window being filled: uint8 cells (wrapping modulo 256 as the official accumulation),
    binned as if the window's last event were at its end, and the cropped columns kept for a recount."""

    def __init__(self, end_us: int, num_bins: int):
        self.end_us = end_us
        self.num_bins = num_bins
        self.counts = np.zeros(2 * num_bins * RVT_HW[0] * RVT_HW[1], np.uint8)
        self.columns: list[tuple[np.ndarray, ...]] = []
        self.first_us: int | None = None
        self.last_us: int | None = None  # the running maximum of the times so far

    def add(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray) -> None:
        """Count cropped events (columns in crop px) of this window, in stream order."""
        if not len(t):
            return
        t = np.maximum.accumulate(t)  # the official reader's running-maximum correction, within the window
        if self.last_us is not None:
            np.maximum(t, self.last_us, out=t)
        if self.first_us is None:
            self.first_us = int(t[0])
        self.last_us = int(t[-1])
        self.columns.append((x, y, t, p))
        plane = RVT_HW[0] * RVT_HW[1]
        bins = time_bins(t, self.num_bins, first_us=self.first_us, last_us=self.end_us)
        cells = y * RVT_HW[1]
        cells += x
        cells += (p.astype(np.int32) * self.num_bins + bins.astype(np.int32)) * plane
        np.add.at(self.counts, cells, np.uint8(1))

    def histogram(self, count_cutoff: int) -> np.ndarray:
        """The window's stacked histogram, uint8 [2 · B, 240, 304]."""
        if self.last_us is not None and self.last_us != self.end_us:  # binned with the wrong last event: recount
            x, y, t, p = (np.concatenate(column) for column in zip(*self.columns))
            return stacked_histogram(x, y, t, p, num_bins=self.num_bins, count_cutoff=count_cutoff)
        out = np.minimum(self.counts, np.uint8(min(max(count_cutoff, 0), 255)))
        return out.reshape(2 * self.num_bins, *RVT_HW)


class WindowHistograms:
    """Cut a live event stream into RVT's windows and build their stacked histograms of the 304x240 crop as the
    events arrive (see the module).

    The windows end at ``t0 + k · window_us``, ``t0`` the first event's millisecond (as a session's
    ``t_offset``); each holds ``end − window_us ≤ t ≤ end`` (an event on a boundary counts in both windows). A
    window is complete once an event after its end has arrived. Time going back by more than two windows (a
    device timestamp reset) restarts the grid at the new time, and the next window starts a new sequence.
    Within a window, times are made non-decreasing by their running maximum (as the official reader does).

    Args:
        crop_origin_xy: the crop's top-left on the sensor, px.
        window_us: window length, µs.
        num_bins, count_cutoff: the histogram's time bins per polarity and count clip.
    """

    def __init__(self, crop_origin_xy: tuple[int, int], window_us: int = WINDOW_US, num_bins: int = NUM_BINS,
                 count_cutoff: int = COUNT_CUTOFF):
        self.crop_origin_xy = tuple(int(v) for v in crop_origin_xy)
        self.window_us = int(window_us)
        self.num_bins = int(num_bins)
        self.count_cutoff = int(count_cutoff)
        self._open: _OpenWindow | None = None
        self._tail: list[np.ndarray] = []  # events of the open window that the next window holds too (t >= end)
        self._restart = True

    def push(self, events: np.ndarray) -> list[LiveWindow]:
        """Add sensor events (EVENT_DTYPE [N], time-sorted); return the windows they complete, oldest first."""
        if not len(events):
            return []
        t_first, t_last = int(events["t"][0]), int(events["t"][-1])
        window = self._open
        if window is None or t_first < window.end_us - 2 * self.window_us:
            window = self._open = _OpenWindow(t_first // 1000 * 1000 + self.window_us, self.num_bins)
            self._tail, self._restart = [], True
        done = []
        parts = [events]
        while True:
            end = window.end_us
            for part in parts:
                window.add(*crop_parts(_between(part, end - self.window_us, end), self.crop_origin_xy))
            self._tail += [tail for part in parts if len(tail := _between(part, end, None))]
            if t_last <= end:
                return done
            done.append(LiveWindow(end, window.histogram(self.count_cutoff), self._restart,
                                   int(np.argmax(events["t"] > end)), sum(len(c[2]) for c in window.columns)))
            self._restart = False
            window = self._open = _OpenWindow(end + self.window_us, self.num_bins)
            parts, self._tail = self._tail, []
