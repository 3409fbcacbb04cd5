"""libusb's asynchronous transfer API on the virtual DAVIS346: :class:`VirtualAsyncTransfers`, what
``VirtualDavis346Backend.async_transfers`` hands the ring of bulk transfers (:mod:`davis_rig.usb.async_bulk`)."""

from __future__ import annotations

import ctypes
import errno as errno_mod
import threading
import time
from typing import Any

import usb.core

from davis_rig.usb.async_bulk import (
    LIBUSB_ERROR_NO_DEVICE,
    LIBUSB_ERROR_NOT_FOUND,
    LIBUSB_TRANSFER_CANCELLED,
    LIBUSB_TRANSFER_COMPLETED,
    LIBUSB_TRANSFER_ERROR,
    LIBUSB_TRANSFER_NO_DEVICE,
    LIBUSB_TRANSFER_STALL,
    LIBUSB_TRANSFER_TYPE_INTERRUPT,
    LibusbTransfer,
)
from davis_rig.usb.virtual.device import VirtualDavis346

__all__ = ["VirtualAsyncTransfers"]


class VirtualAsyncTransfers:
    """libusb's asynchronous transfer API (:class:`~davis_rig.usb.async_bulk.AsyncTransferApi`) on a virtual camera.

    Transfers are real ``LibusbTransfer`` structures completed through their C callback pointers, in submission
    order like a host controller: :meth:`handle_events` serves the oldest transfer in flight with one
    :meth:`VirtualDavis346.bulk_read` (:meth:`~VirtualDavis346.intr_read` for interrupt transfers) into its buffer
    (waiting up to the poll timeout, faults included) and maps the outcome to a transfer status (ETIMEDOUT → still
    in flight, EPIPE → ``STALL``, ENODEV → ``NO_DEVICE``). Cancelled transfers come back with ``CANCELLED`` and no
    data.

    Args:
        device: the virtual camera (its interface claimed by the caller).
    """

    dev_handle = None

    def __init__(self, device: "VirtualDavis346"):
        self._device = device
        self._queue: list[Any] = []
        self._cancelled: set[int] = set()
        self._lock = threading.Lock()

    def alloc_transfer(self) -> Any:
        return ctypes.pointer(LibusbTransfer())

    def free_transfer(self, transfer: Any) -> None:
        return None

    def submit_transfer(self, transfer: Any) -> int:
        if self._device.unplugged:
            return LIBUSB_ERROR_NO_DEVICE
        with self._lock:
            self._queue.append(transfer)
        return 0

    def cancel_transfer(self, transfer: Any) -> int:
        with self._lock:
            key = ctypes.addressof(transfer.contents)
            if key in self._cancelled or not any(ctypes.addressof(t.contents) == key for t in self._queue):
                return LIBUSB_ERROR_NOT_FOUND  # like libusb: not in flight, or already cancelled
            self._cancelled.add(key)
        return 0

    def handle_events(self, timeout_ms: int) -> int:
        with self._lock:
            if not self._queue:
                head = None
            else:
                head = self._queue[0]
                cancelled = ctypes.addressof(head.contents) in self._cancelled
        if head is None:
            time.sleep(timeout_ms / 1000.0)
            return 0
        fields = head.contents
        count = 0
        if cancelled:
            status = LIBUSB_TRANSFER_CANCELLED
        else:
            buffer = (ctypes.c_ubyte * fields.length).from_address(fields.buffer)
            try:
                interrupt = fields.type == LIBUSB_TRANSFER_TYPE_INTERRUPT
                read = self._device.intr_read if interrupt else self._device.bulk_read
                count = read(fields.endpoint, buffer, timeout_ms)
                status = LIBUSB_TRANSFER_COMPLETED
            except usb.core.USBTimeoutError:
                return 0  # nothing yet: the transfer stays in flight
            except usb.core.USBError as exc:
                status = {errno_mod.EPIPE: LIBUSB_TRANSFER_STALL, errno_mod.ENODEV: LIBUSB_TRANSFER_NO_DEVICE}.get(
                    exc.errno, LIBUSB_TRANSFER_ERROR
                )
        with self._lock:
            self._queue.pop(0)
            self._cancelled.discard(ctypes.addressof(fields))
        fields.status = status
        fields.actual_length = count
        fields.callback(head)
        return 0
