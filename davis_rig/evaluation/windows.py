"""``davis-eval``'s window grid: where the windows end, which window a label falls in, and the per-window histograms.

Window ``k`` (k = 1, 2, …) ends at ``t0 + k · window_us`` from the session's ``t_offset`` (its first event's
millisecond) and holds the events with ``end − window_us ≤ t ≤ end`` (RVT's inclusive windows,
:mod:`davis_rig.events.histogram`); a label at time ``t`` belongs to the window with ``end − window_us < t ≤ end``.
The evaluation, the viewer and the RVT export all step through a recording on this grid, so a viewed frame and an
exported window are exactly one scored RVT input.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Iterator

import numpy as np

from davis_rig.errors import SessionError
from davis_rig.events.histogram import WINDOW_US
from davis_rig.types import DAVIS346_HW, EVENT_DTYPE, RVT_HW

__all__ = ["LABEL_SPAN_SLACK_US", "event_chunks", "label_windows", "labelled_window_grid", "labels_in_span",
           "window_grid"]

#: How far after the last event a label may lie and still be scored (on windows without events), µs.
LABEL_SPAN_SLACK_US = 1_000_000


def window_grid(t0_us: int, t_last_us: int, window_us: int = WINDOW_US) -> np.ndarray:
    """The window ends: ``t0 + k · window_us`` for ``k = 1 .. max(1, ceil((t_last − t0) / window_us))``.

    Args:
        t0_us: start of the grid, device µs.
        t_last_us: the grid reaches at least this time, device µs.
        window_us: window length, µs (> 0).

    Returns:
        int64 [T] window ends, device µs.
    """
    n_windows = max(1, -(-(int(t_last_us) - int(t0_us)) // int(window_us)))
    return int(t0_us) + int(window_us) * np.arange(1, n_windows + 1, dtype=np.int64)


def label_windows(labels: np.ndarray, window_end_us: np.ndarray, window_us: int) -> np.ndarray:
    """Window index of every label: the window with ``end − window_us < t ≤ end``; int64 [L] (−1 outside)."""
    t = labels["t"].astype(np.int64)
    index = np.searchsorted(window_end_us, t, side="left")
    inside = (index < len(window_end_us))
    inside[inside] &= window_end_us[index[inside]] - window_us < t[inside]
    return np.where(inside, index, -1)


def labels_in_span(labels: np.ndarray, t0_us: int, t_end_us: int, path, *, refuse_none: bool = True) -> np.ndarray:
    """The labels inside the events' span ``[t0_us, t_end_us + 1 s]`` (device µs): the window grid covers the
    events, so a label time far outside them (a damaged label, or a ``t_offset`` that does not match the labels)
    would otherwise stretch it over hours of empty windows. Warns with the count of labels left out.

    Args:
        labels: BBOX_DTYPE [L] (``t`` device µs), at least one.
        t0_us: the grid's start (the session's ``t_offset``), device µs.
        t_end_us: the end of the events (:meth:`~davis_rig.session.SessionReader.indexed_span_us` after ``t0_us``).
        path: the session (named in the messages).
        refuse_none: raise when no label is inside (else warn and return none).

    Raises:
        SessionError: no label is inside the span (with ``refuse_none``).
    """
    t = labels["t"].astype(np.float64)  # uint64 label times: no wrap-around in the comparison
    inside = (t >= t0_us) & (t <= t_end_us + LABEL_SPAN_SLACK_US)
    if not inside.any() and refuse_none:
        raise SessionError(f"{path}: none of the {len(labels)} labels (t {int(labels['t'].min())}.."
                           f"{int(labels['t'].max())} µs) lies inside the events' span ({t0_us}..{t_end_us} µs): "
                           "the labels or the file's t_offset are damaged")
    if not inside.all():
        warnings.warn(f"{Path(path).name}: {int((~inside).sum())} of {len(labels)} labels lie outside the events' "
                      f"span ({t0_us}..{t_end_us} µs) and are left out", stacklevel=3)
    return labels[inside]


def labelled_window_grid(reader, labels: np.ndarray, window_us: int, path) -> tuple[np.ndarray, np.ndarray]:
    """The window grid of a labelled session and the labels it scores: ``(labels, ends)``.

    The grid starts at the session's ``t_offset`` and covers the events (:meth:`~davis_rig.session.SessionReader.
    indexed_span_us`) and the labels inside their span (:func:`labels_in_span`, which warns about the others).

    Raises:
        SessionError: no label is inside the events' span.
    """
    t0 = int(reader.t_offset_us)
    t_events_end = t0 + reader.indexed_span_us()
    labels = labels_in_span(labels, t0, t_events_end, path)
    return labels, window_grid(t0, max(t_events_end, int(labels["t"].max())), window_us)


def event_chunks(reader, ends: np.ndarray, origin_xy: tuple[int, int], *, window_us: int, chunk_windows: int,
                 gif_windows: int = 0, timings: dict | None = None,
                 damage: dict | None = None) -> Iterator[tuple]:
    """Per chunk of windows, ``(chunk_ends, uint8 hists [k, 20, 240, 304], gif images, events read)``.

    Reads the recording once, front to back, in consecutive pieces (each up to its chunk's last window end),
    crops them and makes their timestamps non-decreasing across the whole recording like RVT's reader (the
    running maximum carries from piece to piece); the corrected events the next chunk's first window still
    holds (the boundary events, and events a step back in time lifted past the boundary) are carried over.
    So every window holds exactly the events of RVT's whole-recording correction, whatever ``chunk_windows``.

    Args:
        reader: an open :class:`~davis_rig.session.SessionReader` (DAVIS346 events).
        ends: int64 [T] window ends, device µs (:func:`window_grid`).
        origin_xy: the 304x240 crop's origin on the sensor, px.
        window_us: window length, µs.
        chunk_windows: windows per read (>= 1).
        gif_windows: the first this many windows also come back as int16 ON − OFF count images [g, 240, 304]
            (the annotated GIF); the other chunks give empty ones.
        timings: when given, its ``"read"`` and ``"histogram"`` entries gain this generator's busy seconds.
        damage: when given, its ``"outside_sensor"`` entry gains the count of events whose pixel lies outside
            the 346x260 sensor (damaged coordinates: the crop drops them like any event outside it).
    """
    from davis_rig.events.crop import crop_events
    from davis_rig.events.histogram import stacked_histograms

    window_us = int(window_us)
    running_max = np.iinfo(np.int64).min
    carried = np.zeros(0, EVENT_DTYPE)
    t_read = int(ends[0]) - window_us
    gif_left = gif_windows
    for i0 in range(0, len(ends), chunk_windows):
        chunk_ends = ends[i0 : i0 + chunk_windows]
        tic = time.perf_counter()
        t_next = int(chunk_ends[-1]) + 1
        events = reader.events_between(t_read, t_next)
        t_read = t_next
        num_read = len(events)
        if damage is not None:
            outside = (events["x"] >= DAVIS346_HW[1]) | (events["y"] >= DAVIS346_HW[0])
            damage["outside_sensor"] = damage.get("outside_sensor", 0) + int(np.count_nonzero(outside))
        events = crop_events(events, origin_xy, frame_hw=RVT_HW, sensor_hw=DAVIS346_HW)
        if len(events):
            t = np.maximum.accumulate(np.maximum(events["t"], running_max))
            running_max = int(t[-1])
            events["t"] = t
        if len(carried):
            events = np.concatenate([carried, events])
        next_start = int(ends[min(i0 + chunk_windows, len(ends) - 1)]) - window_us
        carried = events[np.searchsorted(events["t"], next_start, side="left"):]
        tac = time.perf_counter()
        hists = stacked_histograms(events, chunk_ends, window_us=window_us)
        gif = hists[:max(gif_left, 0)]
        half = hists.shape[1] // 2
        gif = gif[:, half:].sum(1, dtype=np.int16) - gif[:, :half].sum(1, dtype=np.int16)
        gif_left -= len(gif)
        if timings is not None:
            timings["read"] += tac - tic
            timings["histogram"] += time.perf_counter() - tac
        yield chunk_ends, hists, gif, num_read
