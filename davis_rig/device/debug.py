"""FX3 debug endpoint (0x81): firmware error reports (PROTOCOL.md §2, libcaer ``davis.c`` debug-transfer callback).

A message of at least 7 bytes whose first byte is 0x00 is an error report: byte 1 = error code, bytes 2-5 = a
32-bit time value (libcaer reads it in host byte order, i.e. little-endian on x86/ARM hosts), bytes 6… = text.
Anything else is kept as an unknown message.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections import deque
from dataclasses import dataclass
from typing import Callable

_log = logging.getLogger("davis_rig.device")

#: How many debug messages a :class:`DebugReader` keeps.
MAX_DEBUG_MESSAGES = 1000


@dataclass(frozen=True)
class DebugMessage:
    """One message from the FX3 debug endpoint.

    Attributes:
        raw: the bytes as received.
        is_error: True for an error report (length ≥ 7, first byte 0x00).
        error_code: firmware error code (byte 1) for error reports, else ``None``.
        time_value: the 32-bit time field (bytes 2-5, little-endian) for error reports, else ``None``.
        text: the message text (bytes 6…, NUL-terminated, decoded as ASCII with replacement), else ``""``.
    """

    raw: bytes
    is_error: bool
    error_code: int | None = None
    time_value: int | None = None
    text: str = ""


def parse_debug_message(data: bytes | bytearray | memoryview) -> DebugMessage:
    """Parse one debug-endpoint transfer.

    Args:
        data: the transfer's bytes.

    Returns:
        The parsed message (never raises for odd input: unknown formats are kept raw).
    """
    raw = bytes(data)
    if len(raw) >= 7 and raw[0] == 0x00:
        (time_value,) = struct.unpack_from("<I", raw, 2)
        text = raw[6:].split(b"\x00", 1)[0].decode("ascii", errors="replace")
        return DebugMessage(raw=raw, is_error=True, error_code=raw[1], time_value=time_value, text=text)
    return DebugMessage(raw=raw, is_error=False)


class DebugReader:
    """A thread polling the debug endpoint; keeps the last :data:`MAX_DEBUG_MESSAGES` messages and logs them.

    Args:
        read: ``read(timeout_ms) -> bytes | None`` (e.g. ``UsbTransport.read_debug``).
        timeout_ms: per-read timeout, ms (bounds how long :meth:`stop` waits).

    The thread ends quietly on any USB error (the data path reports disconnects).
    """

    def __init__(self, read: Callable[[int], bytes | None], timeout_ms: int = 100):
        self._read = read
        self.timeout_ms = int(timeout_ms)
        self._messages: deque[DebugMessage] = deque(maxlen=MAX_DEBUG_MESSAGES)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "DebugReader":
        """Start polling."""
        self._thread = threading.Thread(target=self._run, name="davis-usb-debug", daemon=True)
        self._thread.start()
        return self

    def stop(self, join_timeout_s: float = 5.0) -> None:
        """Stop polling and wait for the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(join_timeout_s)

    @property
    def messages(self) -> list[DebugMessage]:
        """Messages received so far (oldest first, at most :data:`MAX_DEBUG_MESSAGES`)."""
        with self._lock:
            return list(self._messages)

    def _run(self) -> None:
        from davis_rig.errors import DavisRigError

        while not self._stop.is_set():
            try:
                data = self._read(self.timeout_ms)
            except DavisRigError:
                return
            if not data:
                continue
            message = parse_debug_message(data)
            with self._lock:
                self._messages.append(message)
            if message.is_error:
                _log.warning("DAVIS firmware error %d at %d: %s", message.error_code, message.time_value, message.text)
            else:
                _log.info("DAVIS debug message of unknown format: %s", message.raw.hex())
