"""A ring of asynchronous transfers: several in flight, like libcaer's 8 × 8 KiB bulk on 0x82 (and 4 × 64 B interrupt
on 0x81).

pyusb only exposes synchronous reads, so between two reads nothing is queued on the endpoint. libcaer instead keeps
a ring of asynchronous transfers submitted and resubmits each one from its completion callback (PROTOCOL.md §2),
so the host controller always holds empty buffers for the device. :class:`BulkTransferRing` does the same through
libusb's asynchronous API (``libusb_alloc_transfer`` / ``libusb_submit_transfer`` / ``libusb_cancel_transfer`` /
``libusb_handle_events_timeout_completed``), reached with ctypes on the libusb-1.0 library pyusb already loaded,
on the device handle pyusb opened and claimed (:class:`LibusbAsyncApi`).

The ring only talks to an :class:`AsyncTransferApi`: the real one above, or the virtual camera's
(:class:`davis_rig.usb.virtual.VirtualAsyncTransfers`), which completes the same ctypes transfer structures
through their C callback pointers — so every fake-device recording runs the ring's code unchanged.

Completion order is submission order for one endpoint, and libusb runs callbacks one at a time (in whichever thread
holds its event lock), so the bytes reach ``on_data`` in stream order. Teardown has one owner, the ring's thread
(see :class:`BulkTransferRing`). Policies (libcaer's, PROTOCOL.md §2 and §9.10):

* a transfer that completes (or is cancelled) with ``actual_length > 0`` delivers its bytes; a completed transfer is
  resubmitted at once, before its bytes are handed on;
* a stall: the other transfers are cancelled (their bytes delivered), the halt is cleared once all are back and the
  whole ring is resubmitted (counted in :attr:`RingStats.stalls`; libcaer instead gives up the stream);
* ``NO_DEVICE`` → :class:`~davis_rig.errors.DeviceDisconnectedError`, any other transfer error →
  :class:`~davis_rig.errors.TransportError`: no transfer is resubmitted, the others are cancelled and the error is
  reported after every byte received before it.
"""

from __future__ import annotations

import ctypes
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

from davis_rig.errors import DeviceDisconnectedError, TransportError

# libusb-1.0 constants (libusb.h)
LIBUSB_TRANSFER_TYPE_BULK = 2
LIBUSB_TRANSFER_TYPE_INTERRUPT = 3
LIBUSB_TRANSFER_COMPLETED = 0
LIBUSB_TRANSFER_ERROR = 1
LIBUSB_TRANSFER_TIMED_OUT = 2
LIBUSB_TRANSFER_CANCELLED = 3
LIBUSB_TRANSFER_STALL = 4
LIBUSB_TRANSFER_NO_DEVICE = 5
LIBUSB_TRANSFER_OVERFLOW = 6
LIBUSB_ERROR_NO_DEVICE = -4
LIBUSB_ERROR_NOT_FOUND = -5
LIBUSB_ERROR_INTERRUPTED = -10

#: libusb_transfer_status names, for messages.
TRANSFER_STATUS_NAMES = {
    LIBUSB_TRANSFER_COMPLETED: "completed",
    LIBUSB_TRANSFER_ERROR: "error",
    LIBUSB_TRANSFER_TIMED_OUT: "timed out",
    LIBUSB_TRANSFER_CANCELLED: "cancelled",
    LIBUSB_TRANSFER_STALL: "stall",
    LIBUSB_TRANSFER_NO_DEVICE: "no device",
    LIBUSB_TRANSFER_OVERFLOW: "overflow",
}

#: Default number of transfers in flight (libcaer: 8).
DEFAULT_TRANSFERS = 8
#: Default bytes per transfer: 4 × libcaer's 8 KiB, so one Python callback covers more data at the peak rate.
DEFAULT_TRANSFER_BYTES = 32 * 1024
#: How long one event-handling call waits, ms (bounds how late a stop is noticed).
EVENT_POLL_MS = 10
#: How long the ring keeps trying to collect its transfers when libusb's event handling fails, s.
DRAIN_LIMIT_S = 5.0


class LibusbTransfer(ctypes.Structure):
    """``struct libusb_transfer`` (libusb.h), without the trailing isochronous packet array (bulk only)."""


LibusbTransferPointer = ctypes.POINTER(LibusbTransfer)
#: ``void (*libusb_transfer_cb_fn)(struct libusb_transfer *)``
TransferCallback = ctypes.CFUNCTYPE(None, LibusbTransferPointer)
LibusbTransfer._fields_ = [
    ("dev_handle", ctypes.c_void_p),
    ("flags", ctypes.c_uint8),
    ("endpoint", ctypes.c_uint8),
    ("type", ctypes.c_uint8),
    ("timeout", ctypes.c_uint),
    ("status", ctypes.c_int),
    ("length", ctypes.c_int),
    ("actual_length", ctypes.c_int),
    ("callback", TransferCallback),
    ("user_data", ctypes.c_void_p),
    ("buffer", ctypes.c_void_p),
    ("num_iso_packets", ctypes.c_int),
]


class _Timeval(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long)]


class AsyncTransferApi(Protocol):
    """What :class:`BulkTransferRing` needs of libusb's asynchronous API, for one open device.

    Return codes are libusb's (0 = success, negative = ``LIBUSB_ERROR_*``).
    """

    dev_handle: int | None

    def alloc_transfer(self) -> Any:
        """A new ``LibusbTransfer`` pointer (no isochronous packets)."""

    def free_transfer(self, transfer: Any) -> None:
        """Free a transfer that is not in flight."""

    def submit_transfer(self, transfer: Any) -> int:
        """Queue a filled transfer on the device."""

    def cancel_transfer(self, transfer: Any) -> int:
        """Ask for an in-flight transfer to come back with ``CANCELLED`` (``LIBUSB_ERROR_NOT_FOUND`` if not in
        flight); thread-safe."""

    def handle_events(self, timeout_ms: int) -> int:
        """Run completion callbacks that are due, waiting up to ``timeout_ms`` for one."""


class LibusbAsyncApi:
    """:class:`AsyncTransferApi` on the real libusb-1.0, for a device opened by pyusb's libusb1 backend.

    Own ctypes prototypes on a separate ``CDLL`` object of the same library, so pyusb's are left untouched.

    Args:
        library_path: the libusb-1.0 shared library pyusb loaded.
        context: ``libusb_context *`` of pyusb's backend.
        dev_handle: ``libusb_device_handle *`` pyusb opened (interface 0 claimed).
    """

    def __init__(self, library_path: str, context: int | None, dev_handle: int):
        lib = ctypes.CDLL(library_path)
        self._alloc = lib.libusb_alloc_transfer
        self._alloc.argtypes = [ctypes.c_int]
        self._alloc.restype = LibusbTransferPointer
        self._free = lib.libusb_free_transfer
        self._free.argtypes = [LibusbTransferPointer]
        self._free.restype = None
        self._submit = lib.libusb_submit_transfer
        self._submit.argtypes = [LibusbTransferPointer]
        self._submit.restype = ctypes.c_int
        self._cancel = lib.libusb_cancel_transfer
        self._cancel.argtypes = [LibusbTransferPointer]
        self._cancel.restype = ctypes.c_int
        self._handle = lib.libusb_handle_events_timeout_completed
        self._handle.argtypes = [ctypes.c_void_p, ctypes.POINTER(_Timeval), ctypes.POINTER(ctypes.c_int)]
        self._handle.restype = ctypes.c_int
        self._context = context
        self.dev_handle = dev_handle

    def alloc_transfer(self) -> Any:
        transfer = self._alloc(0)
        if not transfer:
            raise MemoryError("libusb_alloc_transfer failed")
        return transfer

    def free_transfer(self, transfer: Any) -> None:
        self._free(transfer)

    def submit_transfer(self, transfer: Any) -> int:
        return self._submit(transfer)

    def cancel_transfer(self, transfer: Any) -> int:
        return self._cancel(transfer)

    def handle_events(self, timeout_ms: int) -> int:
        """Run the callbacks that are due (0); a signal that interrupts the wait is not an error.

        Raises:
            TransportError: libusb's event handling failed (its negative code): the ring ends with it, and the
                drain gives up after :data:`DRAIN_LIMIT_S` instead of waiting on completions that never come.
        """
        timeout = _Timeval(timeout_ms // 1000, (timeout_ms % 1000) * 1000)
        code = self._handle(self._context, ctypes.byref(timeout), None)
        if code < 0 and code != LIBUSB_ERROR_INTERRUPTED:
            raise TransportError(f"libusb_handle_events_timeout_completed failed (libusb error {code})", code)
        return 0


@dataclass
class RingStats:
    """Counters of a :class:`BulkTransferRing`.

    Attributes:
        completions: transfers that came back (any status).
        empty_completions: completed transfers with no data (the device ended a transfer with a zero-length packet).
        stalls: endpoint stalls cleared.
    """

    completions: int = 0
    empty_completions: int = 0
    stalls: int = 0


class BulkTransferRing:
    """Keep ``transfers`` bulk (or interrupt) IN transfers of ``transfer_bytes`` in flight on one endpoint.

    Ownership (PROTOCOL.md §7.2: libcaer cancels, waits for every completion and frees in one thread): the ring's
    own thread allocates nothing after :meth:`start`, and is the only one that cancels and frees. The completion
    callback may run in any thread that handles libusb events — the ring's, or another one: libusb runs every due
    callback in whichever thread holds its event lock, e.g. a synchronous control transfer of the caller's — so it
    only records the completion and resubmits, under the ring's lock. A transfer counts as outstanding from its
    submission until its callback has returned; the transfers are freed only when none is outstanding. :meth:`stop`
    only signals and waits for the thread.

    Args:
        api: the asynchronous transfer API of the open device.
        endpoint: IN endpoint (0x82 bulk data, 0x81 interrupt debug).
        on_data: ``on_data(bytes)``, called in stream order for every transfer that brought data, from the thread
            that runs the completion callback; it must not block for long (hand the bytes to a queue).
        on_end: ``on_end(error)``, called once from the ring's thread after every transfer is back and freed
            (``None`` after :meth:`stop`, else the error that ended the stream).
        clear_halt: ``clear_halt()`` after a stall (a synchronous control request; raises if the device is gone).
        transfers: transfers in flight.
        transfer_bytes: bytes per transfer (a multiple of the endpoint's packet size).
        describe: device name for messages.
        transfer_type: ``LIBUSB_TRANSFER_TYPE_BULK`` or ``LIBUSB_TRANSFER_TYPE_INTERRUPT``.
        thread_name: name of the ring's thread.
    """

    def __init__(
        self,
        api: AsyncTransferApi,
        endpoint: int,
        on_data: Callable[[bytes], Any],
        on_end: Callable[[BaseException | None], Any],
        clear_halt: Callable[[], Any],
        *,
        transfers: int = DEFAULT_TRANSFERS,
        transfer_bytes: int = DEFAULT_TRANSFER_BYTES,
        describe: str = "DAVIS",
        transfer_type: int = LIBUSB_TRANSFER_TYPE_BULK,
        thread_name: str = "davis-usb-ring",
    ):
        if transfers < 1:
            raise ValueError(f"transfers must be >= 1, got {transfers}")
        if transfer_bytes < 1:
            raise ValueError(f"transfer_bytes must be >= 1, got {transfer_bytes}")
        if transfer_type not in (LIBUSB_TRANSFER_TYPE_BULK, LIBUSB_TRANSFER_TYPE_INTERRUPT):
            raise ValueError(f"transfer_type must be bulk (2) or interrupt (3), got {transfer_type}")
        self._api = api
        self.endpoint = int(endpoint)
        self._on_data = on_data
        self._on_end = on_end
        self._clear_halt = clear_halt
        self.transfers = int(transfers)
        self.transfer_bytes = int(transfer_bytes)
        self.transfer_type = int(transfer_type)
        self._describe = describe
        self._thread_name = thread_name
        self._kind = "bulk" if transfer_type == LIBUSB_TRANSFER_TYPE_BULK else "interrupt"
        self.stats = RingStats()
        self._c_callback = TransferCallback(self._completed)  # kept alive as long as the ring
        self._buffers = [(ctypes.c_ubyte * self.transfer_bytes)() for _ in range(self.transfers)]
        self._slots: list[Any] = []
        self._slot_of: dict[int, int] = {}
        self._lock = threading.Lock()
        self._outstanding: set[int] = set()  # submitted, callback not yet returned
        self._cancelled: set[int] = set()  # cancel requested since the last submission
        self._stopping = False
        self._stalled = False
        self._error: BaseException | None = None
        self._probe_on_end = False  # a transfer came back ERROR: unplugged, or a USB error on a live camera?
        self._started = False
        self._thread: threading.Thread | None = None

    # --- control ----------------------------------------------------------------------------------
    def start(self) -> "BulkTransferRing":
        """Allocate and submit the transfers, then start the ring's thread.

        Raises:
            DeviceDisconnectedError / TransportError: the first submission failed (nothing was left in flight).
                A later submission that fails ends the started stream with that error instead (``on_end``), after
                the bytes of the transfers already in flight.
        """
        if self._started:
            raise RuntimeError("BulkTransferRing already started (a ring runs once)")
        self._started = True
        try:
            self._allocate_and_submit()
        except BaseException:
            with self._lock:
                self._stopping = True
            self._drain_and_free()  # no thread yet: the caller is the owner
            raise
        self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self, join_timeout_s: float = 5.0) -> None:
        """Ask the ring's thread to cancel the transfers in flight (their bytes are still delivered), wait for every
        completion and free them; wait up to ``join_timeout_s`` for it to finish.

        Safe from any thread, any number of times; a call from the ring's own thread (e.g. from ``on_data``) only
        signals.
        """
        with self._lock:
            self._stopping = True
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(join_timeout_s)

    @property
    def running(self) -> bool:
        """Whether the ring's thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def in_flight(self) -> int:
        """Transfers submitted whose completion callback has not returned yet."""
        with self._lock:
            return len(self._outstanding)

    # --- internals (the _locked methods run with self._lock held) ----------------------------------
    def _allocate_and_submit(self) -> None:
        for index, buffer in enumerate(self._buffers):
            transfer = self._api.alloc_transfer()
            fields = transfer.contents
            fields.dev_handle = self._api.dev_handle
            fields.flags = 0
            fields.endpoint = self.endpoint
            fields.type = self.transfer_type
            fields.timeout = 0  # infinite, like libcaer: a stop cancels them
            fields.length = self.transfer_bytes
            fields.actual_length = 0
            fields.callback = self._c_callback
            fields.user_data = None
            fields.buffer = ctypes.addressof(buffer)
            fields.num_iso_packets = 0
            self._slots.append(transfer)
            self._slot_of[ctypes.addressof(fields)] = index
        with self._lock:
            for index in range(self.transfers):
                try:
                    self._submit_locked(index)
                except (DeviceDisconnectedError, TransportError) as exc:
                    if index == 0:
                        raise  # nothing in flight: the stream never started
                    # Transfers are in flight and may already hold data (a camera unplugged while the ring was
                    # being filled): the stream started and ends with this error, after their bytes.
                    self._fail_locked(exc)
                    return

    def _submit_locked(self, index: int) -> None:
        code = self._api.submit_transfer(self._slots[index])
        if code != 0:
            raise self._submit_error(code)
        self._outstanding.add(index)
        self._cancelled.discard(index)

    def _submit_error(self, code: int) -> BaseException:
        if code == LIBUSB_ERROR_NO_DEVICE:
            return DeviceDisconnectedError(
                f"{self._describe}: {self._kind} transfer on 0x{self.endpoint:02x} could not be submitted: "
                "the camera was disconnected",
                code,
            )
        return TransportError(
            f"{self._describe}: {self._kind} transfer on 0x{self.endpoint:02x} could not be submitted "
            f"(libusb error {code})",
            code,
        )

    def _cancel_outstanding_locked(self) -> None:
        """Cancel every outstanding transfer not cancelled since its submission (ring thread / owner only)."""
        for index in self._outstanding - self._cancelled:
            self._cancelled.add(index)
            self._api.cancel_transfer(self._slots[index])  # NOT_FOUND if it just came back: harmless

    def _fail_locked(self, error: BaseException) -> None:
        if self._error is None:
            self._error = error

    def _completed(self, transfer_pointer: Any) -> None:
        """libusb completion callback (any event-handling thread). Exceptions must not escape into C."""
        index = None
        resubmitted = False
        try:
            fields = transfer_pointer.contents
            index = self._slot_of.get(ctypes.addressof(fields))
            if index is None:
                return  # not one of ours (cannot happen with a correct libusb)
            status = fields.status
            count = fields.actual_length
            data = ctypes.string_at(fields.buffer, count) if count > 0 else None
            with self._lock:
                self.stats.completions += 1
                if status == LIBUSB_TRANSFER_COMPLETED:
                    if data is None:
                        self.stats.empty_completions += 1
                    if not (self._stopping or self._stalled or self._error is not None):
                        try:
                            self._submit_locked(index)  # before the bytes are handed on, as libcaer does
                            resubmitted = True
                        except (DeviceDisconnectedError, TransportError) as exc:
                            self._fail_locked(exc)
                elif status == LIBUSB_TRANSFER_STALL:
                    self._stalled = True
                elif status == LIBUSB_TRANSFER_NO_DEVICE:
                    self._fail_locked(
                        DeviceDisconnectedError(
                            f"{self._describe}: {self._kind} transfer on 0x{self.endpoint:02x} failed: "
                            "the camera was disconnected"
                        )
                    )
                elif status != LIBUSB_TRANSFER_CANCELLED:
                    name = TRANSFER_STATUS_NAMES.get(status, f"status {status}")
                    # Linux reports an unplug to transfers in flight as EPROTO / EILSEQ (ERROR) as often as
                    # ENODEV (NO_DEVICE): probed once every transfer is back (see _run)
                    if status == LIBUSB_TRANSFER_ERROR and self._error is None:
                        self._probe_on_end = True
                    self._fail_locked(
                        TransportError(
                            f"{self._describe}: {self._kind} transfer on 0x{self.endpoint:02x} failed ({name})"
                        )
                    )
            if data is not None:
                self._on_data(data)
        except BaseException as exc:  # a bug or a failing on_data: end the stream with it
            with self._lock:
                self._fail_locked(exc)
        finally:
            if index is not None and not resubmitted:
                with self._lock:
                    self._outstanding.discard(index)
                    self._cancelled.discard(index)

    def _recover_stall(self) -> None:
        """Every transfer is back after a stall: clear the halt (no lock held: a synchronous request may run other
        callbacks in this thread) and resubmit the ring."""
        self._clear_halt()
        with self._lock:
            self._stalled = False
            self.stats.stalls += 1
            if self._stopping or self._error is not None:
                return
            for index in range(self.transfers):
                self._submit_locked(index)

    def _run(self) -> None:
        """The ring's thread: handle events; when stopping, stalled or failed, cancel what is outstanding; once
        nothing is outstanding, recover a stall or end."""
        try:
            while True:
                with self._lock:
                    ending = self._stopping or self._error is not None
                    if not self._outstanding:
                        if not self._stalled or ending:
                            break
                        recover = True
                    else:
                        recover = False
                        if ending or self._stalled:
                            self._cancel_outstanding_locked()
                if recover:
                    try:
                        self._recover_stall()
                    except BaseException as exc:  # the halt could not be cleared (unplugged), or resubmission failed
                        with self._lock:
                            self._fail_locked(exc)
                    continue
                self._api.handle_events(EVENT_POLL_MS)
        except BaseException as exc:  # handle_events itself failed
            with self._lock:
                self._fail_locked(exc)
        finally:
            self._drain_and_free()
            self._probe_failed_transfer()
            self._on_end(self._error)

    def _probe_failed_transfer(self) -> None:
        """After a transfer came back ERROR, clear the endpoint's halt as the synchronous reader does after EIO: on
        a vanished camera that fails too, and the stream ends "disconnected" (a clean end of a recording) rather
        than with a transfer error; on a live one the transfer error stands."""
        if not self._probe_on_end:
            return
        try:
            self._clear_halt()
        except BaseException as exc:  # any failure to reach the endpoint: it is gone
            self._error = DeviceDisconnectedError(
                f"{self._error} and the endpoint could not be recovered ({exc}); the camera was disconnected"
            )
            self._error.__cause__ = exc

    def _drain_and_free(self) -> None:
        """Cancel what is outstanding, handle events until every callback has returned, then free the transfers.

        If libusb stops handing back completions (handle_events keeps failing for :data:`DRAIN_LIMIT_S`), the
        transfers are left allocated rather than freed while in flight.
        """
        deadline = None
        while True:
            with self._lock:
                if not self._outstanding:
                    break
                self._cancel_outstanding_locked()
            try:
                self._api.handle_events(EVENT_POLL_MS)
                deadline = None
            except BaseException as exc:
                with self._lock:
                    self._fail_locked(exc)
                deadline = deadline or time.monotonic() + DRAIN_LIMIT_S
                if time.monotonic() > deadline:
                    return  # leak, never free a transfer libusb may still complete
        for transfer in self._slots:
            self._api.free_transfer(transfer)
        self._slots.clear()
        self._slot_of.clear()
