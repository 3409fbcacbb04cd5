"""The recording clock of a :class:`~davis_rig.session.writer.SessionWriter`: one monotonic time for a session.

The file stores every item at ``t_device + offset`` (µs). The offset starts at 0 and changes at timestamp resets
(the device clock restarts at 0) and at time discontinuities (damaged timestamps, see
:mod:`davis_rig.session.timeline`); :meth:`SessionWriter.append <davis_rig.session.writer.SessionWriter.append>`
documents the rules. :class:`RecordingClock` keeps that state: the current offset, the latest time accepted on
any stream, the lists of offset changes and the reset epoch of each stream; it splits a chunk at its timestamp
resets and chooses the times of one epoch's items. It writes nothing: the writer buffers what it returns.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np

from davis_rig.protocol.words import SpecialType
from davis_rig.session import schema
from davis_rig.session.timeline import EventTimes, advance_clock, plan_event_times, shift_for

__all__ = ["MAX_OFFSET_ENTRIES", "Epoch", "RecordingClock"]

#: Offset-change entries kept in the ``stats`` attribute per list (HDF5 attributes hold at most 64 KiB).
MAX_OFFSET_ENTRIES = 256


def reset_positions(specials) -> np.ndarray:
    """Indices of the TIMESTAMP_RESET specials in a chunk's specials table (int64 [R]; empty without a type field)."""
    if specials is None or not len(specials):
        return np.zeros(0, np.int64)
    names = np.asarray(specials).dtype.names or ()
    if "type" not in names:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.asarray(specials)["type"] == SpecialType.TIMESTAMP_RESET)


class Epoch(NamedTuple):
    """The part of a chunk that lies in one reset epoch (device µs).

    Attributes:
        reset_t_us: device time of the TIMESTAMP_RESET special that starts it (``None``: the current epoch goes on).
        events, frames, specials, imu: the chunk's items of this epoch (as :meth:`SessionWriter.append` takes them).
        bridge_gaps: whether forward jumps over ``max_gap_us`` are bridged (device clock times).
    """

    reset_t_us: int | None
    events: object
    frames: list
    specials: object
    imu: object
    bridge_gaps: bool


class RecordingClock:
    """Maps device times onto the session's monotonic recording time (module docstring).

    Args:
        max_gap_us: largest forward jump of the device clock taken as it is, µs (``None``: any); see
            :class:`~davis_rig.session.writer.SessionWriter`.
        label: what the warnings name (the session file).

    Attributes:
        offset_us: recording µs − device µs of the current stretch.
        last_t: recording µs of the last accepted event (``None`` before the first).
        t_max: latest recording µs accepted on any stream (events, frames, tables).
        clock_us: latest plausible recording µs on any stream (bridges event gaps).
        repaired_events, n_discontinuities, n_resets: counts for the ``stats`` attribute.
        discontinuities, resets: the first :data:`MAX_OFFSET_ENTRIES` ``{"t_us", "offset_us"}`` entries of each.
    """

    def __init__(self, max_gap_us: int | None, label: object):
        self.max_gap_us = max_gap_us
        self.label = label
        self.offset_us = 0
        self.last_t: int | None = None
        self.t_max: int | None = None
        self.clock_us: int | None = None
        self.repaired_events = 0
        self.discontinuities: list[dict] = []
        self.n_discontinuities = 0
        self.resets: list[dict] = []  # {"t_us": reset special's time, "offset_us"}
        self.n_resets = 0
        # device µs of each stream's last item in the current reset epoch (None: nothing since the last reset)
        self._epoch_last_device_t: dict[str, int | None] = {"events": None, "frames": None, "imu": None}

    # --- reset epochs -------------------------------------------------------------------------
    def split_at_resets(self, events, frames: list, specials, imu, *, device_clock: bool) -> list[Epoch] | None:
        """Split a chunk at its TIMESTAMP_RESET specials (only with ``device_clock``); ``None`` when the whole chunk
        lies in the current epoch. Call :meth:`start_reset` with each later epoch's ``reset_t_us`` before placing
        its items.

        A chunk may hold data from before and after a reset (the decoder does not split at resets; each array is
        in stream order). The specials are split exactly at the reset specials; events, frames (by end-of-frame
        time) and IMU samples are split where their device time goes back (the restart), at most once per reset in
        the chunk. If the data after a reset is not earlier than the data before it (a reset within about one
        chunk's span of the previous epoch's start), no split is visible and it stays in the old epoch: nothing is
        lost and time stays monotonic, but those items' offset is 0 (relative to the true one).
        """
        reset_at = reset_positions(specials) if device_clock and specials is not None and len(specials) else None
        if reset_at is None or not reset_at.shape[0]:  # the common case: one epoch, remember each stream's last time
            if events is not None and len(events):
                self._epoch_last_device_t["events"] = int(events["t"][-1])
            if frames:
                self._epoch_last_device_t["frames"] = int(frames[-1].t_end_of_frame_us)
            if imu is not None and len(imu):
                self._epoch_last_device_t["imu"] = int(imu["t"][-1])
            return None
        n_resets = reset_at.shape[0]
        event_epoch = self._epochs("events", None if events is None else np.asarray(events)["t"], n_resets)
        frame_t = np.array([int(frame.t_end_of_frame_us) for frame in frames], dtype=np.int64)
        frame_epoch = self._epochs("frames", frame_t, n_resets)
        imu_epoch = self._epochs("imu", None if imu is None else np.asarray(imu)["t"], n_resets)
        bounds = [0, *reset_at.tolist(), len(specials)]
        return [
            Epoch(
                int(specials["t"][bounds[k]]) if k else None,
                None if event_epoch is None else events[event_epoch == k],
                [frame for frame, epoch in zip(frames, frame_epoch.tolist()) if epoch == k],
                specials[bounds[k] : bounds[k + 1]],
                None if imu_epoch is None else imu[imu_epoch == k],
                True,
            )
            for k in range(n_resets + 1)
        ]

    def _epochs(self, kind: str, t: np.ndarray | None, n_resets: int) -> np.ndarray | None:
        """Reset epoch (0..n_resets) of each item of one stream of a chunk holding ``n_resets`` resets.

        An item starts a new epoch where its device time is earlier than the previous item's (the previous chunk's
        last one in the current epoch for the first item); at most ``n_resets`` such restarts are counted.
        """
        if t is None:
            self._epoch_last_device_t[kind] = None
            return None
        t = np.asarray(t, dtype=np.int64)
        if not t.shape[0]:
            self._epoch_last_device_t[kind] = None
            return np.zeros(0, np.int64)
        prev = self._epoch_last_device_t[kind]
        restart = np.empty(t.shape[0], bool)
        restart[0] = prev is not None and int(t[0]) < prev
        np.less(t[1:], t[:-1], out=restart[1:])
        epoch = np.minimum(np.cumsum(restart), n_resets)
        self._epoch_last_device_t[kind] = int(t[-1]) if int(epoch[-1]) == n_resets else None
        return epoch

    def start_reset(self, t_reset_device_us: int) -> None:
        """A TIMESTAMP_RESET special at device time ``t_reset_device_us``: continue after the latest time accepted."""
        if self.t_max is not None:
            self.offset_us = self.t_max + 1 - t_reset_device_us
        self.n_resets += 1
        if len(self.resets) < MAX_OFFSET_ENTRIES:
            self.resets.append({"t_us": t_reset_device_us + self.offset_us, "offset_us": self.offset_us})
        for kind in self._epoch_last_device_t:
            self._epoch_last_device_t[kind] = None
        if self.n_resets == 1:
            warnings.warn(
                f"{self.label}: the device timestamp was reset; later data is stored after the earlier data "
                "(offsets in stats['writer']['timestamp_reset_offsets'])",
                stacklevel=3,
            )

    # --- placing one epoch --------------------------------------------------------------------
    def note_time(self, t_us: int) -> None:
        """An item at recording time ``t_us`` was accepted (frames and tables: by the writer, after buffering)."""
        if self.t_max is None or t_us > self.t_max:
            self.t_max = t_us

    def place(self, events: np.ndarray | None, frames: list, tables: list, *,
              bridge_gaps: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Choose the recording times of one epoch's checked items (device µs of the current epoch).

        Args:
            events: EVENT_DTYPE [N] (N > 0) or ``None``.
            frames: ``ApsFrame`` list (the offset follows the end of frame).
            tables: the non-empty specials / IMU tables (structured, with ``t``).
            bridge_gaps: bridge forward jumps over ``max_gap_us`` (device clock times).

        Returns:
            ``(events, offsets)``: the events at their recording times (the caller's array when no time changed;
            ``None`` without events) and int64 [F + K] the offsets, µs, of the frames, then of each table's rows in
            the order given (``None`` without frames and tables). The caller buffers them and reports each frame's
            and table's latest recording time with :meth:`note_time`.
        """
        base = self.offset_us
        max_gap = self.max_gap_us if bridge_gaps else None
        other_t = None  # the end of frame for frames
        if frames or tables:
            frame_t = np.array([[int(getattr(f, name)) for name in schema.FRAME_TIME_COLUMNS] for f in frames],
                               dtype=np.int64).reshape(-1, len(schema.FRAME_TIME_COLUMNS))
            other_t = np.concatenate([frame_t[:, -1]] + [table["t"].astype(np.int64) for table in tables]) + base
        if max_gap is not None:
            if self.clock_us is None and events is not None:  # the other streams' evidence starts at the first event
                self.clock_us = int(events["t"][0]) + base
            if other_t is not None:
                self.clock_us = advance_clock(self.clock_us, other_t, max_gap)
        plan = None
        if events is not None:
            events, plan = self._place_events(events, base, max_gap)
        if other_t is None:
            return events, None
        shifts = np.zeros(other_t.shape[0], np.int64) if plan is None else \
            shift_for(other_t, plan.seg_lo_us, plan.seg_hi_us, plan.seg_shift_us)
        shifts += base
        return events, shifts

    def _place_events(self, events: np.ndarray, base_us: int,
                      max_gap_us: int | None) -> tuple[np.ndarray, EventTimes]:
        """Place (see :func:`~davis_rig.session.timeline.plan_event_times`) checked events; returns them (a copy
        when a time changed) and the plan."""
        plan = plan_event_times(events["t"] + base_us, self.last_t, self.clock_us, max_gap_us)
        self._note_repairs(plan, base_us)
        if base_us or plan.repaired or plan.shifts:  # else the times are unchanged: no copy at the peak rate
            events = events.copy()
            events["t"] = plan.t_us
        self.last_t = int(events["t"][-1])
        self.clock_us = self.last_t if self.clock_us is None else max(self.clock_us, self.last_t)
        self.note_time(self.last_t)
        return events, plan

    def _note_repairs(self, plan: EventTimes, base_us: int) -> None:
        """Count a batch's repaired timestamps and discontinuities, move the offset, warn once for each kind."""
        if plan.repaired:
            if not self.repaired_events:
                warnings.warn(
                    f"{self.label}: {plan.repaired} events have a timestamp that goes back or sticks out (a damaged "
                    "timestamp word); they are kept at the previous events' time (counted in "
                    "stats['writer']['events_time_repaired'])",
                    stacklevel=5,
                )
            self.repaired_events += plan.repaired
        if not plan.shifts:
            return
        if not self.n_discontinuities:
            warnings.warn(
                f"{self.label}: the device time jumps (a damaged timestamp: it goes back, or ahead by more than "
                f"{self.max_gap_us} µs with nothing in between); the data after it continues where the data before "
                "it ended (offsets in stats['writer']['time_discontinuity_offsets'])",
                stacklevel=5,
            )
        for index, shift in plan.shifts:
            self.n_discontinuities += 1
            if len(self.discontinuities) < MAX_OFFSET_ENTRIES:
                self.discontinuities.append({"t_us": int(plan.t_us[index]), "offset_us": base_us + shift})
        self.offset_us = base_us + plan.shifts[-1][1]
