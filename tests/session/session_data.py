"""Shared synthetic data for the session and cli tests: events, frames and chunks like the decoder emits."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from davis_rig.session.reader import StoredFrame
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


def random_frame(rng: np.random.Generator, t_us: int, roi=None) -> StoredFrame:
    """A random APS frame (10-bit values << 6) starting at t_us; roi = (x, y, w, h) or full sensor."""
    height, width = DAVIS346_HW
    x0, y0, w, h = roi if roi is not None else (0, 0, width, height)
    pixels = (rng.integers(0, 1024, (h, w)) << 6).astype(np.uint16)
    return StoredFrame(pixels, x0, y0, t_us, t_us + 10, t_us + 4010, t_us + 4100)


def split_chunks(events: np.ndarray, sizes) -> list[np.ndarray]:
    """Split events at the given cumulative chunk sizes (copies)."""
    bounds = np.cumsum(sizes)
    return [part.copy() for part in np.split(events, bounds[bounds < len(events)])]
