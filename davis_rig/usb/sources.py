"""Data sources for the virtual DAVIS346's bulk endpoint, and fault injection described as data.

A source hands out bulk transfers (``bytes``), each with a release time in µs after the device started
streaming (0 = immediately). The virtual device serves one transfer per bulk read once its release time has
passed on the device clock, which gives optional real-time pacing.

- :class:`TransferListSource`: a fixed list of transfers (e.g. a test vector's ``transfers_hex``).
- :class:`ReplaySource`: transfers from a replay file (:mod:`davis_rig.usb.replay`), paced by host time or not.
- :class:`EncodedSource`: events and APS frames turned into the DAVIS346 word stream by
  :class:`davis_rig.protocol.encoder.StreamEncoder`, cut into transfers per pacing slice.
"""

from __future__ import annotations

import threading
import warnings
import weakref
from collections import deque
from dataclasses import dataclass
from os import PathLike
from typing import Iterable, Sequence

import numpy as np

from davis_rig.errors import ConfigError, FormatError, ProtocolError, ShapeError
from davis_rig.types import EVENT_DTYPE

#: Default size of one device transfer, bytes (libcaer's buffer size).
TRANSFER_BYTES = 8192


@dataclass(frozen=True)
class Faults:
    """Faults the virtual device injects, as data (all off by default).

    Attributes:
        disconnect_after_transfers: after serving this many bulk transfers the device vanishes: every later call
            fails like libusb's ``LIBUSB_ERROR_NO_DEVICE`` (ENODEV) and enumeration no longer lists it.
        stall_every: every n-th bulk read on 0x82 stalls (EPIPE, no data lost); the endpoint stays halted
            (further reads fail with EPIPE) until the host clears the halt.
        timeout_every: every n-th bulk read on 0x82 times out without data (no data lost).
        short_transfer_bytes: transfers are delivered in pieces of at most this many bytes.
        odd_length: every n-th transfer gets one extra trailing byte (0xA5) — the decoder must drop it.
        garbage_rate: probability with which each served byte is replaced by a random byte.
        seed: seed of the garbage generator.
        open_errno: ``open_device`` fails with this errno (e.g. ``errno.EACCES`` = missing udev rule).
        claim_errno: ``claim_interface`` fails with this errno (e.g. ``errno.EBUSY`` = another process).

    Raises:
        ConfigError: a value out of its range (its ``field`` names the attribute).
    """

    disconnect_after_transfers: int | None = None
    stall_every: int | None = None
    timeout_every: int | None = None
    short_transfer_bytes: int | None = None
    odd_length: int | None = None
    garbage_rate: float = 0.0
    seed: int = 0
    open_errno: int | None = None
    claim_errno: int | None = None

    def __post_init__(self) -> None:
        for name in ("disconnect_after_transfers", "stall_every", "timeout_every", "short_transfer_bytes", "odd_length"):
            value = getattr(self, name)
            if value is not None and int(value) < 1:
                raise ConfigError(name, f"must be >= 1 (or None), got {value}")
        if not 0.0 <= self.garbage_rate <= 1.0:
            raise ConfigError("garbage_rate", f"must be in [0, 1], got {self.garbage_rate}")


class DataSource:
    """Base class: a thread-safe FIFO of ``(release_us, transfer)`` pairs.

    Subclasses fill the queue with :meth:`_push`. ``release_us`` is the device time, µs after streaming
    started, before which a transfer must not be served (0 for unpaced sources).
    """

    def __init__(self) -> None:
        self._queue: deque[tuple[float, bytes]] = deque()
        self._lock = threading.Lock()

    def _push(self, release_us: float, data: bytes) -> None:
        with self._lock:
            self._queue.append((float(release_us), bytes(data)))

    def peek_release_us(self) -> float | None:
        """Release time of the next transfer, µs after streaming start, or ``None`` when exhausted."""
        with self._lock:
            return self._queue[0][0] if self._queue else None

    def pop(self) -> bytes:
        """Remove and return the next transfer.

        Raises:
            IndexError: the source is exhausted.
        """
        with self._lock:
            return self._queue.popleft()[1]

    def __len__(self) -> int:
        with self._lock:
            return len(self._queue)


class TransferListSource(DataSource):
    """Serve a fixed list of transfers, unpaced, exactly as given (odd lengths included).

    Args:
        transfers: the transfers, in order.
    """

    def __init__(self, transfers: Iterable[bytes | bytearray]):
        super().__init__()
        for data in transfers:
            self._push(0.0, bytes(data))

    @classmethod
    def from_hex(cls, transfers_hex: Sequence[str]) -> "TransferListSource":
        """Build from hex strings (the test vectors' ``transfers_hex``)."""
        return cls(bytes.fromhex(h) for h in transfers_hex)


class ReplaySource(DataSource):
    """Serve the transfers of a replay file, each read from the file when it is served.

    Memory holds an index of the records (24 bytes each), not their payloads: a replay longer than the memory
    can be served.

    Args:
        path: replay file written by :class:`~davis_rig.usb.replay.ReplayWriter`.
        paced: release each transfer at its recorded host time relative to the first record
            (:func:`~davis_rig.usb.replay.pacing_us`: a damaged host time, going back or jumping over
            ``MAX_PACING_STEP_NS``, is paced as no pause, with one ``RuntimeWarning``).

    Attributes:
        header: the file's :class:`~davis_rig.usb.replay.ReplayHeader` (device read-outs for the virtual device).
        truncated: whether the file's last record was incomplete.
        bad_host_times: pacing steps taken as 0 because of damaged host times (0 when not paced).
    """

    def __init__(self, path: str | PathLike, *, paced: bool = False):
        super().__init__()
        from davis_rig.usb.replay import MAX_PACING_STEP_NS, ReplayReader, pacing_us

        with ReplayReader(path) as reader:
            self.header = reader.header
            host_times, self._offsets, self._lengths = reader.index()
            self.truncated = reader.truncated
        self._releases, self.bad_host_times = pacing_us(host_times) if paced else (np.zeros(len(host_times)), 0)
        self._path, self._next = path, 0
        self._file = open(path, "rb", buffering=0)  # seek + read under the lock: portable (os.pread is POSIX-only)
        weakref.finalize(self, self._file.close)
        if self.bad_host_times:
            warnings.warn(
                f"{path}: {self.bad_host_times} replay records have a host time that goes back or jumps more than "
                f"{MAX_PACING_STEP_NS / 1e9:g} s (damaged); they are released right after the previous record",
                RuntimeWarning,
                stacklevel=2,
            )

    def peek_release_us(self) -> float | None:
        """Release time of the next transfer, µs after streaming start, or ``None`` when exhausted."""
        with self._lock:
            return float(self._releases[self._next]) if self._next < len(self._releases) else None

    def pop(self) -> bytes:
        """Read and return the next transfer.

        Raises:
            IndexError: the source is exhausted.
            FormatError: the file got shorter since it was opened.
        """
        with self._lock:
            k = self._next
            if k >= len(self._offsets):
                raise IndexError("pop from an exhausted replay source")
            self._file.seek(int(self._offsets[k]))
            data = self._file.read(int(self._lengths[k]))
            if len(data) != self._lengths[k]:
                raise FormatError(f"{self._path}: record {k}: {len(data)} of {self._lengths[k]} bytes left (the file "
                                  "was cut while being replayed)")
            self._next = k + 1
            return data

    def __len__(self) -> int:
        with self._lock:
            return len(self._offsets) - self._next


def _slice_edges(t_first: int, t_last: int, slice_us: int, frame_spans: np.ndarray) -> np.ndarray:
    """Slice boundaries every ``slice_us`` from ``t_first``, dropping any that fall inside a frame (SOF, EOF]."""
    edges = np.arange(t_first + slice_us, t_last + slice_us, slice_us, dtype=np.int64)
    if edges.size and frame_spans.size:
        inside = np.zeros(edges.size, dtype=bool)
        lo = np.searchsorted(edges, frame_spans[:, 0], side="right")  # first edge > SOF
        hi = np.searchsorted(edges, frame_spans[:, 1], side="right")  # first edge > EOF
        for a, b in zip(lo.tolist(), hi.tolist()):  # one iteration per frame, not per event
            inside[a:b] = True
        edges = edges[~inside]
    return edges


class EncodedSource(DataSource):
    """Serve events and APS frames encoded into the exact word stream a DAVIS346 sends.

    The scene is cut into time slices of ``slice_us`` (never inside an APS frame), each slice is encoded with
    one :class:`~davis_rig.protocol.encoder.StreamEncoder` (state carried across slices) and sent as one or more
    transfers of at most ``transfer_bytes`` — like the camera, which ends a transfer after its early-packet
    delay (1 ms by default) or when the buffer is full. A slice is released when the device clock reaches its
    end (``paced=True``) or immediately.

    Args:
        events: structured array with :data:`~davis_rig.types.EVENT_DTYPE`, time-sorted, [N].
        frames: full-sensor :class:`~davis_rig.protocol.frames.ApsFrame` objects, sorted by start of frame.
        layout: the sensor layout the encoder and decoder share.
        slice_us: pacing/transfer slice, µs (default 1000 = the camera's 1 ms early-packet delay).
        transfer_bytes: maximum transfer size, bytes.
        paced: release slices in device real time.

    Raises:
        ShapeError: ``events`` has the wrong dtype or shape.
        ProtocolError: events are not time-sorted or ``slice_us``/``transfer_bytes`` < 1.
    """

    def __init__(
        self,
        events: np.ndarray,
        frames: Sequence = (),
        *,
        layout,
        slice_us: int = 1000,
        transfer_bytes: int = TRANSFER_BYTES,
        paced: bool = False,
    ):
        super().__init__()
        from davis_rig.protocol.encoder import StreamEncoder

        events = np.asarray(events)
        if events.dtype != EVENT_DTYPE or events.ndim != 1:
            raise ShapeError(f"events: expected 1-D array with EVENT_DTYPE, got dtype {events.dtype} shape {events.shape}")
        if slice_us < 1 or transfer_bytes < 2:
            raise ProtocolError(f"slice_us must be >= 1 and transfer_bytes >= 2, got {slice_us}, {transfer_bytes}")
        t = events["t"]
        if t.size > 1 and np.any(np.diff(t) < 0):
            raise ProtocolError("events must be sorted by time")
        frames = list(frames)
        spans = np.array(
            [[f.t_start_of_frame_us, f.t_end_of_frame_us] for f in frames], dtype=np.int64
        ).reshape(-1, 2)
        times = [int(t[0]), int(t[-1])] if t.size else []
        if spans.size:
            times += [int(spans.min()), int(spans.max())]
        self.total_bytes = 0
        self.transfers = 0
        if not times:
            return
        t_first, t_last = min(times), max(times)
        edges = _slice_edges(t_first, t_last, int(slice_us), spans)
        bounds = np.concatenate([edges[edges <= t_last], [t_last + 1]]).astype(np.int64)
        # events [lo, hi) of slice k are those with t < bounds[k] (and >= bounds[k-1])
        ev_idx = np.searchsorted(t, bounds, side="left")
        fr_slice = np.searchsorted(bounds, spans[:, 1], side="right") if spans.size else np.zeros(0, dtype=np.int64)
        encoder = StreamEncoder(layout)
        start = 0
        for k, end in enumerate(ev_idx.tolist()):
            slice_frames = [frames[i] for i in np.flatnonzero(fr_slice == k).tolist()]
            if end == start and not slice_frames:
                continue
            data = encoder.encode(events[start:end], slice_frames)
            start = end
            release = float(bounds[k] - t_first) if paced else 0.0
            for off in range(0, len(data), transfer_bytes):
                self._push(release, data[off : off + transfer_bytes])
                self.transfers += 1
            self.total_bytes += len(data)
