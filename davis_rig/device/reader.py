"""Background USB readers: keep bulk transfers going on 0x82 while the caller decodes and writes.

Two producers feed one bounded :class:`TransferQueue` (the consumer side: order, drop policy, end-of-stream error):

* :class:`RingReader` (default): a :class:`~davis_rig.usb.async_bulk.BulkTransferRing` of asynchronous libusb
  transfers, ``transfers`` × ``transfer_bytes`` always in flight and each resubmitted from its completion callback,
  as libcaer does (8 × 8 KiB). The host controller always holds empty buffers for the device, so no gap between
  two reads can overflow the FX3's FIFO.
* :class:`TransferReader`: a thread of synchronous reads, for pyusb backends without libusb's asynchronous API.
  Each read asks for ``read_bytes`` (default 128 KiB = 16 × 8 KiB): libusb splits it into several URBs queued at
  once, and a read returns when the buffer is full or the FX3 ends a transfer with a short packet (at least every
  early-packet delay, 1 ms); at the worst-case ~48 MB/s (~2 words per event at 12 Mev/s) one read covers ~2.7 ms
  and the host-side gap between reads (tens of µs) is ~1-2 % of the time.

Either way the producer does nothing but receive and enqueue (libusb releases the GIL while it waits), so decoding
and disk writes never delay USB; if the consumer falls behind for longer than the bounded queue covers
(``queue_transfers``), whole transfers are dropped and counted in :attr:`ReaderStats.dropped_transfers` (plus one
warning) instead of blocking USB — the same policy as libcaer's ring buffer (and the FPGA's own "drop DVS on
transfer stall").
"""

from __future__ import annotations

import queue
import threading
import time
import warnings
from dataclasses import dataclass
from typing import Callable

from davis_rig.protocol.config import DATA_ENDPOINT
from davis_rig.usb.async_bulk import DEFAULT_TRANSFER_BYTES, DEFAULT_TRANSFERS, AsyncTransferApi, BulkTransferRing


#: Default bytes per synchronous bulk read: 16 libcaer-sized (8 KiB) transfers.
DEFAULT_READ_BYTES = 16 * 8192
#: Default read timeout, ms (bounds how long stop() waits for the thread).
DEFAULT_READ_TIMEOUT_MS = 100
#: Default queue depth of the synchronous reader, in reads (64 MiB nominal at 128 KiB).
DEFAULT_QUEUE_TRANSFERS = 512
#: Default nominal queue capacity of the ring, bytes: the same 64 MiB (2048 transfers of 32 KiB).
DEFAULT_QUEUE_BYTES = DEFAULT_QUEUE_TRANSFERS * DEFAULT_READ_BYTES


@dataclass
class ReaderStats:
    """Counters of a reader (snapshot copies are returned).

    Attributes:
        transfers: transfers (or reads) that returned data.
        bytes: bytes received.
        dropped_transfers: transfers discarded because the queue was full.
        dropped_bytes: bytes in those transfers.
        timeouts: reads that returned no data within the timeout, or transfers that completed empty (idle camera,
            not an error).
        stalls: endpoint stalls cleared (ring only; synchronous reads count them in ``UsbTransport.stalls``).
    """

    transfers: int = 0
    bytes: int = 0
    dropped_transfers: int = 0
    dropped_bytes: int = 0
    timeouts: int = 0
    stalls: int = 0


class _End:
    """Queue sentinel: the reader stopped (``error`` set when it died of an error)."""

    def __init__(self, error: BaseException | None):
        self.error = error


class TransferQueue:
    """The consumer side shared by the readers: a bounded queue of transfers in arrival order.

    Producers call :meth:`_put` for every transfer with data and :meth:`_end` once; the consumer calls :meth:`get`
    / :meth:`get_nowait`. Subclasses provide ``start()``, ``stop()`` and ``running``.

    Args:
        queue_transfers: queue depth in transfers; when full, new transfers are dropped and counted.
    """

    def __init__(self, queue_transfers: int = DEFAULT_QUEUE_TRANSFERS):
        self._queue: queue.Queue = queue.Queue(maxsize=int(queue_transfers))
        self._stop = threading.Event()
        self._stats = ReaderStats()
        self._lock = threading.Lock()
        self._warned = False
        self._finished = False
        self._held_end: _End | None = None
        #: the exception that ended the reader, if any
        self.error: BaseException | None = None

    @property
    def stats(self) -> ReaderStats:
        """A snapshot of the counters."""
        with self._lock:
            return ReaderStats(**vars(self._stats))

    # --- producer side ----------------------------------------------------------------------------
    def _put(self, data: bytes) -> None:
        """Queue one transfer, or drop and count it when the queue is full (never blocks)."""
        try:
            self._queue.put_nowait(data)
        except queue.Full:
            with self._lock:
                self._stats.dropped_transfers += 1
                self._stats.dropped_bytes += len(data)
            if not self._warned:
                self._warned = True
                warnings.warn(
                    "DAVIS reader: the consumer is too slow, USB transfers are being dropped "
                    "(see stats.dropped_transfers)",
                    RuntimeWarning,
                    stacklevel=1,
                )
            return
        with self._lock:
            self._stats.transfers += 1
            self._stats.bytes += len(data)

    def _count_timeout(self) -> None:
        with self._lock:
            self._stats.timeouts += 1

    def _end(self, error: BaseException | None) -> None:
        """Queue the end of the stream (after every transfer queued before it)."""
        self.error = error
        # the sentinel must get through even if the queue is full: block until the consumer makes room
        # or the consumer is gone (stop() called), then give up after a short while
        end = _End(error)
        while True:
            try:
                self._queue.put(end, timeout=0.05)
                break
            except queue.Full:
                if self._stop.is_set():
                    break  # nobody will drain the queue any more; the error stays in self.error

    def _producer_alive(self) -> bool:
        raise NotImplementedError

    # --- consumer side ----------------------------------------------------------------------------
    def get(self, timeout_s: float | None = None) -> bytes | None:
        """Next transfer, in arrival order.

        Args:
            timeout_s: how long to wait, s (``None`` = until data or the end of the thread).

        Returns:
            The transfer's bytes, or ``None`` if nothing arrived in time or the reader has ended and its queue is
            drained (see :attr:`finished`).

        Raises:
            Exception: the error that ended the reader (e.g. ``DeviceDisconnectedError``), raised once all
                transfers read before it have been returned.
        """
        if self._finished:
            return None
        if self._held_end is not None:
            item, self._held_end = self._held_end, None
            self._finished = True
            if item.error is not None:
                raise item.error
            return None
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                item = self._queue.get(timeout=0.1 if wait is None else min(wait, 0.1))
            except queue.Empty:
                if not self._producer_alive() and self._queue.empty():
                    self._finished = True
                    return None
                if deadline is not None and time.monotonic() >= deadline:
                    return None
                continue
            if isinstance(item, _End):
                self._finished = True
                if item.error is not None:
                    raise item.error
                return None
            return item

    def get_nowait(self) -> bytes | None:
        """Next transfer if one is already queued, else ``None`` (never blocks, never raises).

        The end of the stream (and its error) is left for the next :meth:`get`.
        """
        if self._finished or self._held_end is not None:
            return None
        try:
            item = self._queue.get_nowait()
        except queue.Empty:
            return None
        if isinstance(item, _End):
            self._held_end = item
            return None
        return item

    @property
    def finished(self) -> bool:
        """True once :meth:`get` has seen the end of the stream (thread stopped and queue drained)."""
        return self._finished



class TransferReader(TransferQueue):
    """A thread that calls ``read(size, timeout_ms)`` in a loop and queues the results.

    Args:
        read: ``read(size_bytes, timeout_ms) -> bytes | None`` (``None`` = timed out), e.g.
            :meth:`UsbTransport.read_data`. Errors it raises end the thread and are re-raised by :meth:`get`
            after every transfer read before them has been handed out.
        read_bytes: bytes per read (a multiple of 8192 is best).
        timeout_ms: per-read timeout, ms.
        queue_transfers: queue depth in reads; when full, new reads are dropped and counted.

    Use as a context manager or call :meth:`start` / :meth:`stop`.
    """

    def __init__(
        self,
        read: Callable[[int, int], bytes | None],
        *,
        read_bytes: int = DEFAULT_READ_BYTES,
        timeout_ms: int = DEFAULT_READ_TIMEOUT_MS,
        queue_transfers: int = DEFAULT_QUEUE_TRANSFERS,
    ):
        super().__init__(queue_transfers)
        self._read = read
        self.read_bytes = int(read_bytes)
        self.timeout_ms = int(timeout_ms)
        self._thread: threading.Thread | None = None

    def start(self) -> "TransferReader":
        """Start the reader thread (once)."""
        if self._thread is not None:
            raise RuntimeError("TransferReader already started")
        self._thread = threading.Thread(target=self._run, name="davis-usb-reader", daemon=True)
        self._thread.start()
        return self

    def stop(self, join_timeout_s: float = 5.0) -> None:
        """Ask the thread to stop after its current read and wait for it (queued data stays available)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(join_timeout_s)

    @property
    def running(self) -> bool:
        """Whether the thread is alive."""
        return self._producer_alive()

    def _producer_alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        error: BaseException | None = None
        try:
            while not self._stop.is_set():
                data = self._read(self.read_bytes, self.timeout_ms)
                if data:
                    self._put(data)
                else:
                    self._count_timeout()
        except Exception as exc:  # handed to the consumer, re-raised by get()
            error = exc
        finally:
            self._end(error)

    def __enter__(self) -> "TransferReader":
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()


class RingReader(TransferQueue):
    """Several asynchronous bulk transfers in flight on 0x82 (a :class:`BulkTransferRing`), queued in order.

    Args:
        api: libusb's asynchronous API on the open device (:meth:`UsbTransport.async_transfers`).
        clear_halt: ``clear_halt()`` of the data endpoint, run after a stall.
        transfers: transfers in flight (libcaer: 8).
        transfer_bytes: bytes per transfer.
        queue_transfers: queue depth in transfers; when full, new transfers are dropped and counted (default:
            ``DEFAULT_QUEUE_BYTES // transfer_bytes``).
        describe: device name for messages.

    Errors that end the stream (unplug, a failed transfer) are re-raised by :meth:`get` after every transfer
    received before them. Use as a context manager or call :meth:`start` / :meth:`stop`.
    """

    def __init__(
        self,
        api: AsyncTransferApi,
        clear_halt: Callable[[], object],
        *,
        transfers: int = DEFAULT_TRANSFERS,
        transfer_bytes: int = DEFAULT_TRANSFER_BYTES,
        queue_transfers: int | None = None,
        describe: str = "DAVIS",
    ):
        super().__init__(queue_transfers or max(1, DEFAULT_QUEUE_BYTES // int(transfer_bytes)))
        self._ring = BulkTransferRing(
            api,
            DATA_ENDPOINT,
            self._put,
            self._end,
            clear_halt,
            transfers=transfers,
            transfer_bytes=transfer_bytes,
            describe=describe,
        )
        self._started = False

    def start(self) -> "RingReader":
        """Submit the transfers and start the ring's event thread (once).

        Raises:
            DeviceDisconnectedError / TransportError: the transfers could not be submitted.
        """
        if self._started:
            raise RuntimeError("RingReader already started")
        self._started = True
        self._ring.start()
        return self

    def stop(self, join_timeout_s: float = 5.0) -> None:
        """Cancel the transfers in flight (their data is still queued) and wait for the ring's thread."""
        self._stop.set()
        self._ring.stop(join_timeout_s)

    @property
    def running(self) -> bool:
        """Whether the ring's event thread is alive."""
        return self._producer_alive()

    @property
    def stats(self) -> ReaderStats:
        """A snapshot of the counters (empty completions count as timeouts)."""
        stats = super().stats
        stats.timeouts = self._ring.stats.empty_completions
        stats.stalls = self._ring.stats.stalls
        return stats

    def _producer_alive(self) -> bool:
        return self._ring.running

    def __enter__(self) -> "RingReader":
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()
