"""What a ``.davisreplay`` file holds: the camera it came from, its transfers, and what they decode to.

A replay is not a session: it stores the raw USB transfers of a recording (``firmware_notes/replay_format.md``)
so the virtual DAVIS346 can serve them again. :func:`describe_replay` decodes every transfer once, one at a
time (memory bounded by one transfer's output), to count events, frames, special events and IMU samples.
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from davis_rig.errors import FormatError, ProtocolError
from davis_rig.usb.replay import MAX_PACING_STEP_NS, ReplayReader

__all__ = ["ReplayInfo", "describe_replay"]


@dataclass(frozen=True)
class ReplayInfo:
    """Summary of one replay file; event times are device µs.

    Attributes:
        path, file_size_bytes: the file.
        serial, firmware_version, logic_version: the camera it was recorded from.
        sensor_hw: (height, width) of the DVS pixel array, px.
        transfers, transfer_bytes: complete records and their payload bytes.
        truncated: the last record was cut short (recording killed, disk full) and is ignored.
        host_duration_us: host clock from the first to the last transfer, µs: the sum of the steps between
            transfers, a damaged step (going back, or over ``MAX_PACING_STEP_NS``) counted as 0 — the time a paced
            replay takes (:func:`~davis_rig.usb.replay.pacing_us`).
        events, frames, specials, imu_samples: what the transfers decode to.
        t_first_event_us, t_last_event_us: first / last event time (``None`` without events); duration_us:
            their difference; event_rate_mean_hz: events per second over it.
        decoder_counters: the decoder's counters other than ``words`` that are not zero (data it could not use,
            timestamp resets and wraps, out-of-order timestamps).
        header_extra: the header's free-form keys (tool, started_utc, config writes, ...).
    """

    path: str
    file_size_bytes: int
    serial: str
    firmware_version: int
    logic_version: int
    sensor_hw: tuple
    transfers: int
    transfer_bytes: int
    truncated: bool
    host_duration_us: int
    events: int
    frames: int
    specials: int
    imu_samples: int
    t_first_event_us: int | None
    t_last_event_us: int | None
    duration_us: int
    event_rate_mean_hz: float
    decoder_counters: dict
    header_extra: dict

    def to_json(self) -> dict:
        """A JSON-ready dict of every field."""
        return json.loads(json.dumps(asdict(self), default=str))


def describe_replay(path: str | os.PathLike) -> ReplayInfo:
    """Decode a replay file once and summarise it (see the module docstring).

    Args:
        path: the ``.davisreplay`` file.

    Returns:
        A :class:`ReplayInfo`.

    Raises:
        FormatError: not a replay file, a malformed header, a corrupt record length, or a sensor layout in the
            header the decoder cannot use.
    """
    from davis_rig.protocol.decoder import StreamDecoder
    from davis_rig.protocol.layout import SensorLayout

    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such replay file")
    counts = {"transfers": 0, "bytes": 0, "events": 0, "frames": 0, "specials": 0, "imu": 0}
    t_first = t_last = host_last = None
    host_ns = 0
    with ReplayReader(path) as reader, warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the truncation warning: reported as a field instead
        header = reader.header
        try:
            layout = SensorLayout.from_mapping(header.device_info)
        except ProtocolError as exc:
            raise FormatError(f"{path}: the header's device_info is not a usable sensor layout ({exc})") from exc
        decoder = StreamDecoder(layout)
        for record in reader:
            chunk = decoder.feed(record.data)
            counts["transfers"] += 1
            counts["bytes"] += len(record.data)
            counts["events"] += len(chunk.events)
            counts["frames"] += len(chunk.frames)
            counts["specials"] += len(chunk.specials)
            counts["imu"] += len(chunk.imu)
            if host_last is not None and 0 <= record.host_time_ns - host_last <= MAX_PACING_STEP_NS:
                host_ns += record.host_time_ns - host_last  # a damaged step counts 0, as in pacing_us
            host_last = record.host_time_ns
            if len(chunk.events):
                t = chunk.events["t"]
                t_first = int(t[0]) if t_first is None else t_first
                t_last = int(np.max(t)) if t_last is None else max(t_last, int(np.max(t)))
        truncated = reader.truncated
    duration_us = (t_last - t_first) if t_first is not None else 0
    return ReplayInfo(
        path=str(path), file_size_bytes=path.stat().st_size, serial=header.serial,
        firmware_version=header.firmware_version, logic_version=header.logic_version,
        sensor_hw=(layout.dvs_height, layout.dvs_width), transfers=counts["transfers"],
        transfer_bytes=counts["bytes"], truncated=truncated,
        host_duration_us=host_ns // 1000,
        events=counts["events"], frames=counts["frames"], specials=counts["specials"], imu_samples=counts["imu"],
        t_first_event_us=t_first, t_last_event_us=t_last, duration_us=duration_us,
        event_rate_mean_hz=counts["events"] * 1e6 / duration_us if duration_us > 0 else 0.0,
        decoder_counters={key: value for key, value in decoder.stats.as_dict().items() if value and key != "words"},
        header_extra=dict(header.extra))
