"""Test helper: read a ``Davis346`` over a virtual DAVIS346 until everything the device served is decoded."""

from __future__ import annotations

import time


def read_until_drained(cam, device, raw: list[bytes], limit_s: float = 20.0) -> list:
    """Read chunks until the device served everything and the raw listener saw every served byte.

    The end is known from the virtual device's counters, not guessed from idle reads.

    Args:
        cam: a started ``Davis346`` with ``raw.append`` registered as a raw listener.
        device: the ``VirtualDavis346`` behind ``cam``.
        raw: the transfers (bytes) the raw listener has appended so far, and goes on appending.
        limit_s: give up after this long, s.

    Returns:
        The ``DecodedChunk`` objects in read order.

    Raises:
        AssertionError: data still missing after ``limit_s``.
    """
    chunks = []
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        chunk = cam.read(0.02)
        if chunk is not None:
            chunks.append(chunk)
        elif device.drained and sum(len(r) for r in raw) == device.bytes_served:
            return chunks
    raise AssertionError(f"data still missing after {limit_s} s")
