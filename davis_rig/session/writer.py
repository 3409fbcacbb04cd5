"""Write a session.h5 incrementally while a recording runs (see :mod:`davis_rig.session.schema`)."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import enum
import errno
import json
import os
import time
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from davis_rig import __version__
from davis_rig.errors import FormatError, SessionError, ShapeError
from davis_rig.session import schema
from davis_rig.session.journal import SessionJournal, journal_path
from davis_rig.session.timeline import advance_clock, plan_event_times, shift_for
from davis_rig.types import EVENT_DTYPE

#: libcaer special type id of TIMESTAMP_RESET (``davis_rig.protocol.words.SpecialType.TIMESTAMP_RESET``; the
#: session package does not import the protocol package).
TIMESTAMP_RESET_TYPE = 1
#: Buffered events that trigger a write to HDF5 before the flush interval is up.
WRITE_BATCH_EVENTS = 1 << 20
#: Free space kept for HDF5 metadata on top of the data of each write, bytes.
METADATA_MARGIN_BYTES = 1 << 20
#: Default free space that must remain after a write, bytes (the recording stops cleanly below it).
MIN_FREE_BYTES = 64 << 20
#: Default largest forward jump of the device clock taken as it is, µs (policy, see :class:`SessionWriter`).
MAX_GAP_US = 1_000_000
#: ``ms_to_idx`` entries computed and written at once (8 MiB): memory stays bounded whatever the time gap.
MS_INDEX_BLOCK = 1 << 20
#: Offset-change entries kept in the ``stats`` attribute per list (HDF5 attributes hold at most 64 KiB).
MAX_OFFSET_ENTRIES = 256


def to_jsonable(obj):
    """Convert device info / config objects (dataclasses, enums, numpy scalars, mappings) into JSON-able values."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        for name in ("dvs_width", "dvs_height", "aps_width", "aps_height"):
            if hasattr(type(obj), name) and isinstance(getattr(type(obj), name), property):
                out.setdefault(name, to_jsonable(getattr(obj, name)))
        return out
    if isinstance(obj, enum.Enum):
        return obj.name
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if hasattr(obj, "_asdict"):
        return to_jsonable(obj._asdict())
    return str(obj)


def _reset_positions(specials) -> np.ndarray:
    """Indices of the TIMESTAMP_RESET specials in a chunk's specials table (int64 [R]; empty without a type field)."""
    if specials is None or not len(specials):
        return np.zeros(0, np.int64)
    names = np.asarray(specials).dtype.names or ()
    if "type" not in names:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.asarray(specials)["type"] == TIMESTAMP_RESET_TYPE)


def frame_hw_from_device_info(info: Mapping | None) -> tuple[int, int]:
    """Return the APS (height, width) in px from a device-info dict (its ``layout``), else DAVIS346's."""
    layout = (info or {}).get("layout") or {}
    height = layout.get("aps_height") or layout.get("aps_size_rows")
    width = layout.get("aps_width") or layout.get("aps_size_columns")
    if height and width:
        return int(height), int(width)
    return schema.DEFAULT_FRAME_HW


class SessionWriter:
    """Write one recording into a session.h5, incrementally and crash-tolerantly.

    Data passed to :meth:`append` is buffered and written at least every ``flush_interval_s`` (then the HDF5
    file is flushed, so a reader or a crash sees everything up to the last flush) or as soon as
    :data:`WRITE_BATCH_EVENTS` events are buffered. With ``journal=True`` the raw USB transfers given to
    :meth:`append_raw` also go to ``<path>.journal`` (see :mod:`davis_rig.session.journal`), which is deleted on a
    clean :meth:`close` and lets :func:`~davis_rig.session.recovery.recover_session` rebuild the file after a crash.

    Args:
        path: the session.h5 to create.
        device_info: the camera's ``DeviceInfo`` (dataclass) or an equivalent mapping; stored as JSON.
        config: recording configuration (exposure_us, frame_interval_us, biases, ...), mapping; stored as JSON.
        overwrite: replace an existing file (else :class:`SessionError`).
        journal: keep a raw-transfer journal next to the file.
        flush_interval_s: longest time between two HDF5 flushes, s (≤ 1 keeps the "lose ≤ 1 s" promise).
        start_unix_us: wall-clock start of the recording, µs since the Unix epoch (default: now).
        min_free_bytes: free disk space to leave; below it the recording stops cleanly (HDF5 corrupts a file
            it cannot extend, so the writer checks ``statvfs`` before every write instead of waiting for ENOSPC).
        max_gap_us: largest forward jump of the device clock that :meth:`append` stores as it is, µs (``None``:
            any). A longer jump that no APS frame, IMU sample or special event bridges in steps of at most this
            length is taken for a damaged timestamp (a corrupt wrap word): the data after it continues 1 µs after
            the data before it, and the offset is recorded (see :meth:`append`), so the file's time span, and
            with it ``ms_to_idx``, stays proportional to the data. The default, 1 s, is a policy: a DAVIS346 with
            its DVS on sends background-activity events all the time, and frames or IMU samples bridge a quiet
            scene; a real gap longer than that is only a USB stall, which is stored shortened (nothing is lost:
            device time = recording time - offset).

    Use as a context manager (``with SessionWriter(...) as writer:``) or call :meth:`open` / :meth:`close`.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        device_info=None,
        config: Mapping | None = None,
        *,
        overwrite: bool = False,
        journal: bool = False,
        flush_interval_s: float = 1.0,
        start_unix_us: int | None = None,
        min_free_bytes: int = MIN_FREE_BYTES,
        max_gap_us: int | None = MAX_GAP_US,
    ):
        self.path = Path(path)
        self.device_info = device_info
        self.config = config
        self.overwrite = overwrite
        self.use_journal = journal
        self.flush_interval_s = flush_interval_s
        self.start_unix_us = start_unix_us
        self.min_free_bytes = min_free_bytes
        self.max_gap_us = max_gap_us
        self.journal: SessionJournal | None = None
        self._file = None
        self._extra_stats: dict = {}

    # --- life cycle ---------------------------------------------------------------------------
    def open(self) -> "SessionWriter":
        """Create the file, its groups and root attributes (and the journal); returns ``self``.

        Raises:
            SessionError: the file exists and ``overwrite`` is false, or it (or its journal) cannot be created;
                then a file created by this call is removed again (it holds no data).
        """
        import h5py

        if self._file is not None:
            return self
        if self.path.exists() and not self.overwrite:
            raise SessionError(f"{self.path}: file exists (pass overwrite=True / --overwrite to replace it)")
        if journal_path(self.path).exists() and not self.overwrite:
            raise SessionError(
                f"{journal_path(self.path)} exists: an interrupted recording was never recovered; run "
                f"`davis-record --recover {self.path}` first (or pass overwrite=True / --overwrite to discard it)"
            )
        info = to_jsonable(self.device_info) if self.device_info is not None else {}
        config = to_jsonable(self.config) if self.config is not None else {}
        start_us = self.start_unix_us if self.start_unix_us is not None else time.time_ns() // 1000
        start_utc = _dt.datetime.fromtimestamp(start_us / 1e6, tz=_dt.timezone.utc).isoformat()
        self._frame_hw = frame_hw_from_device_info(info)
        compression = schema.compression_options()
        try:
            # Default libver: no superblock "open for write" flag that would block reading after a crash.
            self._file = h5py.File(self.path, "w")
        except OSError as exc:
            raise SessionError(f"{self.path}: cannot create the session file: {exc}") from exc
        try:
            f = self._file
            f.attrs[schema.ATTR_FORMAT] = schema.FORMAT_NAME
            f.attrs[schema.ATTR_FORMAT_VERSION] = schema.FORMAT_VERSION
            f.attrs[schema.ATTR_TOOLKIT_VERSION] = __version__
            f.attrs[schema.ATTR_COMPLETE] = False
            f.attrs[schema.ATTR_START_UTC] = start_utc
            f.attrs[schema.ATTR_START_UNIX_US] = np.int64(start_us)
            f.attrs[schema.ATTR_DEVICE_INFO] = json.dumps(info)
            f.attrs[schema.ATTR_CONFIG] = json.dumps(config)
            f.attrs[schema.ATTR_BIASES] = json.dumps(config.get("biases", {}) if isinstance(config, dict) else {})
            f.attrs[schema.ATTR_STATS] = json.dumps({})
            events = f.create_group(schema.EVENTS_GROUP)
            for name, dtype in schema.EVENT_COLUMNS.items():
                events.create_dataset(
                    name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(schema.EVENT_CHUNK,), **compression
                )
            events.create_dataset(
                schema.MS_TO_IDX, shape=(0,), maxshape=(None,), dtype=schema.MS_TO_IDX_DTYPE,
                chunks=(schema.SMALL_CHUNK * 4,), **compression,
            )
            events.attrs[schema.T_OFFSET_ATTR] = np.int64(0)
            # DSEC's EventSlicer reads /ms_to_idx and /t_offset at the root: a hard link and a scalar dataset.
            f[schema.MS_TO_IDX] = events[schema.MS_TO_IDX]
            f.create_dataset(schema.T_OFFSET_ATTR, data=np.int64(0))
            frames = f.create_group(schema.FRAMES_GROUP)
            height, width = self._frame_hw
            frames.create_dataset(
                schema.FRAME_DATA, shape=(0, height, width), maxshape=(None, height, width),
                dtype=schema.FRAME_DTYPE, chunks=(1, height, width), **compression,
            )
            frames.create_dataset(
                schema.FRAME_ROI, shape=(0, 4), maxshape=(None, 4), dtype="<i4", chunks=(schema.SMALL_CHUNK, 4)
            )
            for name in schema.FRAME_TIME_COLUMNS:
                frames.create_dataset(
                    name, shape=(0,), maxshape=(None,), dtype="<i8", chunks=(schema.SMALL_CHUNK,)
                )
            f.create_group(schema.SPECIALS_GROUP)
            f.flush()
        except OSError as exc:
            self._discard_new_file()
            raise SessionError(f"{self.path}: cannot create the session file: {exc}") from exc
        if self.use_journal:
            header = {
                "format": "davis_rig.journal",
                "session_path": str(self.path),
                "toolkit_version": __version__,
                "recording_start_unix_us": start_us,
                "device_info": info,
                "config": config,
            }
            try:
                self.journal = SessionJournal(journal_path(self.path), header).open()
            except SessionError:
                self._discard_new_file()  # the journal removed its own partial file
                raise
        self._t_offset: int | None = None
        self._buffers: dict[str, list] = {"events": [], "frames": [], "specials": [], "imu": []}
        self._buffered_events = 0
        self._ms_written = 0  # number of finalized ms_to_idx entries
        self._n_events_written = 0
        self._n_frames_written = 0
        self._n_table_written = {"specials": 0, "imu": 0}
        self._last_t_written = None
        self._last_t = None  # recording µs (device µs + offset) of the last accepted event
        self._t_max: int | None = None  # latest recording µs accepted on any stream (events, frames, tables)
        self._clock_us: int | None = None  # latest plausible recording µs on any stream (bridges event gaps)
        self._offset_us = 0  # recording µs - device µs; changed by timestamp resets and time discontinuities
        self._discontinuities: list[dict] = []  # the first MAX_OFFSET_ENTRIES {"t_us", "offset_us"} of them
        self._n_discontinuities = 0
        self._repaired_events = 0
        self._resets: list[dict] = []  # the first MAX_OFFSET_ENTRIES {"t_us": reset special's time, "offset_us"}
        self._n_resets = 0
        # device µs of each stream's last item in the current reset epoch (None: nothing since the last reset)
        self._epoch_last_device_t: dict[str, int | None] = {"events": None, "frames": None, "imu": None}
        self._counts = {"events": 0, "frames": 0, "specials": 0, "imu": 0}
        self._committed = dict(self._counts)  # counts as of the last successful HDF5 flush
        self._committed_t_us = None
        self._last_flush = time.monotonic()
        self._failed: Exception | None = None
        self._aborting = False
        return self

    def _discard_new_file(self) -> None:
        """Close and delete the session file :meth:`open` has just created (no data in it yet; best effort)."""
        f, self._file = self._file, None
        try:
            f.close()
        except (OSError, RuntimeError):
            pass  # the file is deleted below either way
        try:
            self.path.unlink(missing_ok=True)
        except OSError:
            pass  # an empty complete=False file: a later recording needs --overwrite, no data is lost

    def discard(self) -> None:
        """Close and delete the file and its journal of a recording that never received data (e.g. the camera
        did not start).

        Raises:
            SessionError: data was already appended (nothing is deleted then; use :meth:`abort`).
        """
        if self._file is None:
            return
        journaled = self.journal.transfers if self.journal is not None else 0
        if any(self._counts.values()) or journaled:
            raise SessionError(
                f"{self.path}: refusing to discard a recording that holds data ({self._counts}, {journaled} "
                "journaled transfers)"
            )
        self._discard_new_file()
        if self.journal is not None:
            self._close_journal(delete=False)
            try:
                self.journal.path.unlink(missing_ok=True)
            except OSError:
                pass  # header only: recover_session turns it into an empty session

    def __enter__(self) -> "SessionWriter":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    @property
    def is_open(self) -> bool:
        """Whether the file is open for appending."""
        return self._file is not None

    @property
    def counts(self) -> dict:
        """Items accepted so far: ``{"events", "frames", "specials", "imu"}`` (buffered + written)."""
        return dict(self._counts)

    @property
    def last_t_us(self) -> int | None:
        """Recording time of the last accepted event, µs: device time plus the offset of the timestamp resets
        before it (see :meth:`append`); ``None`` before the first event."""
        return self._last_t

    def set_stats(self, stats: Mapping) -> None:
        """Record counters kept outside the writer (device drops, decoder stats); stored in the ``stats`` attr.

        Args:
            stats: JSON-able mapping (dataclasses are converted), merged into the stored dict.
        """
        self._extra_stats.update(to_jsonable(dict(stats)))

    def stats(self) -> dict:
        """Return the counters stored in the root ``stats`` attribute."""
        return {
            **self._extra_stats,
            "writer": {
                "events": self._counts["events"],
                "frames": self._counts["frames"],
                "specials": self._counts["specials"],
                "imu": self._counts["imu"],
                "events_time_repaired": self._repaired_events,
                "time_discontinuities": self._n_discontinuities,
                "time_discontinuity_offsets": [dict(entry) for entry in self._discontinuities],
                "timestamp_resets": self._n_resets,
                "timestamp_reset_offsets": [dict(reset) for reset in self._resets],
                "journal_transfers": self.journal.transfers if self.journal else 0,
            },
        }

    # --- appending ----------------------------------------------------------------------------
    def append_raw(self, data: bytes | bytearray | memoryview) -> None:
        """Journal one raw USB transfer (thread-safe; a no-op without a journal)."""
        if self.journal is not None:
            self.journal.append_transfer(data)

    def append(self, chunk, *, device_clock: bool = True) -> None:
        """Append one decoded chunk (anything with ``events``, ``frames``, ``specials`` and optional ``imu``).

        The file keeps one monotonic *recording time*: every item is stored at ``t_device + offset`` (µs). The
        offset starts at 0 (recording time = device time) and changes at two kinds of events, each listed in the
        ``stats`` attribute as ``{"t_us": recording time from which it holds, "offset_us": the new offset}``, so
        the device time of an item at recording time ``t`` is ``t - offset_us`` of the last entry (of both lists)
        with ``t_us <= t``. Each list keeps its first :data:`MAX_OFFSET_ENTRIES` entries; the counts are complete.

        * **Timestamp resets** (``stats["writer"]["timestamp_resets"]``, ``["timestamp_reset_offsets"]``): the
          device clock restarts at 0 after a TIMESTAMP_RESET special (``Davis346.timestamp_reset`` or a sync
          master), and the decoder reports the stream faithfully. Every item after the reset is stored at
          ``t_device + T_before + 1 - t_reset``, where ``t_reset`` is the reset special's device time (0 from the
          decoder) and ``T_before`` the latest recording time written before it on any stream (event times, the
          four frame times, specials, IMU); the reset special itself is stored at ``T_before + 1``. A reset before
          any data keeps the offset.
        * **Time discontinuities** (``["time_discontinuities"]``, ``["time_discontinuity_offsets"]``): damaged
          event timestamps, see :mod:`davis_rig.session.timeline` — time that keeps going back (a lost wrap word)
          continues from the last event time, and a forward jump over ``max_gap_us`` that no other stream bridges
          (a corrupt wrap word) continues 1 µs after it. A single run of events whose timestamp alone goes back or
          sticks out (one corrupt timestamp word) is kept at the previous run's time instead and counted in
          ``["events_time_repaired"]``. Nothing is dropped; a warning is issued once for each kind.

        A chunk may hold data from before and after a reset (the decoder does not split at resets; each array is
        in stream order). The specials are split exactly at the reset specials; events, frames (by end-of-frame
        time) and IMU samples are split where their device time goes back (the restart), at most once per reset in
        the chunk. If the data after a reset is not earlier than the data before it (a reset within about one
        chunk's span of the previous epoch's start), no split is visible and it stays in the old epoch: nothing is
        lost and time stays monotonic, but those items' offset is 0 (relative to the true one). Frames, specials
        and IMU samples take the offset of the stretch of events nearest to their own time.

        Args:
            chunk: a ``DecodedChunk``: ``events`` EVENT_DTYPE [N] in stream order (device µs); ``frames`` list of
                ``ApsFrame``; ``specials`` structured [M] with a ``t`` (and ``type``) field; ``imu`` structured [K]
                or None.
            device_clock: the times are the device clock (reset handling and ``max_gap_us`` above); False for
                times that are already continuous (e.g. an AEDAT4 import): TIMESTAMP_RESET specials are then stored
                as they are and forward jumps are kept (events that go back are still repaired).

        Raises:
            SessionError: the writer is not open or an earlier write failed (disk full, ...).
            FormatError / ShapeError: a field has the wrong dtype or shape.
        """
        self._check_usable()
        events = getattr(chunk, "events", None)
        frames = list(getattr(chunk, "frames", None) or ())
        specials = getattr(chunk, "specials", None)
        imu = getattr(chunk, "imu", None)
        reset_at = _reset_positions(specials) if device_clock and specials is not None and len(specials) else None
        if reset_at is None or not reset_at.shape[0]:  # the common case: one epoch, remember each stream's last time
            if events is not None and len(events):
                self._epoch_last_device_t["events"] = int(events["t"][-1])
            if frames:
                self._epoch_last_device_t["frames"] = int(frames[-1].t_end_of_frame_us)
            if imu is not None and len(imu):
                self._epoch_last_device_t["imu"] = int(imu["t"][-1])
            self._append_epoch(events, frames, specials, imu, bridge_gaps=device_clock)
            self.maybe_flush()
            return
        n_resets = reset_at.shape[0]
        event_epoch = self._epochs("events", None if events is None else np.asarray(events)["t"], n_resets)
        frame_t = np.array([int(frame.t_end_of_frame_us) for frame in frames], dtype=np.int64)
        frame_epoch = self._epochs("frames", frame_t, n_resets)
        imu_epoch = self._epochs("imu", None if imu is None else np.asarray(imu)["t"], n_resets)
        bounds = [0, *reset_at.tolist(), len(specials)]
        for k in range(n_resets + 1):
            if k:
                self._start_reset_epoch(int(specials["t"][bounds[k]]))
            self._append_epoch(
                None if event_epoch is None else events[event_epoch == k],
                [frame for frame, epoch in zip(frames, frame_epoch.tolist()) if epoch == k],
                specials[bounds[k] : bounds[k + 1]],
                None if imu_epoch is None else imu[imu_epoch == k],
                bridge_gaps=True,
            )
        self.maybe_flush()

    def _append_epoch(self, events, frames, specials, imu, *, bridge_gaps: bool) -> None:
        """Append the data of one chunk that lies in the current reset epoch (device µs, see :meth:`append`)."""
        events = self._check_events(events)
        for frame in frames:
            self._check_frame(frame)
        specials = self._check_table("specials", specials)
        imu = self._check_table("imu", imu)
        base = self._offset_us
        max_gap = self.max_gap_us if bridge_gaps else None
        tables = [table for table in (specials, imu) if table is not None]
        other_t = None  # the end of frame for frames
        if frames or tables:
            frame_t = np.array([[int(getattr(f, name)) for name in schema.FRAME_TIME_COLUMNS] for f in frames],
                               dtype=np.int64).reshape(-1, len(schema.FRAME_TIME_COLUMNS))
            other_t = np.concatenate([frame_t[:, -1]] + [table["t"].astype(np.int64) for table in tables]) + base
        if max_gap is not None:
            if self._clock_us is None and events is not None:  # the other streams' evidence starts at the first event
                self._clock_us = int(events["t"][0]) + base
            if other_t is not None:
                self._clock_us = advance_clock(self._clock_us, other_t, max_gap)
        plan = self._append_events(events, base, max_gap) if events is not None else None
        if other_t is None:
            return
        shifts = np.zeros(other_t.shape[0], np.int64) if plan is None else \
            shift_for(other_t, plan.seg_lo_us, plan.seg_hi_us, plan.seg_shift_us)
        shifts += base
        n_frames = frame_t.shape[0]
        for frame, times, offset in zip(frames, frame_t.tolist(), shifts[:n_frames].tolist()):
            self._buffers["frames"].append((frame, offset))
            self._counts["frames"] += 1
            self._note_time(max(times) + offset)
        start = n_frames
        for kind, table in (("specials", specials), ("imu", imu)):
            if table is not None:
                self._buffer_table(kind, table, shifts[start : start + len(table)])
                start += len(table)

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

    def _start_reset_epoch(self, t_reset_device_us: int) -> None:
        """A TIMESTAMP_RESET special at device time ``t_reset_device_us``: continue after the latest time written."""
        if self._t_max is not None:
            self._offset_us = self._t_max + 1 - t_reset_device_us
        self._n_resets += 1
        if len(self._resets) < MAX_OFFSET_ENTRIES:
            self._resets.append({"t_us": t_reset_device_us + self._offset_us, "offset_us": self._offset_us})
        for kind in self._epoch_last_device_t:
            self._epoch_last_device_t[kind] = None
        if self._n_resets == 1:
            warnings.warn(
                f"{self.path}: the device timestamp was reset; later data is stored after the earlier data "
                "(offsets in stats['writer']['timestamp_reset_offsets'])",
                stacklevel=3,
            )

    def _note_time(self, t_us: int) -> None:
        if self._t_max is None or t_us > self._t_max:
            self._t_max = t_us

    def append_events(self, events: np.ndarray) -> None:
        """Append events (EVENT_DTYPE [N] in stream order, device µs of the current reset epoch).

        The current offset (see :meth:`append`, which detects timestamp resets; 0 before any) is added to ``t``
        (the caller's array is not modified). The times are taken as continuous: forward jumps are kept, while
        events that go back in time (which ``ms_to_idx`` cannot index) are repaired as :meth:`append` describes,
        counted in ``stats["writer"]["events_time_repaired"]`` / ``["time_discontinuities"]`` and warned about
        once.

        Raises:
            FormatError: ``events`` is not an EVENT_DTYPE array.
            ShapeError: ``events`` is not 1-D.
        """
        self._check_usable()
        self._append_epoch(events, (), None, None, bridge_gaps=False)

    @staticmethod
    def _check_events(events) -> np.ndarray | None:
        """The events as an EVENT_DTYPE [N] array (``None`` when absent or empty); FormatError / ShapeError."""
        if events is None:
            return None
        events = np.asarray(events)
        if events.dtype != EVENT_DTYPE:
            raise FormatError(f"events: expected dtype {EVENT_DTYPE}, got {events.dtype}")
        if events.ndim != 1:
            raise ShapeError(f"events: expected shape (N,), got {events.shape}")
        return events if len(events) else None

    def _append_events(self, events: np.ndarray, base_us: int, max_gap_us: int | None):
        """Place (see :func:`~davis_rig.session.timeline.plan_event_times`) and buffer checked events."""
        plan = plan_event_times(events["t"] + base_us, self._last_t, self._clock_us, max_gap_us)
        self._note_repairs(plan, base_us)
        if base_us or plan.repaired or plan.shifts:  # else the times are unchanged: no copy at the peak rate
            events = events.copy()
            events["t"] = plan.t_us
        if self._t_offset is None:
            self._t_offset = int(events["t"][0]) // 1000 * 1000
            self._file[schema.EVENTS_GROUP].attrs[schema.T_OFFSET_ATTR] = np.int64(self._t_offset)
            self._file[schema.T_OFFSET_ATTR][()] = np.int64(self._t_offset)
        self._buffers["events"].append(events)
        self._buffered_events += len(events)
        self._counts["events"] += len(events)
        self._last_t = int(events["t"][-1])
        self._clock_us = self._last_t if self._clock_us is None else max(self._clock_us, self._last_t)
        self._note_time(self._last_t)
        if self._buffered_events >= WRITE_BATCH_EVENTS:
            self._write_out()
        return plan

    def _note_repairs(self, plan, base_us: int) -> None:
        """Count a batch's repaired timestamps and discontinuities, move the offset, warn once for each kind."""
        if plan.repaired:
            if not self._repaired_events:
                warnings.warn(
                    f"{self.path}: {plan.repaired} events have a timestamp that goes back or sticks out (a damaged "
                    "timestamp word); they are kept at the previous events' time (counted in "
                    "stats['writer']['events_time_repaired'])",
                    stacklevel=4,
                )
            self._repaired_events += plan.repaired
        if not plan.shifts:
            return
        if not self._n_discontinuities:
            warnings.warn(
                f"{self.path}: the device time jumps (a damaged timestamp: it goes back, or ahead by more than "
                f"{self.max_gap_us} µs with nothing in between); the data after it continues where the data before "
                "it ended (offsets in stats['writer']['time_discontinuity_offsets'])",
                stacklevel=4,
            )
        for index, shift in plan.shifts:
            self._n_discontinuities += 1
            if len(self._discontinuities) < MAX_OFFSET_ENTRIES:
                self._discontinuities.append({"t_us": int(plan.t_us[index]), "offset_us": base_us + shift})
        self._offset_us = base_us + plan.shifts[-1][1]

    def append_frame(self, frame) -> None:
        """Append one APS frame (``ApsFrame``: ``pixels`` uint16 [h, w] at ``position_x/y`` plus four times, device
        µs; the current offset is added when written, see :meth:`append`).

        Raises:
            ShapeError: the frame's region does not fit the sensor.
        """
        self._check_usable()
        self._append_epoch(None, [frame], None, None, bridge_gaps=False)

    def _check_frame(self, frame) -> None:
        """Raise ShapeError unless the frame's pixels are 2-D and its region fits the sensor."""
        pixels = np.asarray(frame.pixels)
        height, width = self._frame_hw
        if pixels.ndim != 2:
            raise ShapeError(f"frame pixels: expected shape (rows, cols), got {pixels.shape}")
        x0, y0 = int(frame.position_x), int(frame.position_y)
        if x0 < 0 or y0 < 0 or y0 + pixels.shape[0] > height or x0 + pixels.shape[1] > width:
            raise ShapeError(
                f"frame ROI {pixels.shape} at (x={x0}, y={y0}) does not fit the sensor ({height}, {width})"
            )

    @staticmethod
    def _check_table(kind: str, table) -> np.ndarray | None:
        """The table as an array (``None`` when absent or empty); FormatError without a ``t`` field."""
        if table is None:
            return None
        table = np.asarray(table)
        if table.dtype.names is None or "t" not in table.dtype.names:
            raise FormatError(f"{kind}: expected a structured array with a 't' field, got dtype {table.dtype}")
        return table if len(table) else None

    def _buffer_table(self, kind: str, table: np.ndarray, offsets_us: np.ndarray) -> None:
        """Buffer specials or IMU samples with their offsets (int64 [K], µs) added to ``t``."""
        table = table.copy()
        table["t"] += offsets_us.astype(table.dtype["t"])
        self._buffers[kind].append(table)
        self._counts[kind] += len(table)
        self._note_time(int(table["t"].max()))

    # --- writing ------------------------------------------------------------------------------
    def maybe_flush(self) -> None:
        """Flush if the last flush is older than ``flush_interval_s`` (called by :meth:`append`)."""
        if time.monotonic() - self._last_flush >= self.flush_interval_s:
            self.flush()
        elif self.journal is not None:
            self.journal.sync()

    def flush(self) -> None:
        """Write all buffered data, update the stats attribute and flush the HDF5 file; check the journal for
        write errors (it fsyncs in its own thread every :data:`~davis_rig.session.journal.FSYNC_INTERVAL_S`).

        Raises:
            SessionError: the write failed (disk full, ...); the file keeps the data of the last good flush.
        """
        self._check_usable()
        self._write_out()
        self._guarded(self._flush_file)
        self._committed = dict(self._counts)
        self._committed_t_us = self._last_t
        self._last_flush = time.monotonic()
        if self.journal is not None:
            self.journal.sync()  # raises a journal write error; the journal fsyncs in its own thread

    def _flush_file(self) -> None:
        self._file.attrs[schema.ATTR_STATS] = json.dumps(self.stats())
        self._file.flush()

    def _write_out(self) -> None:
        if not (self._buffered_events or any(self._buffers[k] for k in ("frames", "specials", "imu"))):
            return
        self._check_space()
        self._guarded(self._write_buffers)

    def _write_buffers(self) -> None:
        f = self._file
        if self._buffers["events"]:
            parts, self._buffers["events"] = self._buffers["events"], []
            self._buffered_events = 0
            group = f[schema.EVENTS_GROUP]
            n0 = self._n_events_written
            # Column by column: contiguous arrays straight from the strided views, no structured copy.
            t_rel = np.concatenate([part["t"] for part in parts])
            t_rel -= self._t_offset
            _extend(group["t"], t_rel)
            for name in ("x", "y", "p"):
                _extend(group[name], np.concatenate([part[name] for part in parts]))
            # ms m is final once an event with t >= 1000 m has been seen (later events are not older).
            # Written in blocks of MS_INDEX_BLOCK entries: memory stays bounded however long the gap is.
            last_ms = int(t_rel[-1]) // 1000
            for lo in range(self._ms_written, last_ms + 1, MS_INDEX_BLOCK):
                ms = np.arange(lo, min(lo + MS_INDEX_BLOCK, last_ms + 1), dtype=np.int64) * 1000
                idx = n0 + np.searchsorted(t_rel, ms, side="left")
                _extend(group[schema.MS_TO_IDX], idx.astype(schema.MS_TO_IDX_DTYPE))
            self._ms_written = max(self._ms_written, last_ms + 1)
            self._n_events_written = n0 + len(t_rel)
            self._last_t_written = int(t_rel[-1]) + self._t_offset
        if self._buffers["frames"]:
            frames, self._buffers["frames"] = self._buffers["frames"], []
            height, width = self._frame_hw
            data = np.zeros((len(frames), height, width), dtype=schema.FRAME_DTYPE)
            roi = np.empty((len(frames), 4), dtype="<i4")
            times = {name: np.empty(len(frames), dtype="<i8") for name in schema.FRAME_TIME_COLUMNS}
            for i, (frame, offset_us) in enumerate(frames):
                pixels = np.asarray(frame.pixels)
                x0, y0 = int(frame.position_x), int(frame.position_y)
                data[i, y0 : y0 + pixels.shape[0], x0 : x0 + pixels.shape[1]] = pixels
                roi[i] = (x0, y0, pixels.shape[1], pixels.shape[0])
                for name in schema.FRAME_TIME_COLUMNS:
                    times[name][i] = int(getattr(frame, name)) + offset_us
            group = f[schema.FRAMES_GROUP]
            _extend(group[schema.FRAME_DATA], data)
            _extend(group[schema.FRAME_ROI], roi)
            for name, column in times.items():
                _extend(group[name], column)
            self._n_frames_written += len(frames)
        for kind, group_name in (("specials", schema.SPECIALS_GROUP), ("imu", schema.IMU_GROUP)):
            if not self._buffers[kind]:
                continue
            table = np.concatenate(self._buffers[kind])
            self._buffers[kind] = []
            group = f.require_group(group_name)
            for name in table.dtype.names:
                if name not in group:
                    group.create_dataset(
                        name, shape=(0,), maxshape=(None,), dtype=table.dtype[name], chunks=(schema.SMALL_CHUNK,)
                    )
                _extend(group[name], np.ascontiguousarray(table[name]))
            self._n_table_written[kind] += len(table)

    def _guarded(self, operation) -> None:
        """Run an HDF5 write; turn a failure into SessionError (the file is closed, the journal kept)."""
        try:
            operation()
        except (OSError, RuntimeError) as exc:
            self._failed = exc
            kept = dict(self._committed)
            f, self._file = self._file, None
            try:
                f.close()
            except (OSError, RuntimeError, ValueError):
                pass
            self._close_journal(delete=False)
            reason = "disk full" if _is_disk_full(exc) else "write failed"
            raise SessionError(
                f"{self.path}: {reason} while writing ({exc}); the file may be damaged — data up to the last "
                f"flush: {kept['events']} events, {kept['frames']} frames"
                + (f"; recover it from the journal with `davis-record --recover {self.path}`"
                   if self.journal is not None else "")
            ) from exc

    def _free_bytes(self) -> int:
        """Bytes available to this process on the file's filesystem (``os.statvfs``)."""
        stat = os.statvfs(self.path.parent if str(self.path.parent) else ".")
        return stat.f_bavail * stat.f_frsize

    def _check_space(self) -> None:
        """Stop cleanly *before* HDF5 can hit a full disk (HDF5 corrupts a file it cannot extend).

        The buffered data's uncompressed size plus :data:`METADATA_MARGIN_BYTES` plus ``min_free_bytes`` must
        be free; otherwise the buffered data (≤ one flush interval) is discarded, the file is finalized with
        what it already holds, and :class:`SessionError` reports what was kept. While :meth:`abort` runs the
        file is not finalized (an aborted recording is never marked complete): the buffered data is left
        unwritten (a journal, which ``abort`` keeps, still holds it) and :class:`SessionError` is raised.
        """
        height, width = self._frame_hw
        needed = (
            self._buffered_events * EVENT_DTYPE.itemsize
            + len(self._buffers["frames"]) * height * width * 2
            + sum(table.nbytes for kind in ("specials", "imu") for table in self._buffers[kind])
            + METADATA_MARGIN_BYTES
        )
        free = self._free_bytes()
        if free >= needed + self.min_free_bytes:
            return
        if self._aborting:
            raise SessionError(
                f"{self.path}: disk nearly full while aborting ({free} bytes free): the buffered data was not "
                "written; the file stays marked incomplete"
            )
        lost_events = self._buffered_events
        lost_frames = len(self._buffers["frames"])
        for kind in self._buffers:
            self._buffers[kind] = []
        self._buffered_events = 0
        self._counts = {
            "events": self._n_events_written,
            "frames": self._n_frames_written,
            "specials": self._n_table_written["specials"],
            "imu": self._n_table_written["imu"],
        }
        self._last_t = self._last_t_written
        self._extra_stats["stopped_by"] = (
            f"disk nearly full: {free} bytes free, {needed + self.min_free_bytes} needed; "
            f"{lost_events} buffered events and {lost_frames} frames discarded"
        )
        self._finalize_and_close(delete_journal=False)
        self._failed = SessionError("disk nearly full")
        raise SessionError(
            f"{self.path}: disk nearly full ({free / 2**20:.1f} MiB free, {(needed + self.min_free_bytes) / 2**20:.1f}"
            f" MiB needed for the next write): recording stopped and the file was closed cleanly with "
            f"{self._counts['events']} events and {self._counts['frames']} frames "
            f"(the last {lost_events} buffered events / {lost_frames} frames, at most one flush interval, were not "
            "written)" + (f"; the raw journal {self.journal.path} was kept" if self.journal is not None else "")
        )

    def _check_usable(self) -> None:
        if self._failed is not None:
            raise SessionError(f"{self.path}: the writer stopped after an earlier error: {self._failed}")
        if self._file is None:
            raise SessionError(f"{self.path}: the writer is not open (use `with SessionWriter(...) as w:`)")

    def close(self) -> None:
        """Write everything, finalize ``ms_to_idx`` and the attributes, close the file and delete the journal.

        Raises:
            SessionError: the final write failed (the journal is then kept for recovery).
        """
        if self._file is None:
            return
        self._check_usable()
        self._write_out()
        self._finalize_and_close(delete_journal=True)

    def _finalize_and_close(self, delete_journal: bool) -> None:
        def finalize() -> None:
            group = self._file[schema.EVENTS_GROUP]
            # One sentinel entry past the last event's millisecond: ms_to_idx[m + 1] always exists.
            if self._last_t is not None:
                _extend(group[schema.MS_TO_IDX], np.array([self._n_events_written], dtype=schema.MS_TO_IDX_DTYPE))
            self._file.attrs[schema.ATTR_COMPLETE] = True
            self._flush_file()
            self._file.close()

        self._guarded(finalize)
        self._file = None
        self._close_journal(delete=delete_journal)

    def _close_journal(self, delete: bool) -> None:
        if self.journal is not None:
            try:
                self.journal.close(delete=delete)
            except SessionError:
                if delete:
                    raise

    def abort(self) -> None:
        """Close after an error elsewhere: write what is buffered (if the disk has room), keep
        ``complete=False`` and the journal."""
        if self._file is None:
            return
        self._aborting = True
        try:
            if self._failed is None:
                self._write_out()
                self._flush_file()
        except (OSError, RuntimeError, SessionError):
            pass  # the error that made us abort is the one to report; the journal is kept for recovery
        finally:
            if self._file is not None:  # _guarded has closed it after a failed write
                try:
                    self._file.close()
                except (OSError, RuntimeError, ValueError):
                    pass
            self._file = None
            self._close_journal(delete=False)


def _extend(dataset, values: np.ndarray) -> None:
    n0 = dataset.shape[0]
    dataset.resize((n0 + len(values), *dataset.shape[1:]))
    dataset[n0:] = values


def _is_disk_full(exc: OSError) -> bool:
    text = str(exc)
    return getattr(exc, "errno", None) in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT) or "No space" in text \
        or "File too large" in text
