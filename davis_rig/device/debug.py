"""FX3 debug endpoint (0x81): firmware error reports (PROTOCOL.md §2, libcaer ``davis.c`` debug-transfer callback).

A message of at least 7 bytes whose first byte is 0x00 is an error report: byte 1 = error code, bytes 2-5 = a
32-bit time value (libcaer reads it in host byte order, i.e. little-endian on x86/ARM hosts), bytes 6… = text.
Anything else is kept as an unknown message.

:class:`DebugReader` listens from open to close, as libcaer does (4 interrupt transfers of 64 bytes in flight), so
reports the firmware sends outside a run are kept too.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

from davis_rig.errors import DavisRigError
from davis_rig.protocol.config import DEBUG_ENDPOINT
from davis_rig.usb.async_bulk import LIBUSB_TRANSFER_TYPE_INTERRUPT, AsyncTransferApi, BulkTransferRing

_log = logging.getLogger("davis_rig.device")

#: How many debug messages a :class:`DebugReader` keeps.
MAX_DEBUG_MESSAGES = 1000
#: Interrupt transfers kept in flight on 0x81 (libcaer: 4).
DEBUG_TRANSFERS = 4
#: Bytes per debug transfer (libcaer: 64, the endpoint's packet size).
DEBUG_TRANSFER_BYTES = 64


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
    """The debug endpoint from open to close; keeps the last :data:`MAX_DEBUG_MESSAGES` messages and logs them.

    Where the backend has libusb's asynchronous API (``api``), :data:`DEBUG_TRANSFERS` interrupt transfers of
    :data:`DEBUG_TRANSFER_BYTES` stay in flight, as libcaer keeps them (a
    :class:`~davis_rig.usb.async_bulk.BulkTransferRing` of interrupt transfers); otherwise a thread polls ``read``.

    Args:
        read: ``read(timeout_ms) -> bytes | None`` (e.g. ``UsbTransport.read_debug``), used without ``api``.
        api: libusb's asynchronous API on the open device (``UsbTransport.async_transfers()``), or ``None``.
        clear_halt: ``clear_halt()`` of 0x81, run by the ring after a stall.
        timeout_ms: per-read timeout of the polling thread, ms (bounds how long :meth:`stop` waits).
        describe: device name for messages.

    The reader ends quietly on any USB error (the data path reports disconnects).
    """

    def __init__(
        self,
        read: Callable[[int], bytes | None],
        *,
        api: AsyncTransferApi | None = None,
        clear_halt: Callable[[], Any] | None = None,
        timeout_ms: int = 100,
        describe: str = "DAVIS",
    ):
        self._read = read
        self._api = api
        self._clear_halt = clear_halt or (lambda: None)
        self.timeout_ms = int(timeout_ms)
        self._describe = describe
        self._messages: deque[DebugMessage] = deque(maxlen=MAX_DEBUG_MESSAGES)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ring: BulkTransferRing | None = None

    def start(self) -> "DebugReader":
        """Start listening (a failure to submit the transfers is logged, not raised: the data path still works)."""
        if self._api is None:
            self._thread = threading.Thread(target=self._run, name="davis-usb-debug", daemon=True)
            self._thread.start()
            return self
        ring = BulkTransferRing(
            self._api,
            DEBUG_ENDPOINT,
            self._received,
            self._ended,
            self._clear_halt,
            transfers=DEBUG_TRANSFERS,
            transfer_bytes=DEBUG_TRANSFER_BYTES,
            describe=self._describe,
            transfer_type=LIBUSB_TRANSFER_TYPE_INTERRUPT,
            thread_name="davis-usb-debug",
        )
        try:
            ring.start()
        except DavisRigError as exc:
            _log.info("%s: debug endpoint 0x%02x not read: %s", self._describe, DEBUG_ENDPOINT, exc)
            return self
        self._ring = ring
        return self

    def stop(self, join_timeout_s: float = 5.0) -> None:
        """Stop listening: cancel the transfers (or end the polling thread) and wait for it."""
        self._stop.set()
        if self._ring is not None:
            self._ring.stop(join_timeout_s)
        if self._thread is not None:
            self._thread.join(join_timeout_s)

    @property
    def running(self) -> bool:
        """Whether the ring's or the polling thread is alive."""
        if self._ring is not None:
            return self._ring.running
        return self._thread is not None and self._thread.is_alive()

    @property
    def messages(self) -> list[DebugMessage]:
        """Messages received so far (oldest first, at most :data:`MAX_DEBUG_MESSAGES`)."""
        with self._lock:
            return list(self._messages)

    def _received(self, data: bytes) -> None:
        message = parse_debug_message(data)
        with self._lock:
            self._messages.append(message)
        if message.is_error:
            _log.warning("DAVIS firmware error %d at %d: %s", message.error_code, message.time_value, message.text)
        else:
            _log.info("DAVIS debug message of unknown format: %s", message.raw.hex())

    def _ended(self, error: BaseException | None) -> None:
        if error is not None:
            _log.info("%s: debug endpoint 0x%02x closed: %s", self._describe, DEBUG_ENDPOINT, error)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._read(self.timeout_ms)
            except DavisRigError:
                return
            if data:
                self._received(data)
