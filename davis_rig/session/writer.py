"""Write a session.h5 incrementally while a recording runs (see :mod:`davis_rig.session.schema`).

:class:`SessionWriter` buffers, flushes, watches the free space and closes; the times it stores come from a
:class:`~davis_rig.session.clock.RecordingClock` and the HDF5 writes are :mod:`davis_rig.session.h5file`'s.
"""

from __future__ import annotations

import errno
import json
import os
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from davis_rig import __version__
from davis_rig.errors import FormatError, SessionError, ShapeError
from davis_rig.session import h5file, schema
from davis_rig.session.clock import RecordingClock
from davis_rig.session.journal import SessionJournal, journal_in_use, journal_path
from davis_rig.types import EVENT_DTYPE

#: Buffered events that trigger a write to HDF5 before the flush interval is up.
WRITE_BATCH_EVENTS = 1 << 20
#: Free space kept for HDF5 metadata on top of the data of each write, bytes.
METADATA_MARGIN_BYTES = 1 << 20
#: Default free space that must remain after a write, bytes (the recording stops cleanly below it).
MIN_FREE_BYTES = 64 << 20
#: Default largest forward jump of the device clock taken as it is, µs (policy, see :class:`SessionWriter`).
MAX_GAP_US = 1_000_000


def _open_for_writing_elsewhere(path: Path) -> bool:
    """Whether another writer (a recording without a journal, a label writer) holds HDF5's lock on ``path``:
    opening it to read with HDF5's locking fails then. ``False`` for a missing file, one that is not HDF5, or a
    file system without locks."""
    import h5py

    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r", locking=True):
            return False
    except OSError as exc:  # held: EWOULDBLOCK from another process's lock, mismatched lock flags in this one
        # (a file system without locks, errno ENOSYS, and a damaged file are not held: they may be replaced)
        return f"unable to lock file, errno = {errno.EWOULDBLOCK}," in str(exc) or "flag values don't match" in str(exc)


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
            SessionError: the file exists and ``overwrite`` is false, another recording is writing it, or it (or
                its journal) cannot be created;
                then a file created by this call is removed again (it holds no data).
        """
        import h5py

        if self._file is not None:
            return self
        if journal_in_use(journal_path(self.path)) or (self.overwrite and _open_for_writing_elsewhere(self.path)):
            # even with overwrite: "w" would truncate the live file before HDF5's own lock refused this writer
            raise SessionError(f"{self.path}: being recorded right now by another recording; choose another file")
        if self.path.exists() and not self.overwrite:
            raise SessionError(f"{self.path}: file exists (pass overwrite=True / --overwrite to replace it)")
        if journal_path(self.path).exists() and not self.overwrite:
            raise SessionError(
                f"{journal_path(self.path)} exists: an interrupted recording was never recovered; run "
                f"`davis-record --recover {self.path}` first (or pass overwrite=True / --overwrite to discard it)"
            )
        info = h5file.to_jsonable(self.device_info) if self.device_info is not None else {}
        config = h5file.to_jsonable(self.config) if self.config is not None else {}
        start_us = self.start_unix_us if self.start_unix_us is not None else time.time_ns() // 1000
        self._frame_hw = h5file.frame_hw_from_device_info(info)
        compression = schema.compression_options()
        try:
            # Default libver: no superblock "open for write" flag that would block reading after a crash.
            self._file = h5py.File(self.path, "w")
        except OSError as exc:
            raise SessionError(f"{self.path}: cannot create the session file: {exc}") from exc
        try:
            h5file.create_layout(self._file, info=info, config=config, start_us=start_us, frame_hw=self._frame_hw,
                                 compression=compression)
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
        self._clock = RecordingClock(self.max_gap_us, self.path)
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
        return self._clock.last_t

    def set_stats(self, stats: Mapping) -> None:
        """Record counters kept outside the writer (device drops, decoder stats); stored in the ``stats`` attr.

        Args:
            stats: JSON-able mapping (dataclasses are converted), merged into the stored dict.
        """
        self._extra_stats.update(h5file.to_jsonable(dict(stats)))

    def stats(self) -> dict:
        """Return the counters stored in the root ``stats`` attribute."""
        return {
            **self._extra_stats,
            "writer": {
                "events": self._counts["events"],
                "frames": self._counts["frames"],
                "specials": self._counts["specials"],
                "imu": self._counts["imu"],
                "events_time_repaired": self._clock.repaired_events,
                "time_discontinuities": self._clock.n_discontinuities,
                "time_discontinuity_offsets": [dict(entry) for entry in self._clock.discontinuities],
                "timestamp_resets": self._clock.n_resets,
                "timestamp_reset_offsets": [dict(reset) for reset in self._clock.resets],
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
        with ``t_us <= t``. Each list keeps its first :data:`~davis_rig.session.clock.MAX_OFFSET_ENTRIES` entries;
        the counts are complete.

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

        A chunk may hold data from before and after a reset: see
        :meth:`~davis_rig.session.clock.RecordingClock.split_at_resets` for where it is split. Frames, specials
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
            FormatError / ShapeError: a field has the wrong dtype or shape; FormatError also when times are
                so far apart (garbage of a damaged file) that the continued recording time leaves int64 µs.
        """
        self._check_usable()
        events, specials = getattr(chunk, "events", None), getattr(chunk, "specials", None)
        imu = getattr(chunk, "imu", None)
        frames = list(getattr(chunk, "frames", None) or ())
        epochs = self._clock.split_at_resets(events, frames, specials, imu, device_clock=device_clock)
        if epochs is None:  # the common case: one epoch
            self._append_epoch(events, frames, specials, imu, bridge_gaps=device_clock)
        else:
            for epoch in epochs:
                if epoch.reset_t_us is not None:
                    self._clock.start_reset(epoch.reset_t_us)
                self._append_epoch(epoch.events, epoch.frames, epoch.specials, epoch.imu,
                                   bridge_gaps=epoch.bridge_gaps)
        self.maybe_flush()

    def _append_epoch(self, events, frames, specials, imu, *, bridge_gaps: bool) -> None:
        """Append the data of one chunk that lies in the current reset epoch (device µs, see :meth:`append`)."""
        events = self._check_events(events)
        for frame in frames:
            self._check_frame(frame)
        specials = self._check_table("specials", specials)
        imu = self._check_table("imu", imu)
        tables = [table for table in (specials, imu) if table is not None]
        try:
            events, offsets = self._clock.place(events, frames, tables, bridge_gaps=bridge_gaps)
        except OverflowError as exc:  # only garbage times (a damaged import) get offsets beyond int64
            raise FormatError(f"{self.path}: event times out of range: continuing them monotonically leaves the "
                              "int64 µs range (damaged input)") from exc
        if events is not None:
            self._buffer_events(events)
        if offsets is None:
            return
        n_frames = len(frames)
        for frame, offset in zip(frames, offsets[:n_frames].tolist()):
            self._buffers["frames"].append((frame, offset))
            self._counts["frames"] += 1
            self._clock.note_time(max(int(getattr(frame, name)) for name in schema.FRAME_TIME_COLUMNS) + offset)
        start = n_frames
        for kind, table in (("specials", specials), ("imu", imu)):
            if table is not None:
                self._buffer_table(kind, table, offsets[start : start + len(table)])
                start += len(table)

    def append_events(self, events: np.ndarray) -> None:
        """Append events (EVENT_DTYPE [N] in stream order, device µs of the current reset epoch).

        The current offset (see :meth:`append`, which detects timestamp resets; 0 before any) is added to ``t``
        (the caller's array is not modified). The times are taken as continuous: forward jumps are kept, while
        events that go back in time (which ``ms_to_idx`` cannot index) are repaired as :meth:`append` describes,
        counted in ``stats["writer"]["events_time_repaired"]`` / ``["time_discontinuities"]`` and warned about
        once.

        Raises:
            FormatError: ``events`` is not an EVENT_DTYPE array, or its times leave int64 µs (see :meth:`append`).
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

    def _buffer_events(self, events: np.ndarray) -> None:
        """Buffer events placed at their recording times (the first ones set the file's ``t_offset``)."""
        if self._t_offset is None:
            self._t_offset = int(events["t"][0]) // 1000 * 1000
            self._file[schema.EVENTS_GROUP].attrs[schema.T_OFFSET_ATTR] = np.int64(self._t_offset)
            self._file[schema.T_OFFSET_ATTR][()] = np.int64(self._t_offset)
        self._buffers["events"].append(events)
        self._buffered_events += len(events)
        self._counts["events"] += len(events)
        if self._buffered_events >= WRITE_BATCH_EVENTS:
            self._write_out()

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
        self._clock.note_time(int(table["t"].max()))

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
        self._committed_t_us = self._clock.last_t
        self._last_flush = time.monotonic()
        if self.journal is not None:
            self.journal.sync()  # raises a journal write error; the journal fsyncs in its own thread

    def _flush_file(self) -> None:
        self._file.attrs[schema.ATTR_STATS] = json.dumps(self.stats())
        self._file.flush()

    def _write_out(self) -> None:
        if not (self._buffered_events or any(self._buffers[k] for k in ("frames", "specials", "imu"))):
            return
        if self.journal is not None:
            self.journal.flush_to_os()  # the journal first: it must never hold less than the file
        self._check_space()
        self._guarded(self._write_buffers)

    def _write_buffers(self) -> None:
        f = self._file
        if self._buffers["events"]:
            parts, self._buffers["events"] = self._buffers["events"], []
            self._buffered_events = 0
            self._ms_written = h5file.write_events(f[schema.EVENTS_GROUP], parts, self._t_offset,
                                                   self._n_events_written, self._ms_written)
            self._n_events_written += sum(len(part) for part in parts)
            self._last_t_written = int(parts[-1]["t"][-1])
        if self._buffers["frames"]:
            frames, self._buffers["frames"] = self._buffers["frames"], []
            h5file.write_frames(f[schema.FRAMES_GROUP], frames, self._frame_hw)
            self._n_frames_written += len(frames)
        for kind, group_name in (("specials", schema.SPECIALS_GROUP), ("imu", schema.IMU_GROUP)):
            if not self._buffers[kind]:
                continue
            table = np.concatenate(self._buffers[kind])
            self._buffers[kind] = []
            h5file.write_table(f, group_name, table)
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
            reason = "disk full" if h5file.is_disk_full(exc) else "write failed"
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
        self._clock.last_t = self._last_t_written
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
            if self._clock.last_t is not None:
                h5file.extend(group[schema.MS_TO_IDX], np.array([self._n_events_written], dtype=schema.MS_TO_IDX_DTYPE))
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

