"""A virtual DAVIS346 behind a real ``usb.backend.IBackend``, so the unmodified pyusb code path runs without a camera.

The package: :mod:`~davis_rig.usb.virtual.device` (the device model), :mod:`~davis_rig.usb.virtual.backend` (the
pyusb backend and its descriptors), :mod:`~davis_rig.usb.virtual.transfers` (libusb's asynchronous transfers).

Modelled on pyftdi's virtual backend (``pyftdi/tests/backend/usbvirt.py``): the backend answers descriptor and
standard requests, routes vendor control transfers and bulk reads to a :class:`VirtualDavis346` device model.
Pass it explicitly: ``usb.core.find(backend=VirtualDavis346Backend(VirtualDavis346()))`` or
``Davis346.open(backend=...)`` — there is no environment switch.

The device model

- presents VID 0x152A / PID 0x841A, bcdDevice with the firmware version in its low byte, a serial string,
  one configuration with interface 0 and endpoints 0x82 (bulk IN) and 0x81 (interrupt IN);
- answers the read-only registers libcaer reads at open (PROTOCOL.md §5) from a
  :class:`~davis_rig.protocol.layout.SensorLayout`-like mapping, clocks, versions and feature flags — all
  configurable (e.g. a wrong logic version to test the version gate);
- keeps a register file, and **records every control transfer** (:attr:`VirtualDavis346.control_log`,
  :attr:`VirtualDavis346.writes`) so tests can assert the exact §6/§7 sequences;
- honours the RUN flags: bulk data flows only while MUX RUN, USB RUN and at least one of DVS RUN / APS RUN are set;
- serves bulk reads on 0x82 from a :class:`~davis_rig.usb.sources.DataSource`, one transfer per read, and
  injects :class:`~davis_rig.usb.sources.Faults` (disconnect, stalls, timeouts, short/odd transfers, garbage,
  permission/busy errors) with the errno/libusb codes libusb-1.0 reports. Like a real bulk read, a read
  completes at the end of a transfer that ends with a short packet; transfers made of whole 1024-byte packets
  run on into the next released transfer until the host buffer is full.
"""

from davis_rig.usb.virtual.backend import VirtualDavis346Backend
from davis_rig.usb.virtual.device import (
    LIBUSB_ERROR_ACCESS,
    LIBUSB_ERROR_BUSY,
    LIBUSB_ERROR_IO,
    LIBUSB_ERROR_PIPE,
    LIBUSB_ERROR_TIMEOUT,
    MAX_PACKET_BYTES,
    VIRTUAL_CLOCKS,
    VIRTUAL_FEATURES,
    ControlRecord,
    VirtualDavis346,
    usb_error,
)
from davis_rig.usb.virtual.transfers import VirtualAsyncTransfers

__all__ = [
    "LIBUSB_ERROR_ACCESS",
    "LIBUSB_ERROR_BUSY",
    "LIBUSB_ERROR_IO",
    "LIBUSB_ERROR_PIPE",
    "LIBUSB_ERROR_TIMEOUT",
    "MAX_PACKET_BYTES",
    "VIRTUAL_CLOCKS",
    "VIRTUAL_FEATURES",
    "ControlRecord",
    "VirtualAsyncTransfers",
    "VirtualDavis346",
    "VirtualDavis346Backend",
    "usb_error",
]
