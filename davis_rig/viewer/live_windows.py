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

import dataclasses
from dataclasses import dataclass

import numpy as np

from davis_rig.events.histogram import COUNT_CUTOFF, NUM_BINS, WINDOW_US, stacked_histogram, time_bins
from davis_rig.types import EVENT_DTYPE, RVT_HW

__all__ = ["LiveWindow", "WindowHistograms", "bin_starts", "crop_cells", "join_events", "later_window"]


@dataclass(frozen=True)
class LiveWindow:
    """One complete window of a live stream.

    Attributes:
        end_us: its end, µs (events ``end − window_us ≤ t ≤ end``, both ends inclusive as the official code).
        histogram: uint8 [2 · B, 240, 304], the official stacked histogram of its events in the crop.
        starts_sequence: the first window handed out after the stream started or its time went back (RVT states
            reset).
        completed_at: index, in the array pushed last, of the first event after ``end_us`` (the one that
            completed the window).
        events: events of the window in the crop.
    """

    end_us: int
    histogram: np.ndarray
    starts_sequence: bool
    completed_at: int
    events: int


def later_window(replaced: LiveWindow, window: LiveWindow) -> LiveWindow:
    """``window``, handed on in place of an earlier window that was not scored: it starts a sequence if the
    replaced one did (the RVT states must still be reset)."""
    if replaced.starts_sequence and not window.starts_sequence:
        return dataclasses.replace(window, starts_sequence=True)
    return window


def join_events(parts: list[np.ndarray]) -> np.ndarray:
    """The EVENT_DTYPE arrays ``parts`` as one array: a view where they lie one after the other in one buffer (the
    chunks of one :meth:`~davis_rig.viewer.live_process.EventRing.read`), else copied as bytes (a memcpy, where
    numpy's field-wise copy of the packed structured dtype is ~10x slower)."""
    if len(parts) == 1:
        return parts[0]
    if (view := _adjacent_view(parts)) is not None:
        return view
    return np.concatenate([np.ascontiguousarray(part).view(np.uint8) for part in parts]).view(EVENT_DTYPE)


def _adjacent_view(parts: list[np.ndarray]) -> np.ndarray | None:
    """One view of ``parts`` when they are C-contiguous, of one dtype, and follow each other in the memory of
    one array; else ``None``."""
    root = _root(parts[0])
    if not root.flags.c_contiguous:
        return None
    address = parts[0].__array_interface__["data"][0]
    for part in parts:
        if part.dtype != parts[0].dtype or not part.flags.c_contiguous or _root(part) is not root \
                or part.__array_interface__["data"][0] != address:
            return None
        address += part.nbytes
    offset = parts[0].__array_interface__["data"][0] - root.__array_interface__["data"][0]
    return np.ndarray((sum(len(part) for part in parts),), parts[0].dtype, buffer=root, offset=offset)


def _root(array: np.ndarray) -> np.ndarray:
    """The array whose memory ``array`` views (``array`` itself when it owns it)."""
    while isinstance(array.base, np.ndarray):
        array = array.base
    return array


def crop_cells(events: np.ndarray, origin_xy: tuple[int, int], num_bins: int = NUM_BINS):
    """The events of ``events`` (EVENT_DTYPE [N]) inside the 304x240 crop at ``origin_xy`` (the same events and
    order as :func:`~davis_rig.events.crop.crop_events`), as their histogram cell in time bin 0 and their time.

    Returns:
        ``(cells, t)``: int32 [M] ``x + 304 · y + p · num_bins · 240 · 304`` (crop px; the cell of time bin ``b`` is
        ``cells + b · 240 · 304``), int64 [M] µs.
    """
    x0, y0 = (int(v) for v in origin_xy)
    x = events["x"] - np.uint16(x0)  # uint16: left of the crop wraps to a large value
    y = events["y"] - np.uint16(y0)
    keep = x < RVT_HW[1]
    keep &= y < RVT_HW[0]
    cells = y.astype(np.int32)
    cells *= RVT_HW[1]
    cells += x
    cells += events["p"].astype(np.int32) * (num_bins * RVT_HW[0] * RVT_HW[1])
    return cells[keep], events["t"][keep]


def bin_starts(first_us: int, last_us: int, num_bins: int = NUM_BINS) -> np.ndarray:
    """The first time of time bins ``1 .. num_bins − 1`` of a window whose first and last events are at
    ``first_us`` and ``last_us`` (official float32 binning, :func:`~davis_rig.events.histogram.time_bins`): an
    event at ``t`` is in bin ``b`` iff ``starts[b − 1] <= t < starts[b]`` — so the bins of time-sorted events are
    runs found by binary search, exactly as the per-event formula bins them (tested over every µs).

    Returns:
        int64 [num_bins − 1], µs.
    """
    span = max(int(last_us) - int(first_us), 1)
    # the float32 formula is monotone in t and within a µs of the exact b · span / B: search a few µs around it
    guess = int(first_us) + np.arange(1, num_bins)[:, None] * span // num_bins + np.arange(-3, 5)[None, :]
    guess = np.maximum(guess, int(first_us))
    bins = time_bins(guess.ravel(), num_bins, first_us=first_us, last_us=last_us).reshape(guess.shape)
    above = bins >= np.arange(1, num_bins)[:, None]
    return guess[np.arange(num_bins - 1), above.argmax(axis=1)]


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
    binned as if the window's last event were at its end, and the cropped events kept for a recount."""

    def __init__(self, end_us: int, num_bins: int):
        self.end_us = end_us
        self.num_bins = num_bins
        self.counts = np.zeros(2 * num_bins * RVT_HW[0] * RVT_HW[1], np.uint8)
        self.columns: list[tuple[np.ndarray, np.ndarray]] = []  # (cells, t) as added
        self.events = 0
        self.first_us: int | None = None
        self.last_us: int | None = None  # the running maximum of the times so far
        self._starts: np.ndarray | None = None  # bin_starts(first, end)

    def add(self, cells: np.ndarray, t: np.ndarray) -> None:
        """Count cropped events (:func:`crop_cells`) of this window, in stream order."""
        if not len(t):
            return
        if not (t[1:] >= t[:-1]).all():  # (a tenth of the running maximum's cost where already sorted)
            t = np.maximum.accumulate(t)  # the official reader's running-maximum correction, within the window
        if self.last_us is not None and t[0] < self.last_us:
            np.maximum(t, self.last_us, out=t)  # (t: a new array from crop_cells)
        if self.first_us is None:
            self.first_us = int(t[0])
            self._starts = bin_starts(self.first_us, self.end_us, self.num_bins)
        self.last_us = int(t[-1])
        self.columns.append((cells, t))
        self.events += len(t)
        plane = RVT_HW[0] * RVT_HW[1]
        bounds = [0, *np.searchsorted(t, self._starts, side="left").tolist(), len(t)]
        for b in range(self.num_bins):
            if bounds[b] < bounds[b + 1]:  # bin b: the cells b planes on (np.add.at on uint8 wraps modulo 256)
                np.add.at(self.counts[b * plane:], cells[bounds[b]:bounds[b + 1]], np.uint8(1))

    def histogram(self, count_cutoff: int) -> np.ndarray:
        """The window's stacked histogram, uint8 [2 · B, 240, 304]."""
        if self.last_us is not None and self.last_us != self.end_us:  # binned with the wrong last event: recount
            cells, t = (np.concatenate(column) for column in zip(*self.columns))
            p, pixel = np.divmod(cells, self.num_bins * RVT_HW[0] * RVT_HW[1])
            y, x = np.divmod(pixel, RVT_HW[1])
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
        #: complete windows not counted: the same push completed a newer one (it would replace them)
        self.superseded = 0

    def push(self, events: np.ndarray) -> LiveWindow | None:
        """Add sensor events (EVENT_DTYPE [N], time-sorted); return the newest window they complete, or ``None``.

        Windows completed by the same push before the newest are not counted, only tallied in :attr:`superseded`
        (a consumer taking one window at a time would replace them anyway): a consumer that fell behind catches
        up at the cost of one window.
        """
        if not len(events):
            return None
        t_first, t_last = int(events["t"][0]), int(events["t"][-1])
        window = self._open
        if window is None or t_first < window.end_us - 2 * self.window_us:
            window = self._open = _OpenWindow(t_first // 1000 * 1000 + self.window_us, self.num_bins)
            self._tail, self._restart = [], True
        parts = [events]
        if t_last > window.end_us + self.window_us:  # later windows are complete too: skip to the newest of them
            skipped = (t_last - window.end_us - 1) // self.window_us
            self.superseded += skipped
            start = window.end_us + (skipped - 1) * self.window_us  # the newest complete window's start
            parts = [kept for part in self._tail + parts if len(kept := _between(part, start, None))]
            window = self._open = _OpenWindow(start + self.window_us, self.num_bins)
            self._tail = []
        done = None
        for _ in range(2):  # the open window, and the next one when the events complete it
            end = window.end_us
            for part in parts:
                window.add(*crop_cells(_between(part, end - self.window_us, end), self.crop_origin_xy, self.num_bins))
            self._tail += [tail for part in parts if len(tail := _between(part, end, None))]
            if t_last <= end:
                break
            done = LiveWindow(end, window.histogram(self.count_cutoff), self._restart,
                              int(np.argmax(events["t"] > end)), window.events)
            self._restart = False
            window = self._open = _OpenWindow(end + self.window_us, self.num_bins)
            parts, self._tail = self._tail, []
        return done
