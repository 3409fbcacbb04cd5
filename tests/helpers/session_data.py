"""Shared synthetic data for the session and cli tests: events, frames and chunks like the decoder emits."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from davis_rig.protocol.frames import ApsFrame
from davis_rig.types import DAVIS346_HW, make_events

SPECIAL_DTYPE = np.dtype([("t", "<i8"), ("type", "u1")])


@dataclass
class Chunk:
    """Stand-in for protocol.decoder.DecodedChunk (same field names)."""

    events: np.ndarray
    frames: list = field(default_factory=list)
    specials: np.ndarray = field(default_factory=lambda: np.zeros(0, SPECIAL_DTYPE))
    imu: np.ndarray | None = None


def random_events(rng: np.random.Generator, n: int, t0_us: int = 0, span_us: int = 1_000_000) -> np.ndarray:
    """Time-sorted random events (ties included) over [t0_us, t0_us + span_us)."""
    t = np.sort(rng.integers(t0_us, t0_us + span_us, n))
    height, width = DAVIS346_HW
    return make_events(t, rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n))


def random_frame(rng: np.random.Generator, t_us: int, roi=None) -> ApsFrame:
    """A random APS frame (10-bit values << 6) starting at t_us; roi = (x, y, w, h) or full sensor."""
    height, width = DAVIS346_HW
    x0, y0, w, h = roi if roi is not None else (0, 0, width, height)
    pixels = (rng.integers(0, 1024, (h, w)) << 6).astype(np.uint16)
    return ApsFrame(pixels, x0, y0, t_us, t_us + 10, t_us + 4010, t_us + 4100)


def split_chunks(events: np.ndarray, sizes) -> list[np.ndarray]:
    """Split events at the given cumulative chunk sizes (copies)."""
    bounds = np.cumsum(sizes)
    return [part.copy() for part in np.split(events, bounds[bounds < len(events)])]


def synth_stream(events: np.ndarray) -> bytes:
    """The DAVIS346 word stream of ``events`` (wrap, timestamp, Y, X words per event), for decoder-level tests.

    Independent of protocol.encoder on purpose (a second, minimal writer of the same wire format).
    """
    from davis_rig.protocol import words as w

    t = events["t"].astype(np.int64)
    high = t >> 15
    wraps = np.diff(np.concatenate([[0], high]))
    if np.any(wraps < 0) or np.any(wraps > 4095):
        raise ValueError("synth_stream: timestamps must be non-decreasing with gaps < 4095 * 32768 µs")
    out = np.zeros((len(t), 4), dtype=np.int64)
    out[:, 0] = (7 << 12) | wraps
    out[:, 1] = 0x8000 | (t & 0x7FFF)
    out[:, 2] = (1 << 12) | events["y"]
    out[:, 3] = ((2 + events["p"].astype(np.int64)) << 12) | events["x"]
    keep = np.ones_like(out, dtype=bool)
    keep[:, 0] = wraps > 0
    return w.words_to_bytes(out[keep])


class FakeCamera:
    """A minimal stand-in with the Davis346 recording API, fed by raw transfers through the real decoder.

    Used by the session tests so they do not depend on the USB layer; the end-to-end tests use the real
    Davis346 on the virtual backend.

    Args:
        transfers: raw transfers (bytes) served in order, one per chunk.
        disconnect_after: raise DeviceDisconnectedError after serving this many transfers.
        delay_s: sleep per transfer (to make recordings last in wall-clock time).
        start_error: raised by ``start()`` (a camera that fails to start).
    """

    #: What ``send_default_config`` sets, µs (the Davis346 defaults).
    DEFAULT_EXPOSURE_US = 4000
    DEFAULT_FRAME_INTERVAL_US = 40000

    def __init__(self, transfers, disconnect_after=None, delay_s=0.0, start_error=None):
        from davis_rig.protocol.decoder import StreamDecoder
        from davis_rig.protocol.layout import SensorLayout

        self.layout = SensorLayout.davis346()
        self.info = {"serial": "FAKE0001", "firmware_version": 0, "logic_version": 18, "chip_id": 5,
                     "layout": self.layout.to_dict()}
        self.biases = {"PrBp": 1}
        self.transfers = list(transfers)
        self.disconnect_after = disconnect_after
        self.delay_s = delay_s
        self.start_error = start_error
        self.exposure_us = None
        self.frame_interval_us = None
        self.decoder = StreamDecoder(self.layout)
        self.listeners = []
        self.calls = []
        self.served = 0
        self.running = False
        self._pending = iter(())

    def send_default_config(self):
        self.calls.append("send_default_config")
        self.exposure_us = self.DEFAULT_EXPOSURE_US
        self.frame_interval_us = self.DEFAULT_FRAME_INTERVAL_US

    def set_exposure(self, us):
        self.calls.append(("set_exposure", us))
        self.exposure_us = us

    def set_frame_interval(self, us):
        self.calls.append(("set_frame_interval", us))
        self.frame_interval_us = us

    def add_raw_listener(self, listener):
        self.listeners.append(listener)

    def remove_raw_listener(self, listener):
        if listener in self.listeners:
            self.listeners.remove(listener)

    def start(self):
        self.calls.append("start")
        if self.start_error is not None:
            raise self.start_error
        self.running = True
        self._pending = iter(self.transfers)

    def stop(self):
        self.calls.append("stop")
        self.running = False

    @property
    def stats(self):
        return {"transfers": self.served, "dropped_transfers": 0, "decoder": self.decoder.stats.as_dict()}

    def read(self, timeout_s=None):
        """Next decoded transfer; None (and running=False) once the transfers are exhausted, like a stopped camera."""
        import time

        from davis_rig.errors import DeviceDisconnectedError

        if self.disconnect_after is not None and self.served >= self.disconnect_after:
            self.running = False
            raise DeviceDisconnectedError("fake camera unplugged")
        data = next(self._pending, None) if self.running else None
        if data is None:
            self.running = False
            return None
        if self.delay_s:
            time.sleep(self.delay_s)
        for listener in self.listeners:
            listener(data)
        self.served += 1
        return self.decoder.feed(data)


def cut(data: bytes, size: int = 8192) -> list[bytes]:
    """Cut a byte stream into transfers of ``size`` bytes."""
    return [data[i : i + size] for i in range(0, len(data), size)]
