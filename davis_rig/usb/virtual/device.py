"""The device model of the virtual DAVIS346 (FX3): :class:`VirtualDavis346`, served by
:class:`~davis_rig.usb.virtual.backend.VirtualDavis346Backend` (the package docstring tells what it presents).

Also the libusb-1.0 error mapping every part of the virtual camera raises (:func:`usb_error`).
"""

from __future__ import annotations

import errno as errno_mod
import struct
import threading
import time
from dataclasses import dataclass, fields
from typing import Any, Callable, Mapping

import numpy as np
import usb.core

from davis_rig.protocol.config import (
    DATA_ENDPOINT,
    DAVIS_FX3_PID,
    DEBUG_ENDPOINT,
    DEVICE_INFO_REGISTERS,
    INIVATION_VID,
    REQUEST_TYPE_VENDOR_IN,
    REQUEST_TYPE_VENDOR_OUT,
    VR_FPGA_CONFIG,
    VR_FPGA_CONFIG_MULTIPLE,
    Aps,
    Clocks,
    ConfigWrite,
    DeviceFeatures,
    Dvs,
    Module,
    Mux,
    SysInfo,
    Usb,
    decode_multiple,
)
from davis_rig.protocol.layout import SensorLayout
from davis_rig.usb.async_bulk import LIBUSB_ERROR_NO_DEVICE
from davis_rig.usb.sources import DataSource, Faults

#: libusb-1.0 error codes (what pyusb's libusb1 backend puts in ``backend_error_code``).
LIBUSB_ERROR_IO = -1
LIBUSB_ERROR_ACCESS = -3
LIBUSB_ERROR_BUSY = -6
LIBUSB_ERROR_TIMEOUT = -7
LIBUSB_ERROR_PIPE = -9
_ERRNO_TO_LIBUSB = {
    errno_mod.EIO: LIBUSB_ERROR_IO,
    errno_mod.EACCES: LIBUSB_ERROR_ACCESS,
    errno_mod.ENODEV: LIBUSB_ERROR_NO_DEVICE,
    errno_mod.EBUSY: LIBUSB_ERROR_BUSY,
    errno_mod.ETIMEDOUT: LIBUSB_ERROR_TIMEOUT,
    errno_mod.EPIPE: LIBUSB_ERROR_PIPE,
}
_STRERROR = {
    LIBUSB_ERROR_IO: "Input/output error",
    LIBUSB_ERROR_ACCESS: "Access denied (insufficient permissions)",
    LIBUSB_ERROR_NO_DEVICE: "No such device (it may have been disconnected)",
    LIBUSB_ERROR_BUSY: "Resource busy",
    LIBUSB_ERROR_TIMEOUT: "Operation timed out",
    LIBUSB_ERROR_PIPE: "Pipe error",
}


def usb_error(errno: int) -> usb.core.USBError:
    """The pyusb exception libusb-1.0 would raise for ``errno`` (timeouts as ``USBTimeoutError``)."""
    code = _ERRNO_TO_LIBUSB.get(errno, -99)
    text = _STRERROR.get(code, "Unknown error")
    if errno == errno_mod.ETIMEDOUT:
        return usb.core.USBTimeoutError(text, code, errno)
    return usb.core.USBError(text, code, errno)


def transfer_deadline(timeout_ms: int) -> float | None:
    """The ``time.monotonic()`` deadline, s, of a transfer timeout in ms; ``None`` for 0 (pyusb: wait forever)."""
    return None if timeout_ms == 0 else time.monotonic() + timeout_ms / 1000.0


def copy_into(buff: Any, data: bytes) -> int:
    """Copy as much of ``data`` as fits into the writable transfer buffer ``buff``; returns the byte count."""
    n = min(len(data), len(buff))
    memoryview(buff).cast("B")[:n] = data[:n]
    return n


#: wMaxPacketSize of the bulk endpoint at SuperSpeed, bytes.
MAX_PACKET_BYTES = 1024

#: The read-outs a layout gives the virtual device (``SensorLayout``'s fields, the test vectors' ``device_info``).
READ_OUTS = tuple(f.name for f in fields(SensorLayout))
#: Clocks of the virtual device. Placeholders (jAER's fallback values), not a statement about real DAVIS346 hardware.
VIRTUAL_CLOCKS = Clocks(logic_mhz=90, adc_mhz=30, usb_mhz=30, deviation=1000)
#: Feature flags of the virtual device: a global-shutter APS, no optional DVS filters.
VIRTUAL_FEATURES = DeviceFeatures(aps_has_global_shutter=True)


def _as_info_dict(layout: Any) -> dict[str, int]:
    if layout is None:
        return SensorLayout.davis346().to_dict()
    if isinstance(layout, Mapping):
        src = dict(layout)
    else:
        src = {k: getattr(layout, k) for k in READ_OUTS if hasattr(layout, k)}
    missing = [k for k in READ_OUTS if k not in src]
    if missing:
        raise ValueError(f"virtual DAVIS layout: missing read-outs {missing}")
    return {k: int(src[k]) for k in READ_OUTS}


class Descriptor:
    """A descriptor: attribute bag pyusb reads with getattr."""

    def __init__(self, **kw: Any):
        self.__dict__.update(kw)


@dataclass(frozen=True)
class ControlRecord:
    """One control transfer the virtual device received.

    Attributes:
        request_type: ``bmRequestType``.
        request: ``bRequest``.
        value: ``wValue``.
        index: ``wIndex``.
        data: OUT data stage (bytes), or ``b""`` for IN requests.
        length: IN ``wLength`` (0 for OUT).
    """

    request_type: int
    request: int
    value: int
    index: int
    data: bytes
    length: int


class VirtualDavis346:
    """Device model of a DAVIS346 (FX3) for :class:`VirtualDavis346Backend`.

    Args:
        serial: serial string (≤ 8 chars); ``None`` = no serial descriptor (host falls back to ``TMPnnnnn``).
        layout: raw read-outs — a ``SensorLayout`` or a mapping with the test vectors' ``device_info`` names;
            default ``SensorLayout.davis346()``.
        clocks: SYSINFO 3-6.
        features: ``HAS_*`` read-only flags.
        firmware_version: bcdDevice low byte (6 passes the FX3 gate).
        logic_version: SYSINFO 0 (18 passes the gate).
        logic_patch: SYSINFO 7 (>= 1 passes).
        product_id: USB PID (0x841A FX3).
        source: the bulk data source (can be set later with :meth:`attach_source`).
        faults: fault injection.
        bus, address: USB position (enumeration order and the ``TMPnnnnn`` fallback use them).
        clock: monotonic clock in seconds, for pacing (tests may inject one).

    Attributes:
        registers: ``{(module, param): value}`` register file.
        control_log: every control transfer, in arrival order.
        clear_halts: endpoints on which CLEAR_FEATURE(HALT) was received, in order.
        transfers_served: bulk transfers (pieces) handed out on 0x82.
        bytes_served: bytes handed out on 0x82.
        claimed: whether interface 0 is claimed.
    """

    def __init__(
        self,
        *,
        serial: str | None = "VIRT0001",
        layout: Any = None,
        clocks: Clocks = VIRTUAL_CLOCKS,
        features: DeviceFeatures = VIRTUAL_FEATURES,
        firmware_version: int = 6,
        logic_version: int = 18,
        logic_patch: int = 1,
        product_id: int = DAVIS_FX3_PID,
        source: DataSource | None = None,
        faults: Faults = Faults(),
        bus: int = 1,
        address: int = 2,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.serial = serial
        self.device_info = _as_info_dict(layout)
        self.clocks = clocks
        self.features = features
        self.firmware_version = int(firmware_version)
        self.product_id = int(product_id)
        self.source = source
        self.faults = faults
        self.bus = int(bus)
        self.address = int(address)
        self._clock = clock
        self.registers: dict[tuple[int, int], int] = {}
        self.control_log: list[ControlRecord] = []
        self.clear_halts: list[int] = []
        self.transfers_served = 0
        self.bytes_served = 0
        self.claimed = False
        self.configuration = 0
        self.unplugged = False
        self._halted = False
        self._pending: bytes | None = None
        self._debug: list[bytes] = []
        self._bulk_reads = 0
        self._transfer_count = 0
        self._run_start: float | None = None
        self._streamed_s = 0.0  # device streaming time accumulated over earlier start/stop cycles
        self._rng = np.random.default_rng(faults.seed)
        self._cond = threading.Condition()
        self._read_only = self._build_read_only(logic_version, logic_patch)

    # --- construction helpers ---------------------------------------------------------------------
    def _build_read_only(self, logic_version: int, logic_patch: int) -> dict[tuple[int, int], int]:
        groups = {"layout": self.device_info, "clocks": vars(self.clocks), "features": vars(self.features)}

        def value(field: str) -> int:
            if field == "is_master":
                return 1
            group, name = field.split(".")
            return int(groups[group][name])

        ro = {(int(m), int(p)): value(field) for m, p, field in DEVICE_INFO_REGISTERS}
        ro[(int(Module.SYSINFO), int(SysInfo.LOGIC_VERSION))] = int(logic_version)
        ro[(int(Module.SYSINFO), int(SysInfo.LOGIC_PATCH))] = int(logic_patch)
        return ro

    @classmethod
    def from_replay(cls, path: Any, *, paced: bool = False, **kwargs: Any) -> "VirtualDavis346":
        """A virtual camera that reports the read-outs stored in a replay file and serves its transfers.

        Args:
            path: replay file.
            paced: release transfers at their recorded host times.
            **kwargs: overrides for the constructor.
        """
        from davis_rig.usb.sources import ReplaySource

        source = ReplaySource(path, paced=paced)
        header = source.header
        params: dict[str, Any] = dict(layout=header.device_info, source=source)
        if header.serial:
            params["serial"] = header.serial
        if header.clocks:
            params["clocks"] = Clocks(**header.clocks)
        for name in ("firmware_version", "logic_version", "logic_patch"):
            if getattr(header, name):
                params[name] = getattr(header, name)
        if isinstance(header.extra.get("features"), dict):
            known = {f.name for f in fields(DeviceFeatures)}
            params["features"] = DeviceFeatures(**{k: bool(v) for k, v in header.extra["features"].items() if k in known})
        params.update(kwargs)
        return cls(**params)

    def attach_source(self, source: DataSource) -> None:
        """Set (or replace) the bulk data source."""
        with self._cond:
            self.source = source
            self._cond.notify_all()

    # --- observation helpers for tests ------------------------------------------------------------
    @property
    def writes(self) -> list[ConfigWrite]:
        """Every register write received (0xBF singles and expanded 0xC2 records), in order."""
        out: list[ConfigWrite] = []
        for rec in self.control_log:
            if rec.request_type == REQUEST_TYPE_VENDOR_OUT and rec.request == VR_FPGA_CONFIG:
                out.append(ConfigWrite(rec.value, rec.index, struct.unpack(">I", rec.data)[0]))
            elif rec.request_type == REQUEST_TYPE_VENDOR_OUT and rec.request == VR_FPGA_CONFIG_MULTIPLE:
                out += decode_multiple(rec.data, rec.value)
        return out

    @property
    def reads(self) -> list[tuple[int, int]]:
        """Every register read ``(module, param)`` received, in order."""
        return [
            (rec.value, rec.index)
            for rec in self.control_log
            if rec.request_type == REQUEST_TYPE_VENDOR_IN and rec.request == VR_FPGA_CONFIG
        ]

    def register(self, module: int, param: int) -> int:
        """Current value of a register (read-only registers report their read-out)."""
        key = (int(module), int(param))
        return self._read_only.get(key, self.registers.get(key, 0))

    @property
    def streaming(self) -> bool:
        """Whether the device would send data: MUX RUN, USB RUN and DVS RUN or APS RUN set."""
        r = self.register
        return bool(
            r(Module.MUX, Mux.RUN) and r(Module.USB, Usb.RUN) and (r(Module.DVS, Dvs.RUN) or r(Module.APS, Aps.RUN))
        )

    @property
    def drained(self) -> bool:
        """True once every transfer of the source has been handed to the host (nothing pending either)."""
        with self._cond:
            return self._pending is None and (self.source is None or len(self.source) == 0)

    def unplug(self) -> None:
        """Simulate pulling the cable now: every later request fails with ENODEV."""
        with self._cond:
            self.unplugged = True
            self._cond.notify_all()

    # --- requests from the backend ----------------------------------------------------------------
    def check_present(self) -> None:
        """Raise the ENODEV error libusb reports once the device is unplugged (every request checks it first)."""
        if self.unplugged:
            raise usb_error(errno_mod.ENODEV)

    def control(self, request_type: int, request: int, value: int, index: int, data: Any) -> Any:
        """Handle a vendor control transfer; returns bytes written (OUT) or the reply bytes (IN)."""
        with self._cond:
            self.check_present()
            if request_type & 0x80:
                length = len(data)
                self.control_log.append(ControlRecord(request_type, request, value, index, b"", length))
                if request_type == REQUEST_TYPE_VENDOR_IN and request == VR_FPGA_CONFIG:
                    return struct.pack(">I", self.register(value, index) & 0xFFFFFFFF)[:length]
                raise usb_error(errno_mod.EPIPE)  # unsupported request → stall, like a real device
            payload = bytes(data)
            self.control_log.append(ControlRecord(request_type, request, value, index, payload, 0))
            if request == VR_FPGA_CONFIG:
                if len(payload) != 4:
                    raise usb_error(errno_mod.EPIPE)
                self._write(value, index, struct.unpack(">I", payload)[0])
            elif request == VR_FPGA_CONFIG_MULTIPLE:
                if len(payload) != 6 * value:
                    raise usb_error(errno_mod.EPIPE)
                for w in decode_multiple(payload, value):
                    self._write(w.module, w.param, w.value)
            else:
                raise usb_error(errno_mod.EPIPE)
            return len(payload)

    def _write(self, module: int, param: int, value: int) -> None:
        key = (int(module), int(param))
        if key in self._read_only:
            return  # the FPGA ignores writes to read-only registers
        was_streaming = self.streaming
        self.registers[key] = int(value)
        if not was_streaming and self.streaming:
            self._run_start = self._clock()
        elif was_streaming and not self.streaming and self._run_start is not None:
            self._streamed_s += self._clock() - self._run_start
            self._run_start = None
        self._cond.notify_all()

    def _device_time_us(self) -> float:
        """Streaming time of the device, µs: the pacing clock (it pauses while the device is stopped)."""
        running_s = self._clock() - self._run_start if self._run_start is not None else 0.0
        return (self._streamed_s + running_s) * 1e6

    def clear_halt(self, endpoint: int) -> None:
        """CLEAR_FEATURE(ENDPOINT_HALT)."""
        with self._cond:
            self.check_present()
            self.clear_halts.append(int(endpoint))
            if endpoint == DATA_ENDPOINT:
                self._halted = False

    def _wait(self, deadline: float | None, until: float | None = None) -> bool:
        """Wait on the condition until notified, ``until`` or ``deadline``; False once the deadline passed."""
        now = time.monotonic()
        if deadline is not None and now >= deadline:
            return False
        limits = [x for x in (deadline, until) if x is not None]
        self._cond.wait(timeout=(min(limits) - now) if limits else None)
        return True

    def bulk_read(self, endpoint: int, buff: Any, timeout_ms: int) -> int:
        """Serve one bulk read on 0x82 into ``buff``; returns the byte count (see class docstring for faults)."""
        deadline = transfer_deadline(timeout_ms)
        with self._cond:
            self.check_present()
            if endpoint != DATA_ENDPOINT:
                raise usb_error(errno_mod.EPIPE)
            if self._halted:
                raise usb_error(errno_mod.EPIPE)
            self._bulk_reads += 1
            f = self.faults
            if f.stall_every and self._bulk_reads % f.stall_every == 0:
                self._halted = True
                raise usb_error(errno_mod.EPIPE)
            if f.timeout_every and self._bulk_reads % f.timeout_every == 0:
                raise usb_error(errno_mod.ETIMEDOUT)
            if self._pending is not None:
                data, self._pending = self._pending, None
            else:
                while True:
                    self.check_present()
                    if self.streaming and self.source is not None:
                        release_us = self.source.peek_release_us()
                        if release_us is not None:
                            elapsed_us = self._device_time_us()
                            if release_us <= elapsed_us:
                                break
                            wake = time.monotonic() + (release_us - elapsed_us) / 1e6
                            if not self._wait(deadline, wake):
                                raise usb_error(errno_mod.ETIMEDOUT)
                            continue
                    if not self._wait(deadline):
                        raise usb_error(errno_mod.ETIMEDOUT)
                data = self._shape_transfer(self.source.pop())
            limit = len(buff)
            if f.short_transfer_bytes:
                limit = min(limit, f.short_transfer_bytes)
            # USB semantics: a bulk read only completes early on a short packet. A device transfer made of whole
            # max-size packets does not end the read, so further released transfers keep filling the buffer.
            while (
                data
                and len(data) % MAX_PACKET_BYTES == 0
                and len(data) < limit
                and self.streaming
                and self.source is not None
                and (nxt := self.source.peek_release_us()) is not None
                and nxt <= self._device_time_us()
            ):
                more = self._shape_transfer(self.source.pop())
                if not more:
                    break  # a zero-length packet ends the read
                data = data + more
            if len(data) > limit:
                self._pending = data[limit:]  # the rest comes with the next read, like a device FIFO
                data = data[:limit]
            n = copy_into(buff, data)
            self.transfers_served += 1
            self.bytes_served += n
            if f.disconnect_after_transfers is not None and self.transfers_served >= f.disconnect_after_transfers:
                self.unplugged = True
                self._cond.notify_all()
            return n

    def _shape_transfer(self, data: bytes) -> bytes:
        """Apply the odd-length and garbage faults to a transfer just taken from the source."""
        f = self.faults
        self._transfer_count += 1
        if f.odd_length and self._transfer_count % f.odd_length == 0:
            data = data + b"\xa5"
        if f.garbage_rate > 0 and data:
            arr = np.frombuffer(data, dtype=np.uint8).copy()
            hit = self._rng.random(arr.size) < f.garbage_rate
            arr[hit] = self._rng.integers(0, 256, int(hit.sum()), dtype=np.uint8)
            data = arr.tobytes()
        return data

    def push_debug_message(self, data: bytes) -> None:
        """Queue a message the device will send on the debug endpoint 0x81 (≤ 64 bytes)."""
        with self._cond:
            self._debug.append(bytes(data[:64]))
            self._cond.notify_all()

    def intr_read(self, endpoint: int, buff: Any, timeout_ms: int) -> int:
        """Interrupt endpoint 0x81: serve queued debug messages, else time out."""
        deadline = transfer_deadline(timeout_ms)
        with self._cond:
            self.check_present()
            if endpoint != DEBUG_ENDPOINT:
                raise usb_error(errno_mod.EPIPE)
            while not self._debug:
                if not self._wait(deadline):
                    raise usb_error(errno_mod.ETIMEDOUT)
                self.check_present()
            return copy_into(buff, self._debug.pop(0))

    # --- descriptors ------------------------------------------------------------------------------
    def strings(self) -> dict[int, str]:
        """String descriptors by index (1 manufacturer, 2 product, 3 serial if any)."""
        out = {1: "iniVation", 2: "DAVIS FX3"}
        if self.serial:
            out[3] = self.serial
        return out

    def device_descriptor(self) -> Descriptor:
        """USB device descriptor (plus pyusb's bus/address/port/speed extras)."""
        return Descriptor(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0300,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=9,
            idVendor=INIVATION_VID,
            idProduct=self.product_id,
            bcdDevice=0x0000 | (self.firmware_version & 0xFF),
            iManufacturer=1,
            iProduct=2,
            iSerialNumber=3 if self.serial else 0,
            bNumConfigurations=1,
            address=self.address,
            bus=self.bus,
            port_number=1,
            port_numbers=(1,),
            speed=5,  # LIBUSB_SPEED_SUPER
        )
