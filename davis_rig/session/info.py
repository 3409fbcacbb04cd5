"""What a session.h5 holds, in one summary: duration, counts and rates, losses, device, labels, integrity.

:func:`describe_session` reads only what the file already summarises (attributes, ``ms_to_idx``, the small
per-frame / special / IMU / label tables and two milliseconds of events), so it takes the same time on a 1 GB
session as on the bundled sample. ``davis-info`` prints it as text or JSON.

Integrity (:attr:`SessionInfo.integrity`):

- ``"complete"``: the writer closed the file cleanly and no journal is left;
- ``"recording"``: a running recording holds ``<session>.journal`` (:func:`~davis_rig.session.journal.journal_in_use`):
  the file holds what was flushed so far;
- ``"needs recovery"``: ``<session>.journal`` exists (a crash, or a recording stopped for a full disk):
  ``davis-record --recover`` rebuilds the whole recording from it;
- ``"incomplete"``: not closed cleanly and no journal: what was flushed before the stop is readable, the rest
  is lost.

A file that cannot be read as a session at all raises :class:`~davis_rig.errors.SessionError` (its message says
when a journal can rebuild it).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from davis_rig.errors import SessionError
from davis_rig.session import schema
from davis_rig.session.h5file import frame_hw_from_device_info
from davis_rig.session.journal import journal_in_use, journal_path
from davis_rig.session.labels import labels_crop_origin
from davis_rig.session.reader import SessionReader
from davis_rig.types import GEN1_CLASSES

__all__ = ["PEAK_WINDOW_MS", "LabelsInfo", "SessionInfo", "describe_session", "dvs_hw_from_device_info",
           "sensor_layout"]

#: Window of the peak event rate, ms: the most events in one window of this many milliseconds of ``ms_to_idx``.
PEAK_WINDOW_MS = 100

#: Decoder counters of data the stream carried but the decoder could not use (``stats["camera"]["decoder"]``).
DECODER_LOSS_KEYS = ("odd_bytes_dropped", "unknown_words", "dvs_out_of_range", "aps_frames_dropped",
                     "aps_samples_dropped", "imu_samples_dropped")


@dataclass(frozen=True)
class LabelsInfo:
    """The ``/labels`` group of a session.

    Attributes:
        boxes: number of boxes.
        label_times: distinct box timestamps (labelled instants).
        boxes_per_class: class name (Gen1 names, else ``class_<id>``) -> boxes.
        t_first_us, t_last_us: first / last box time, device µs (``None`` without boxes).
        provenance: the ``/labels`` attributes (labeler, labeler_version, created_utc, source, ...), with JSON
            text values (``settings``) decoded.
    """

    boxes: int
    label_times: int
    boxes_per_class: dict
    t_first_us: int | None
    t_last_us: int | None
    provenance: dict


@dataclass(frozen=True)
class SessionInfo:
    """Summary of one session.h5 (see :func:`describe_session`); times are device µs.

    Attributes:
        path, file_size_bytes, format_version, toolkit_version: the file.
        integrity: ``"complete"``, ``"recording"``, ``"needs recovery"`` or ``"incomplete"`` (module docstring);
            integrity_detail: one sentence on what that means for this file and what to run.
        stopped_by: why the recording ended (``stats["stopped_by"]``), ``None`` when not recorded.
        recording_start_utc: wall-clock start (ISO 8601).
        t_first_event_us, t_last_event_us: first / last event time (``None`` without events);
            duration_us: their difference (0 with fewer than two events).
        events: event count; event_rate_mean_hz: events / duration; event_rate_peak_hz: the most events in one
            :data:`PEAK_WINDOW_MS` window of the millisecond grid, per second.
        frames: APS frames; frame_rate_hz: (frames − 1) / span of their exposure starts;
            exposure_median_us: median exposure (``None`` without frames).
        imu_samples, imu_rate_hz: IMU samples and their rate.
        specials: special events; specials_by_type: libcaer type name (or id) -> count.
        dropped_transfers, dropped_bytes: USB transfers / bytes the camera dropped (``None`` when the file does
            not say, e.g. an import); decoder_losses: the decoder's loss counters that are not zero.
        events_dropped_non_monotonic: events the writer dropped because they went back in time.
        timestamp_resets: device timestamp resets during the recording.
        serial: the camera's serial number; sensor_hw: (height, width) of the pixel array, px.
        device_info, config, biases: the stored dicts, as recorded.
        crop_origin_xy: the RVT crop's top-left on the sensor stored with the labels, px (``None``: not stored;
            the commands then use the centred crop).
        labels: :class:`LabelsInfo`, or ``None`` when the session has no ``/labels``.
    """

    path: str
    file_size_bytes: int
    format_version: int
    toolkit_version: str
    integrity: str
    integrity_detail: str
    stopped_by: str | None
    recording_start_utc: str
    t_first_event_us: int | None
    t_last_event_us: int | None
    duration_us: int
    events: int
    event_rate_mean_hz: float
    event_rate_peak_hz: float
    frames: int
    frame_rate_hz: float
    exposure_median_us: float | None
    imu_samples: int
    imu_rate_hz: float
    specials: int
    specials_by_type: dict
    dropped_transfers: int | None
    dropped_bytes: int | None
    decoder_losses: dict
    events_dropped_non_monotonic: int
    timestamp_resets: int
    serial: str
    sensor_hw: tuple
    device_info: dict
    config: dict
    biases: dict
    crop_origin_xy: tuple | None
    labels: LabelsInfo | None

    def to_json(self) -> dict:
        """A JSON-ready dict of every field (nested dataclasses as dicts, tuples as lists)."""
        return json.loads(json.dumps(asdict(self)))


def _rate_hz(count: int, span_us: int) -> float:
    """``count / span``, per second; 0 for an empty span."""
    return count * 1e6 / span_us if span_us > 0 else 0.0


def _event_bounds(reader: SessionReader) -> tuple[int | None, int | None]:
    """First and last event time, device µs, reading only the two milliseconds that hold them."""
    n = reader.num_events
    if n == 0:
        return None, None
    ms = reader.ms_to_idx
    first_ms = int(np.searchsorted(ms, 0, side="right")) - 1
    last_ms = int(np.searchsorted(ms, n - 1, side="right")) - 1
    t0 = reader.t_offset_us

    def window(m: int) -> np.ndarray:
        return reader.events_between(t0 + 1000 * m, t0 + 1000 * (m + 1))["t"]

    return int(window(first_ms)[0]), int(window(last_ms)[-1])


def _peak_rate_hz(reader: SessionReader) -> float:
    """The most events in one :data:`PEAK_WINDOW_MS` window of the ``ms_to_idx`` grid, per second."""
    ms = reader.ms_to_idx
    if reader.num_events == 0 or len(ms) == 0:
        return 0.0
    bounds = np.append(ms[::PEAK_WINDOW_MS], reader.num_events)
    return float(np.diff(bounds).max()) * 1000.0 / PEAK_WINDOW_MS


def _special_names(types: np.ndarray) -> dict:
    """Count special events per libcaer type name (the id when the protocol package does not know it)."""
    from davis_rig.protocol.words import SpecialType

    ids, counts = np.unique(types, return_counts=True)
    known = {int(t) for t in SpecialType}
    return {(SpecialType(int(i)).name if int(i) in known else str(int(i))): int(c) for i, c in zip(ids, counts)}


def _labels_info(reader: SessionReader) -> LabelsInfo | None:
    labels = reader.labels()
    if labels is None:
        return None
    provenance = {}
    for key, value in reader.labels_attrs().items():
        if isinstance(value, str) and value[:1] in "[{":
            try:
                value = json.loads(value)
            except json.JSONDecodeError:
                pass  # text that only looks like JSON: keep it as stored
        provenance[key] = value
    classes, counts = np.unique(labels["class_id"], return_counts=True)
    t = labels["t"].astype(np.int64)
    return LabelsInfo(
        boxes=int(len(labels)), label_times=int(len(np.unique(t))),
        boxes_per_class={GEN1_CLASSES.get(int(c), f"class_{int(c)}"): int(n) for c, n in zip(classes, counts)},
        t_first_us=int(t.min()) if len(t) else None, t_last_us=int(t.max()) if len(t) else None,
        provenance=provenance)


def _integrity(path: Path, complete: bool, stopped_by: str | None) -> tuple[str, str]:
    journal = journal_path(path)
    if journal_in_use(journal):
        return "recording", (f"being recorded right now ({journal.name} is held by the recording): the file holds "
                             "what was flushed so far")
    if journal.exists():
        state = "the file is readable as it is" if complete else "the file holds what was flushed before the stop"
        return ("needs recovery", f"{journal.name} exists next to it ({state}): run `davis-record --recover "
                                  f"{path}` to rebuild the whole recording from it")
    if complete:
        return "complete", "closed cleanly" + (f" (stopped by: {stopped_by})" if stopped_by else "")
    return ("incomplete", "not closed cleanly and there is no journal to rebuild it from: what was flushed before "
                          "the stop is readable, the rest is lost")


def describe_session(path: str | os.PathLike) -> SessionInfo:
    """Summarise a session.h5 without reading its events (see the module docstring).

    Args:
        path: the session file.

    Returns:
        A :class:`SessionInfo`.

    Raises:
        SessionError: the file is missing, empty, truncated, not a session, or inconsistent (the message says
            when ``davis-record --recover`` can rebuild it).
    """
    path = Path(path)
    with SessionReader(path) as reader:
        stats = reader.stats
        losses = _losses(path, stats)
        stopped_by = stats.get("stopped_by")
        integrity, detail = _integrity(path, reader.complete, stopped_by)

        t_first, t_last = _event_bounds(reader)
        duration_us = (t_last - t_first) if t_first is not None else 0
        frames = reader.frames
        starts = frames.times_us("t_start_exposure_us")
        exposures = frames.times_us("t_end_exposure_us") - starts
        imu = reader.imu()
        imu_t = imu["t"].astype(np.int64) if imu is not None else np.zeros(0, np.int64)
        specials = reader.specials()
        device_info = reader.device_info
        labels = _labels_info(reader)
        return SessionInfo(
            path=str(path), file_size_bytes=path.stat().st_size, format_version=reader.format_version,
            toolkit_version=_toolkit_version(path),
            integrity=integrity, integrity_detail=detail, stopped_by=stopped_by,
            recording_start_utc=reader.recording_start_utc,
            t_first_event_us=t_first, t_last_event_us=t_last, duration_us=int(duration_us),
            events=int(reader.num_events), event_rate_mean_hz=_rate_hz(reader.num_events, duration_us),
            event_rate_peak_hz=_peak_rate_hz(reader),
            frames=len(frames),
            frame_rate_hz=_rate_hz(len(starts) - 1, int(starts[-1] - starts[0])) if len(starts) > 1 else 0.0,
            exposure_median_us=float(np.median(exposures)) if len(exposures) else None,
            imu_samples=int(len(imu_t)),
            imu_rate_hz=_rate_hz(len(imu_t) - 1, int(imu_t[-1] - imu_t[0])) if len(imu_t) > 1 else 0.0,
            specials=int(len(specials)), specials_by_type=_special_names(specials["type"]),
            **losses,
            serial=str(device_info.get("serial", "")),
            sensor_hw=dvs_hw_from_device_info(device_info),
            device_info=device_info, config=reader.config,
            biases=reader.biases,
            crop_origin_xy=labels_crop_origin(reader.labels_attrs(), path) if labels is not None else None,
            labels=labels)


def _losses(path: Path, stats: dict) -> dict:
    """The loss counters of the ``stats`` attribute, as :class:`SessionInfo` fields.

    Raises:
        SessionError: a counter is not a number (a damaged or hand-edited attribute).
    """
    camera = stats.get("camera") if isinstance(stats.get("camera"), dict) else {}
    decoder = camera.get("decoder") or stats.get("decoder") or {}
    writer = stats.get("writer") if isinstance(stats.get("writer"), dict) else {}
    try:
        return {
            "dropped_transfers": _optional_int(camera.get("dropped_transfers")),
            "dropped_bytes": _optional_int(camera.get("dropped_bytes")),
            "decoder_losses": {key: int(decoder[key]) for key in DECODER_LOSS_KEYS if decoder.get(key)},
            "events_dropped_non_monotonic": int(writer.get("events_dropped_non_monotonic", 0) or 0),
            "timestamp_resets": int(writer.get("timestamp_resets", 0) or 0),
        }
    except (AttributeError, TypeError, ValueError) as exc:
        raise SessionError(f"{path}: unreadable stats attribute ({type(exc).__name__}: {exc})") from exc


def _optional_int(value) -> int | None:
    return None if value is None else int(value)


def _toolkit_version(path: Path) -> str:
    """The davis_rig version that wrote the file (root attribute; ``""`` when absent)."""
    import h5py

    with h5py.File(path, "r", locking=False) as f:
        return str(f.attrs.get(schema.ATTR_TOOLKIT_VERSION, ""))


def dvs_hw_from_device_info(info: dict) -> tuple[int, int]:
    """The event pixel array (height, width) in px from a device-info dict's ``layout``, else its APS size."""
    layout = (info or {}).get("layout") or {}
    height = layout.get("dvs_height") or layout.get("dvs_size_rows")
    width = layout.get("dvs_width") or layout.get("dvs_size_columns")
    if height and width:
        return int(height), int(width)
    return frame_hw_from_device_info(info)


def sensor_layout(width: int, height: int) -> dict:
    """A device-info ``layout`` for a sensor of ``width`` x ``height`` px (DVS and APS), as imports store it."""
    width, height = int(width), int(height)
    return {"dvs_size_columns": width, "dvs_size_rows": height, "dvs_width": width, "dvs_height": height,
            "aps_size_columns": width, "aps_size_rows": height, "aps_width": width, "aps_height": height}
