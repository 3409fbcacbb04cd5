"""Replay files: raw USB bulk transfers of a DAVIS camera, with the device read-outs needed to re-serve them.

Format (version 1, all integers little-endian; documented in ``firmware_notes/replay_format.md``)::

    magic       8 bytes   b"DAVISRPL"
    version     u16       1
    header_len  u32       length of the JSON header in bytes
    header      header_len bytes of UTF-8 JSON (an object; see ReplayHeader)
    records     repeated until end of file:
        host_time_ns  u64   host monotonic clock when the transfer completed, ns
        length        u32   payload length, bytes (may be odd: transfers are stored exactly as received)
        payload       length bytes

A file cut short while recording (the last record incomplete) is still readable: the reader stops at the last
complete record and sets :attr:`ReplayReader.truncated`. A header whose ``device_info`` is not a valid sensor
layout (e.g. 0 columns) is a :class:`~davis_rig.errors.FormatError` naming the file. Host times are only used for
pacing (:func:`pacing_us`), which tolerates damaged ones.
"""

from __future__ import annotations

import json
import os
import struct
import time
import warnings
from dataclasses import dataclass, field
from os import PathLike
from typing import Any, BinaryIO, Iterator

import numpy as np

from davis_rig.errors import FormatError, ProtocolError

REPLAY_MAGIC = b"DAVISRPL"
REPLAY_VERSION = 1
_PREAMBLE = struct.Struct("<8sHI")
_RECORD = struct.Struct("<QI")
#: Upper bound on one record's payload, bytes (guards against reading garbage as a length).
MAX_RECORD_BYTES = 64 * 1024 * 1024
#: Longest pause between two records that pacing reproduces, ns. A streaming DAVIS completes a transfer at least
#: every ~33 ms (a wrap word every 32.768 ms, sent after the 1 ms early-packet delay), so a longer step, or one
#: back in time, is a damaged host time.
MAX_PACING_STEP_NS = 1_000_000_000


@dataclass(frozen=True)
class ReplayRecord:
    """One bulk transfer as received.

    Attributes:
        host_time_ns: host monotonic time when the transfer completed, ns.
        data: the transfer's bytes, exactly as received.
    """

    host_time_ns: int
    data: bytes


@dataclass(frozen=True)
class ReplayHeader:
    """What a replay file says about the camera it was recorded from.

    Attributes:
        device_info: raw read-outs named as in the test vectors (``dvs_size_columns``, ``dvs_size_rows``,
            ``dvs_orientation_info``, ``aps_size_columns``, ``aps_size_rows``, ``aps_orientation_info``,
            ``imu_type``, ``imu_orientation_info``, ``chip_id``, ``aps_color_filter``).
        serial: camera serial number.
        firmware_version: bcdDevice low byte.
        logic_version: SYSINFO 0.
        logic_patch: SYSINFO 7.
        clocks: ``{"logic_mhz", "adc_mhz", "usb_mhz", "deviation"}`` (SYSINFO 3-6).
        extra: any other JSON fields (config writes sent, tool version, notes...).
    """

    device_info: dict[str, int]
    serial: str = ""
    firmware_version: int = 0
    logic_version: int = 0
    logic_patch: int = 0
    clocks: dict[str, int] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """JSON-serialisable dict of the header."""
        out = dict(self.extra)
        out.update(
            device_info=dict(self.device_info),
            serial=self.serial,
            firmware_version=self.firmware_version,
            logic_version=self.logic_version,
            logic_patch=self.logic_patch,
            clocks=dict(self.clocks),
        )
        return out

    @classmethod
    def from_json(cls, obj: Any) -> "ReplayHeader":
        """Build from the decoded JSON object.

        Raises:
            FormatError: not an object, ``device_info`` missing, a number that is not an integer, or a
                ``device_info`` that is not a valid sensor layout (all read-outs, sizes 1..4096 px).
        """
        from davis_rig.protocol.layout import SensorLayout

        if not isinstance(obj, dict) or not isinstance(obj.get("device_info"), dict):
            raise FormatError(f"replay header: expected a JSON object with a 'device_info' object, got {obj!r:.200}")
        known = {"device_info", "serial", "firmware_version", "logic_version", "logic_patch", "clocks"}
        try:
            header = cls(
                device_info={str(k): int(v) for k, v in obj["device_info"].items()},
                serial=str(obj.get("serial", "")),
                firmware_version=int(obj.get("firmware_version", 0)),
                logic_version=int(obj.get("logic_version", 0)),
                logic_patch=int(obj.get("logic_patch", 0)),
                clocks={str(k): int(v) for k, v in dict(obj.get("clocks", {})).items()},
                extra={k: v for k, v in obj.items() if k not in known},
            )
            SensorLayout.from_mapping(header.device_info)
        except (TypeError, ValueError, ProtocolError) as exc:
            raise FormatError(f"replay header: {exc}") from exc
        return header


class ReplayWriter:
    """Append raw transfers to a replay file (context manager).

    Args:
        path: file to create (overwritten).
        header: the camera description to store.
        clock_ns: monotonic clock used when ``write`` gets no timestamp (default ``time.monotonic_ns``).
    """

    def __init__(self, path: str | PathLike, header: ReplayHeader, clock_ns: Any = time.monotonic_ns):
        self.path = path
        self.header = header
        self._clock_ns = clock_ns
        self._file: BinaryIO | None = None
        self.records = 0
        self.bytes = 0

    def open(self) -> "ReplayWriter":
        """Create the file and write magic, version and header."""
        payload = json.dumps(self.header.to_json(), sort_keys=True).encode("utf-8")
        self._file = open(self.path, "wb")
        self._file.write(_PREAMBLE.pack(REPLAY_MAGIC, REPLAY_VERSION, len(payload)))
        self._file.write(payload)
        return self

    def write(self, data: bytes | bytearray | memoryview, host_time_ns: int | None = None) -> None:
        """Append one transfer.

        Args:
            data: the transfer's bytes (any length, stored exactly).
            host_time_ns: completion time, ns; ``None`` = now on ``clock_ns``.

        Raises:
            FormatError: the writer is not open.
        """
        if self._file is None:
            raise FormatError(f"replay writer for {self.path}: not open")
        data = bytes(data)
        t_ns = self._clock_ns() if host_time_ns is None else int(host_time_ns)
        self._file.write(_RECORD.pack(t_ns, len(data)))
        self._file.write(data)
        self.records += 1
        self.bytes += len(data)

    def flush(self) -> None:
        """Flush buffered records to the OS."""
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> "ReplayWriter":
        return self.open() if self._file is None else self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class ReplayReader:
    """Read a replay file (context manager); iterate to get :class:`ReplayRecord` objects.

    Args:
        path: replay file.

    Attributes:
        header: the :class:`ReplayHeader`.
        truncated: True once iteration met an incomplete last record.

    Raises:
        FormatError: wrong magic, unsupported version or malformed header (on open).
    """

    def __init__(self, path: str | PathLike):
        self.path = path
        self.header: ReplayHeader | None = None
        self.truncated = False
        self._file: BinaryIO | None = None
        self._data_offset = 0

    def open(self) -> "ReplayReader":
        """Open the file and parse the header.

        Raises:
            FormatError: no such file, or not a replay (the message names the file).
        """
        try:
            f = open(self.path, "rb")
        except FileNotFoundError:
            raise FormatError(f"{self.path}: no such replay file") from None
        try:
            pre = f.read(_PREAMBLE.size)
            if len(pre) < _PREAMBLE.size:
                raise FormatError(f"{self.path}: not a replay file (only {len(pre)} bytes)")
            magic, version, header_len = _PREAMBLE.unpack(pre)
            if magic != REPLAY_MAGIC:
                raise FormatError(f"{self.path}: not a replay file (magic {magic!r}, expected {REPLAY_MAGIC!r})")
            if version != REPLAY_VERSION:
                raise FormatError(f"{self.path}: replay format version {version} not supported, expected {REPLAY_VERSION}")
            raw = f.read(header_len)
            if len(raw) != header_len:
                raise FormatError(f"{self.path}: header truncated ({len(raw)} of {header_len} bytes)")
            try:
                obj = json.loads(raw.decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise FormatError(f"{self.path}: header is not valid UTF-8 JSON ({exc})") from exc
            try:
                self.header = ReplayHeader.from_json(obj)
            except FormatError as exc:
                raise FormatError(f"{self.path}: {exc}") from exc
        except BaseException:
            f.close()
            raise
        self._file = f
        self._data_offset = f.tell()
        self._size = os.fstat(f.fileno()).st_size
        return self

    def __iter__(self) -> Iterator[ReplayRecord]:
        for t_ns, _, _, data in self._walk(read_payload=True):
            yield ReplayRecord(t_ns, data)

    def index(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where the complete records are, without reading their payloads (memory: 24 bytes per record).

        Returns:
            (uint64 [R] host times, ns; int64 [R] payload offsets in the file, bytes; int64 [R] payload lengths,
            bytes), in file order. An incomplete last record is left out as in iteration (warning, ``truncated``).

        Raises:
            FormatError: a record length over :data:`MAX_RECORD_BYTES` (a corrupt file).
        """
        heads = [(t_ns, offset, length) for t_ns, offset, length, _ in self._walk(read_payload=False)]
        table = np.array(heads, dtype=np.uint64).reshape(-1, 3)
        return table[:, 0], table[:, 1].astype(np.int64), table[:, 2].astype(np.int64)

    def _walk(self, read_payload: bool) -> Iterator[tuple[int, int, int, bytes | None]]:
        """``(host_time_ns, payload offset, length, payload or None)`` of each complete record, in file order."""
        if self._file is None:
            self.open()
        assert self._file is not None
        self._file.seek(self._data_offset)
        reader = self._file
        while True:
            head = reader.read(_RECORD.size)
            if not head:
                return
            if len(head) < _RECORD.size:
                self._mark_truncated()
                return
            t_ns, length = _RECORD.unpack(head)
            if length > MAX_RECORD_BYTES:
                raise FormatError(f"{self.path}: record length {length} exceeds {MAX_RECORD_BYTES} bytes (corrupt file)")
            offset = reader.tell()
            if offset + length > self._size:  # cut short: nothing to allocate a buffer for
                self._mark_truncated()
                return
            data = None
            if read_payload:
                data = reader.read(length)
                if len(data) < length:
                    self._mark_truncated()
                    return
            else:
                reader.seek(length, os.SEEK_CUR)
            yield int(t_ns), offset, length, data

    def _mark_truncated(self) -> None:
        self.truncated = True
        warnings.warn(f"{self.path}: last replay record is incomplete and was skipped", RuntimeWarning, stacklevel=4)

    def records(self) -> list[ReplayRecord]:
        """All complete records, in file order."""
        return list(self)

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> "ReplayReader":
        return self.open() if self._file is None else self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def pacing_us(host_times_ns) -> tuple[np.ndarray, int]:
    """Release times of replay records, µs after the first one, from their host times.

    Each record follows the previous one by the difference of their host times; a step that goes back or is
    longer than :data:`MAX_PACING_STEP_NS` (a damaged host time: one flipped bit of a ``u64`` is up to 292 years)
    counts as 0, so one bad record never stalls a paced replay.

    Args:
        host_times_ns: the records' ``host_time_ns`` (0..2**64-1), in file order [R].

    Returns:
        (float64 [R] release times in µs, non-decreasing from 0; number of steps taken as 0).
    """
    t = np.asarray(host_times_ns, dtype=np.uint64).astype(np.float64)  # ns < 2**53 are exact
    if not t.shape[0]:
        return np.zeros(0), 0
    step = np.diff(t)
    bad = (step < 0) | (step > MAX_PACING_STEP_NS)
    step[bad] = 0.0
    return np.concatenate([[0.0], np.cumsum(step) / 1000.0]), int(np.count_nonzero(bad))
