"""Record a camera into a session.h5: the one API call behind ``davis-record``.

:func:`record_session` journals the raw USB transfers next to the file (``<path>.journal``, see
:mod:`davis_rig.session.journal`) so that :func:`~davis_rig.session.recovery.recover_session` can rebuild the file
after a crash; the journal is deleted when the recording ends cleanly. An unplug (:class:`DeviceDisconnectedError`)
ends the recording normally: everything decoded before it is written and the file is closed
(``stopped_by=StopReason.DISCONNECTED``). A device timestamp reset during the recording
(``Davis346.timestamp_reset`` or a sync master) loses nothing: the data after it is stored after the data before
it, offset so the file's time stays monotonic; the offsets are in ``stats["writer"]["timestamp_reset_offsets"]``
(see :meth:`SessionWriter.append`).

Capture path: this module never imports torch (nor the device package: the camera is passed in).
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Callable

from davis_rig.errors import DavisRigError, DeviceDisconnectedError, DeviceError, TransportError
from davis_rig.session.h5file import to_jsonable
from davis_rig.session.writer import SessionWriter

#: Longest wait for data inside the camera's chunk iterator, s (bounds the reaction time to stop / duration).
POLL_TIMEOUT_S = 0.1


class StopReason(StrEnum):
    """Why :func:`record_session` ended: the duration was up, ``stop_event`` was set (Ctrl-C), the camera was
    unplugged, or acquisition was stopped by someone else (the stream ended)."""

    DURATION = "duration"
    STOP = "stop"
    DISCONNECTED = "disconnected"
    END = "end"


@dataclass(frozen=True)
class RecordingProgress:
    """A snapshot passed to the ``progress`` callback about twice per second.

    Attributes:
        elapsed_s: wall-clock time since start, s.
        events, frames: items written so far.
        event_rate_hz: events per second over the last interval, Hz.
        dropped_transfers: USB transfers the camera dropped so far (its ring buffer overflowed).
        decoder_errors: unknown words + out-of-range DVS addresses + dropped frames/samples so far.
    """

    elapsed_s: float
    events: int
    frames: int
    event_rate_hz: float
    dropped_transfers: int
    decoder_errors: int


@dataclass(frozen=True)
class RecordingSummary:
    """What :func:`record_session` recorded.

    Attributes:
        path: the session file.
        duration_s: wall-clock recording time, s.
        events, frames, specials, imu: items in the file.
        stopped_by: a :class:`StopReason`.
        camera_stats: the camera's counters at the end (transfers, bytes, dropped_transfers, decoder stats).
    """

    path: Path
    duration_s: float
    events: int
    frames: int
    specials: int
    imu: int
    stopped_by: StopReason
    camera_stats: dict = field(default_factory=dict)

    @property
    def dropped_transfers(self) -> int:
        """USB transfers the camera dropped during the recording."""
        return int(self.camera_stats.get("dropped_transfers", 0) or 0)


def _camera_stats(camera) -> dict:
    stats = getattr(camera, "stats", None)
    if callable(stats):
        stats = stats()
    return to_jsonable(stats) if stats is not None else {}


def _decoder_errors(stats: dict) -> int:
    decoder = stats.get("decoder") or {}
    if not isinstance(decoder, dict):
        return 0
    keys = ("unknown_words", "dvs_out_of_range", "aps_frames_dropped", "aps_samples_dropped", "imu_samples_dropped")
    return int(sum(int(decoder.get(key, 0) or 0) for key in keys))


def _aps_setting(camera, name: str, requested: int | None, default_config_sent: bool) -> int | None:
    """The APS setting ``name`` (µs) in effect: the requested value, else the camera's tracked value after the
    default configuration (``None`` when neither is known: no default config sent, nothing requested)."""
    if requested is not None:
        return int(requested)
    if not default_config_sent:
        return None
    value = getattr(camera, name, None)
    return int(value) if value is not None else None


def _remove_listener(camera, listener) -> None:
    remove = getattr(camera, "remove_raw_listener", None)
    if remove is not None:
        remove(listener)


def _start_or_discard(camera, writer: SessionWriter) -> None:
    """Start the camera; if that fails nothing was recorded: unhook the writer, delete its file and journal.

    Raises:
        DeviceError: the camera did not start (the original error is chained).
    """
    try:
        camera.start()
    except BaseException as exc:
        _remove_listener(camera, writer.append_raw)
        writer.discard()
        if isinstance(exc, DeviceError):
            raise DeviceError(
                f"the camera did not start ({exc}); nothing was recorded and {writer.path} was not kept"
            ) from exc
        raise


def _stop_and_drain(camera, writer: SessionWriter) -> None:
    """Stop the camera, then write every transfer it read before the stop (its reader keeps them queued;
    ``read`` returns ``None`` once the reader has ended and the queue is empty).

    Raises:
        TransportError: the stop sequence failed (the camera stopped answering); raised after the data read before
            it has been written. ``DeviceDisconnectedError`` (unplugged while stopping) likewise.
    """
    try:
        camera.stop()
        stop_error = None
    except TransportError as exc:
        stop_error = exc
    while (chunk := camera.read(POLL_TIMEOUT_S)) is not None:
        writer.append(chunk)
    if stop_error is not None:
        raise stop_error


class _ProgressReporter:
    """Stores the camera's counters in the file (and its journal) and calls ``progress`` every ``interval_s``."""

    def __init__(self, camera, writer: SessionWriter, progress: Callable[[RecordingProgress], None] | None,
                 interval_s: float):
        self.camera = camera
        self.writer = writer
        self.progress = progress
        self.interval_s = interval_s
        self.t_start = time.monotonic()
        self._last, self._last_events = self.t_start, 0

    def maybe_report(self, now: float) -> None:
        """Report if the last report is at least ``interval_s`` old (``now``: ``time.monotonic()``, s)."""
        if now - self._last < self.interval_s:
            return
        writer = self.writer
        stats = _camera_stats(self.camera)
        writer.set_stats({"camera": stats})
        if writer.journal is not None:
            writer.journal.note({"camera": stats})
        if self.progress is not None:
            events = writer.counts["events"]
            self.progress(RecordingProgress(
                elapsed_s=now - self.t_start,
                events=events,
                frames=writer.counts["frames"],
                event_rate_hz=(events - self._last_events) / (now - self._last),
                dropped_transfers=int(stats.get("dropped_transfers", 0) or 0),
                decoder_errors=_decoder_errors(stats),
            ))
        self._last, self._last_events = now, writer.counts["events"]


def _configure(camera, exposure_us: int | None, frame_interval_us: int | None, send_default_config: bool) -> dict:
    """Send the settings to the camera; returns the recording configuration stored in the file."""
    if send_default_config:
        camera.send_default_config()
    if exposure_us is not None:
        camera.set_exposure(int(exposure_us))
    if frame_interval_us is not None:
        camera.set_frame_interval(int(frame_interval_us))
    return {
        "exposure_us": _aps_setting(camera, "exposure_us", exposure_us, send_default_config),
        "frame_interval_us": _aps_setting(camera, "frame_interval_us", frame_interval_us, send_default_config),
        "default_config_sent": send_default_config,
        "biases": to_jsonable(getattr(camera, "biases", None)) or {},
    }


def _write_until_stopped(camera, writer: SessionWriter, reporter: _ProgressReporter, duration_s: float | None,
                         stop_event: threading.Event) -> StopReason:
    """Write the camera's chunks until the duration is up, ``stop_event`` is set or acquisition ends elsewhere."""
    while True:
        chunk = camera.read(POLL_TIMEOUT_S)
        if chunk is not None:
            writer.append(chunk)
        elif not camera.running:
            return StopReason.END  # acquisition ended elsewhere and everything read was delivered
        else:
            writer.maybe_flush()
        now = time.monotonic()
        reporter.maybe_report(now)
        if stop_event.is_set():
            return StopReason.STOP
        if duration_s is not None and now - reporter.t_start >= duration_s:
            return StopReason.DURATION


def _stop_after_error(camera) -> None:
    """Leave the camera stopped after an error (disk full, Ctrl-C outside the CLI, a bug); the error goes on."""
    try:
        camera.stop()
    except DavisRigError:
        pass


def record_session(
    camera,
    path: str | os.PathLike,
    *,
    duration_s: float | None = None,
    exposure_us: int | None = None,
    frame_interval_us: int | None = None,
    overwrite: bool = False,
    journal: bool = True,
    send_default_config: bool = True,
    stop_event: threading.Event | None = None,
    progress: Callable[[RecordingProgress], None] | None = None,
    progress_interval_s: float = 0.5,
) -> RecordingSummary:
    """Configure an open camera, record it into ``path`` until ``duration_s`` / ``stop_event`` / unplug, and stop.

    The module docstring tells what happens to the journal, at an unplug and at a device timestamp reset.

    Args:
        camera: an open ``davis_rig.device.camera.Davis346`` (or an object with the same methods: ``info``,
            ``send_default_config``, ``set_exposure``, ``set_frame_interval``, ``biases``, ``start``, ``stop``,
            ``read(timeout_s)``, ``running``, ``stats``, ``add_raw_listener``; optionally ``exposure_us`` /
            ``frame_interval_us``, the settings in effect, stored in the file's config).
        path: session.h5 to create.
        duration_s: stop after this wall-clock time, s (``None``: until ``stop_event`` or the stream ends).
        exposure_us: APS exposure, µs (``None``: the camera default; the value in effect is stored either way).
        frame_interval_us: APS frame interval, µs (``None``: the camera default; stored like ``exposure_us``).
        overwrite: replace an existing file.
        journal: keep the raw-transfer journal (crash recovery).
        send_default_config: send libcaer's default configuration before the settings above.
        stop_event: set it (e.g. from a SIGINT handler) to stop cleanly.
        progress: called with a :class:`RecordingProgress` every ``progress_interval_s`` s.
        progress_interval_s: progress period, s.

    Returns:
        A :class:`RecordingSummary`.

    Raises:
        SessionError: the file exists (without ``overwrite``) or cannot be written (disk full: the file is
            closed cleanly with the data written so far, see :class:`SessionWriter`).
        DeviceError: the camera failed before or while starting (then no file and no journal are left).
    """
    if duration_s is not None and duration_s < 0:
        raise ValueError(f"duration_s must be >= 0, got {duration_s}")
    config = _configure(camera, exposure_us, frame_interval_us, send_default_config)
    path = Path(path)
    with SessionWriter(path, device_info=camera.info, config=config, overwrite=overwrite,
                       journal=journal) as writer:
        camera.add_raw_listener(writer.append_raw)
        _start_or_discard(camera, writer)
        reporter = _ProgressReporter(camera, writer, progress, progress_interval_s)
        try:
            stopped_by = _write_until_stopped(camera, writer, reporter, duration_s, stop_event or threading.Event())
            _stop_and_drain(camera, writer)
        except DeviceDisconnectedError:
            stopped_by = StopReason.DISCONNECTED
            camera.stop()  # safe after an unplug: only stops the reader thread
        except BaseException:
            _stop_after_error(camera)
            raise
        finally:
            _remove_listener(camera, writer.append_raw)
        duration = time.monotonic() - reporter.t_start
        stats = _camera_stats(camera)
        writer.set_stats({"camera": stats, "stopped_by": stopped_by})
        counts = writer.counts
    return RecordingSummary(path=path, duration_s=duration, events=counts["events"], frames=counts["frames"],
                            specials=counts["specials"], imu=counts["imu"], stopped_by=stopped_by,
                            camera_stats=stats)


__all__ = ["RecordingProgress", "RecordingSummary", "StopReason", "record_session"]
