"""USB transport to a DAVIS camera over pyusb: discovery, open/claim, version gates, vendor requests, bulk reads.

This module and :mod:`davis_rig.usb.virtual` are the only places that import ``usb``. Every function takes a
``backend`` (any ``usb.backend.IBackend``; ``None`` = pyusb's default libusb-1.0 backend), so the exact same
code path runs against a real camera and against :class:`~davis_rig.usb.virtual.VirtualDavis346Backend`.

What goes over the wire (PROTOCOL.md §1-§3): devices are matched by VID 0x152A and PID 0x841A (FX3, DAVIS346)
or 0x841B (FX2); opening makes sure configuration 1 is active, claims interface 0, checks the firmware version
(bcdDevice low byte), the FPGA logic version (SYSINFO 0, exactly 18) and patch level (SYSINFO 7, >= 1).
Registers are read/written with vendor request 0xBF (4-byte big-endian values), several at once with 0xC2.
Data arrives on bulk endpoint 0x82.

pyusb errors are mapped onto :mod:`davis_rig.errors`: EACCES → :class:`DevicePermissionError` (with the udev
rule to install), EBUSY → :class:`DeviceBusyError`, ENODEV (and EPIPE/EIO once the device is gone) →
:class:`DeviceDisconnectedError`, anything else → :class:`TransportError`. A bulk read that times out is not an
error: :meth:`UsbTransport.read_data` returns ``None``.
"""

from __future__ import annotations

import errno as errno_mod
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import usb.core
import usb.util

from davis_rig.errors import (
    DavisRigError,
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceVersionError,
    MissingDependencyError,
    TransportError,
)
from davis_rig.protocol.config import (
    DATA_ENDPOINT,
    DEBUG_ENDPOINT,
    DAVIS_FX2_PID,
    DAVIS_FX3_PID,
    INIVATION_VID,
    REQUEST_TYPE_VENDOR_IN,
    REQUEST_TYPE_VENDOR_OUT,
    REQUIRED_FIRMWARE_VERSION,
    REQUIRED_LOGIC_PATCH,
    REQUIRED_LOGIC_VERSION,
    USB_CONFIGURATION,
    USB_INTERFACE,
    VR_FPGA_CONFIG,
    VR_FPGA_CONFIG_MULTIPLE,
    ConfigWrite,
    SysInfo,
    decode_value,
    encode_multiple,
    encode_value,
)
from davis_rig.usb.async_bulk import AsyncTransferApi, LibusbAsyncApi

#: Product ids this driver accepts, in libcaer's matching order for "any DAVIS" (FX2 first, then FX3).
DAVIS_PIDS = (DAVIS_FX2_PID, DAVIS_FX3_PID)
#: Size of one FX3 debug-endpoint transfer, bytes (libcaer uses 4 × 64-byte interrupt transfers).
DEBUG_MESSAGE_BYTES = 64
#: Control transfer timeout, ms.
CONTROL_TIMEOUT_MS = 1000
#: Where the udev rule lives in the repository, and how to install it (shown in permission errors).
UDEV_RULE_PATH = "firmware_notes/65-inivation.rules"
UDEV_INSTALL_HINT = (
    f"install the udev rule shipped in {UDEV_RULE_PATH}: "
    f"`sudo cp {UDEV_RULE_PATH} /etc/udev/rules.d/ && sudo udevadm control --reload-rules && "
    "sudo udevadm trigger`, then unplug and re-plug the camera (see firmware_notes/README.md)"
)


def temporary_serial(bus: int | None, address: int | None) -> str:
    """libcaer's made-up serial for a device without a serial string: ``TMP%05u`` of ``(bus << 8) | address``."""
    return "TMP%05u" % ((((bus or 0) & 0xFF) << 8) | ((address or 0) & 0xFF))


def map_usb_error(exc: usb.core.USBError, action: str) -> DavisRigError:
    """Translate a pyusb error into the package's error tree.

    Args:
        exc: the pyusb exception (``errno`` and ``backend_error_code`` are kept).
        action: what was being done, for the message (e.g. ``"claim interface 0 of DAVIS 00000123"``).

    Returns:
        The error to raise (``raise map_usb_error(e, ...) from e``).
    """
    code = getattr(exc, "backend_error_code", None)
    err = getattr(exc, "errno", None)
    text = getattr(exc, "strerror", None) or str(exc)
    if isinstance(exc, usb.core.USBTimeoutError) or err == errno_mod.ETIMEDOUT:
        return TransportError(f"{action}: timed out ({text})", code)
    if err == errno_mod.EACCES:
        return DevicePermissionError(f"{action}: permission denied ({text}); {UDEV_INSTALL_HINT}")
    if err == errno_mod.EBUSY:
        return DeviceBusyError(
            f"{action}: the camera is busy ({text}); another process (DV, jAER, another davis_rig) holds interface 0"
        )
    if err == errno_mod.ENODEV:
        return DeviceDisconnectedError(f"{action}: the camera was disconnected ({text})", code)
    return TransportError(f"{action}: USB error ({text})", code)


@dataclass(frozen=True)
class UsbDeviceEntry:
    """One DAVIS camera seen on the bus during discovery (the interface is not claimed).

    Attributes:
        serial: serial string (≤ 8 ASCII chars), ``TMPnnnnn`` if the device has none, or ``None`` if it could
            not be read (see ``error``).
        product_id: 0x841A (FX3) or 0x841B (FX2).
        firmware_version: bcdDevice low byte.
        bus: USB bus number, or ``None`` if the backend does not say.
        address: USB device address, or ``None``.
        error: why the device could not be opened to read its serial (e.g. permission denied), else ``None``.
    """

    serial: str | None
    product_id: int
    firmware_version: int
    bus: int | None
    address: int | None
    error: str | None = None


def _find_raw(backend: Any) -> list[usb.core.Device]:
    try:
        found = usb.core.find(
            find_all=True,
            backend=backend,
            idVendor=INIVATION_VID,
            custom_match=lambda d: d.idProduct in DAVIS_PIDS,
        )
        return list(found)
    except usb.core.NoBackendError as exc:
        raise MissingDependencyError(
            "no USB backend available: install libusb-1.0 (e.g. `sudo apt install libusb-1.0-0`) "
            "or pass backend= explicitly"
        ) from exc
    except usb.core.USBError as exc:
        raise map_usb_error(exc, "enumerate USB devices") from exc


def _read_serial(dev: usb.core.Device) -> str:
    if not dev.iSerialNumber:
        return temporary_serial(dev.bus, dev.address)
    try:
        serial = dev.serial_number
    except ValueError as exc:
        # pyusb reports "no langid" when the string descriptors cannot be read: almost always permissions.
        raise DevicePermissionError(
            f"cannot read the serial number of DAVIS at bus {dev.bus} address {dev.address} ({exc}); "
            f"{UDEV_INSTALL_HINT}"
        ) from exc
    except usb.core.USBError as exc:
        raise map_usb_error(exc, f"read serial number of DAVIS at bus {dev.bus} address {dev.address}") from exc
    finally:
        usb.util.dispose_resources(dev)
    if not serial:
        return temporary_serial(dev.bus, dev.address)
    return serial[:8]


def list_devices(backend: Any = None) -> list[UsbDeviceEntry]:
    """Discover attached DAVIS cameras (PID 0x841A and 0x841B) without claiming them.

    Args:
        backend: pyusb backend; ``None`` = libusb-1.0.

    Returns:
        One entry per camera, in bus order. Cameras whose serial cannot be read are listed with ``error`` set.

    Raises:
        MissingDependencyError: no libusb backend is available.
    """
    entries = []
    for dev in _find_raw(backend):
        serial, error = None, None
        try:
            serial = _read_serial(dev)
        except DavisRigError as exc:
            error = str(exc)
        entries.append(
            UsbDeviceEntry(
                serial=serial,
                product_id=int(dev.idProduct),
                firmware_version=int(dev.bcdDevice) & 0xFF,
                bus=dev.bus,
                address=dev.address,
                error=error,
            )
        )
    return entries


class UsbTransport:
    """An opened, claimed and version-checked DAVIS camera (context manager).

    Use :meth:`open`; the constructor only stores its arguments. Thread-safety: register access and
    :meth:`read_data` may be called from different threads (libusb and pyusb's resource manager allow it).

    Attributes:
        device: the pyusb device.
        serial: serial string (or ``TMPnnnnn``).
        product_id: 0x841A / 0x841B.
        firmware_version: bcdDevice low byte.
        logic_version: SYSINFO 0.
        logic_patch: SYSINFO 7.
        stalls: number of bulk-endpoint stalls cleared so far.
    """

    def __init__(
        self,
        device: usb.core.Device,
        serial: str,
        firmware_version: int,
        logic_version: int,
        logic_patch: int,
    ):
        self.device = device
        self.serial = serial
        self.product_id = int(device.idProduct)
        self.firmware_version = firmware_version
        self.logic_version = logic_version
        self.logic_patch = logic_patch
        self.stalls = 0
        self._closed = False
        self._gone = False
        self._buffer = None

    # --- opening ----------------------------------------------------------------------------------
    @classmethod
    def open(cls, serial: str | None = None, backend: Any = None) -> "UsbTransport":
        """Find, open, claim and version-check a DAVIS camera.

        Args:
            serial: serial number to open; ``None`` = the first camera that opens.
            backend: pyusb backend; ``None`` = libusb-1.0.

        Returns:
            The open transport (close it, or use it as a context manager).

        Raises:
            DeviceNotFoundError: no DAVIS attached, or none with this serial.
            DevicePermissionError: the OS denied access (message names the udev rule to install).
            DeviceBusyError: another process claimed the camera.
            DeviceVersionError: firmware, logic version or patch outside what this driver supports.
            DeviceDisconnectedError / TransportError: the camera vanished or USB failed while opening.
        """
        devices = _find_raw(backend)
        if not devices:
            raise DeviceNotFoundError(
                f"no DAVIS camera found (looked for USB {INIVATION_VID:04x}:{DAVIS_FX3_PID:04x} and "
                f"{INIVATION_VID:04x}:{DAVIS_FX2_PID:04x})"
            )
        failures: list[DavisRigError] = []
        seen: list[str] = []
        for dev in devices:
            try:
                dev_serial = _read_serial(dev)
            except DavisRigError as exc:
                failures.append(exc)
                continue
            seen.append(dev_serial)
            if serial is not None and dev_serial != serial:
                continue
            try:
                return cls._open_device(dev, dev_serial)
            except DavisRigError as exc:
                if serial is not None:
                    raise
                failures.append(exc)
        if serial is not None and serial not in seen:
            if failures:
                raise failures[0]
            raise DeviceNotFoundError(f"no DAVIS camera with serial {serial!r}; found serials {seen}")
        raise failures[0]

    @classmethod
    def _open_device(cls, dev: usb.core.Device, serial: str) -> "UsbTransport":
        what = f"DAVIS {serial}"
        pid = int(dev.idProduct)
        firmware = int(dev.bcdDevice) & 0xFF
        required_fw = REQUIRED_FIRMWARE_VERSION[pid]
        if firmware < required_fw:
            raise DeviceVersionError(
                f"{what}: firmware version {firmware} is too old, expected >= {required_fw} "
                f"(update the firmware with DV/flashy)"
            )
        try:
            try:
                active = dev.get_active_configuration().bConfigurationValue
            except usb.core.USBError as exc:
                if exc.errno is not None:
                    raise
                active = None  # "Configuration not set"
            if active != USB_CONFIGURATION:
                dev.set_configuration(USB_CONFIGURATION)
            usb.util.claim_interface(dev, USB_INTERFACE)
        except usb.core.USBError as exc:
            usb.util.dispose_resources(dev)
            raise map_usb_error(exc, f"open {what}") from exc
        transport = cls(dev, serial, firmware, logic_version=-1, logic_patch=-1)
        try:
            transport.logic_version = transport.config_read(6, SysInfo.LOGIC_VERSION)
            transport.logic_patch = transport.config_read(6, SysInfo.LOGIC_PATCH)
            if transport.logic_version != REQUIRED_LOGIC_VERSION:
                raise DeviceVersionError(
                    f"{what}: FPGA logic version {transport.logic_version} is not supported, expected exactly "
                    f"{REQUIRED_LOGIC_VERSION} (update the logic with DV/flashy)"
                )
            if transport.logic_patch < REQUIRED_LOGIC_PATCH:
                raise DeviceVersionError(
                    f"{what}: FPGA logic patch level {transport.logic_patch} is too old, expected >= "
                    f"{REQUIRED_LOGIC_PATCH}"
                )
        except BaseException:
            transport.close()
            raise
        return transport

    # --- register access --------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"DAVIS {self.serial}: transport is closed")
        if self._gone:
            raise DeviceDisconnectedError(f"DAVIS {self.serial}: the camera was disconnected")

    def _ctrl(self, action: str, *args: Any) -> Any:
        self._check_open()
        try:
            return self.device.ctrl_transfer(*args, timeout=CONTROL_TIMEOUT_MS)
        except usb.core.USBError as exc:
            err = map_usb_error(exc, f"DAVIS {self.serial}: {action}")
            if isinstance(err, DeviceDisconnectedError):
                self._gone = True
            raise err from exc

    def config_read(self, module: int, param: int) -> int:
        """Read one FPGA register (``0xC0/0xBF``, 4 bytes big-endian).

        Args:
            module: module address (``wValue``).
            param: parameter address (``wIndex``).

        Returns:
            The unsigned 32-bit value.

        Raises:
            TransportError: USB failure or a reply that is not exactly 4 bytes.
            DeviceDisconnectedError: the camera is gone.
        """
        reply = self._ctrl(
            f"read config ({module}, {param})", REQUEST_TYPE_VENDOR_IN, VR_FPGA_CONFIG, int(module), int(param), 4
        )
        data = bytes(reply)
        if len(data) != 4:
            raise TransportError(f"DAVIS {self.serial}: config read ({module}, {param}) returned {len(data)} bytes, expected 4")
        return decode_value(data)

    def config_read_u64(self, module: int, param: int) -> int:
        """Read a 64-bit statistics counter as libcaer does: upper word at ``param``, lower at ``param + 1``,
        upper re-read to detect a carry between the two reads (then the lower word is read again).

        Returns:
            The unsigned 64-bit value.

        Raises:
            TransportError / DeviceDisconnectedError: USB failure.
        """
        upper = self.config_read(module, param)
        lower = self.config_read(module, param + 1)
        upper_again = self.config_read(module, param)
        if upper_again != upper:
            lower = self.config_read(module, param + 1)
        return (upper_again << 32) | lower

    def config_write(self, module: int, param: int, value: int) -> None:
        """Write one FPGA register (``0x40/0xBF``, value as 4 bytes big-endian).

        Raises:
            ProtocolError: value does not fit in 32 bits.
            TransportError / DeviceDisconnectedError: USB failure.
        """
        data = encode_value(value)
        self._ctrl(
            f"write config ({module}, {param}) = {int(value)}",
            REQUEST_TYPE_VENDOR_OUT,
            VR_FPGA_CONFIG,
            int(module),
            int(param),
            data,
        )

    def config_write_multiple(self, writes: Sequence[ConfigWrite]) -> None:
        """Write several registers in one ``0x40/0xC2`` request (``wValue`` = number of records).

        Raises:
            ProtocolError: a record does not fit the 6-byte format, or no records.
            TransportError / DeviceDisconnectedError: USB failure.
        """
        writes = list(writes)
        data = encode_multiple(writes)
        self._ctrl(
            f"write {len(writes)} config records", REQUEST_TYPE_VENDOR_OUT, VR_FPGA_CONFIG_MULTIPLE, len(writes), 0, data
        )

    # --- data endpoint ----------------------------------------------------------------------------
    def clear_halt(self, endpoint: int = DATA_ENDPOINT) -> None:
        """``CLEAR_FEATURE(ENDPOINT_HALT)`` on ``endpoint`` (libcaer does it before streaming).

        Raises:
            TransportError / DeviceDisconnectedError: USB failure.
        """
        self._check_open()
        try:
            self.device.clear_halt(endpoint)
        except usb.core.USBError as exc:
            err = map_usb_error(exc, f"DAVIS {self.serial}: clear halt on 0x{endpoint:02x}")
            if isinstance(err, DeviceDisconnectedError):
                self._gone = True
            raise err from exc

    def read_data(self, size: int, timeout_ms: int) -> bytes | None:
        """One synchronous bulk read on endpoint 0x82.

        Args:
            size: buffer size, bytes (use a multiple of 8192; the device ends a transfer with a short packet).
            timeout_ms: how long to wait for data, ms (0 = forever).

        Returns:
            The bytes received (one or more device transfers; ``b""`` for a zero-length transfer), or ``None`` if
            the read timed out or the endpoint stalled (the stall is cleared and counted in :attr:`stalls`).

        Raises:
            DeviceDisconnectedError: the camera vanished (ENODEV, or EPIPE/EIO with the stall not clearable).
            TransportError: any other USB failure.
        """
        self._check_open()
        if self._buffer is None or len(self._buffer) != size:
            self._buffer = usb.util.create_buffer(size)  # reused: pyusb would allocate one per read
        try:
            n = self.device.read(DATA_ENDPOINT, self._buffer, timeout_ms)
        except usb.core.USBTimeoutError:
            return None
        except usb.core.USBError as exc:
            if exc.errno in (errno_mod.EPIPE, errno_mod.EIO):
                # A stall on a live device is cleared; on a vanished device clearing fails with ENODEV/EPIPE.
                try:
                    self.device.clear_halt(DATA_ENDPOINT)
                except usb.core.USBError as exc2:
                    self._gone = True
                    raise DeviceDisconnectedError(
                        f"DAVIS {self.serial}: bulk read failed ({exc.strerror}) and the endpoint could not be "
                        f"recovered ({exc2.strerror}); the camera was disconnected",
                        getattr(exc, "backend_error_code", None),
                    ) from exc
                self.stalls += 1
                return None
            err = map_usb_error(exc, f"DAVIS {self.serial}: bulk read on 0x{DATA_ENDPOINT:02x}")
            if isinstance(err, DeviceDisconnectedError):
                self._gone = True
            raise err from exc
        return memoryview(self._buffer)[:n].tobytes()

    def async_transfers(self) -> AsyncTransferApi | None:
        """libusb's asynchronous transfer API on this device, for a ring of bulk transfers in flight.

        Returns:
            :class:`~davis_rig.usb.async_bulk.LibusbAsyncApi` when pyusb opened the camera through libusb-1.0, the
            virtual camera's API for a :class:`~davis_rig.usb.virtual.VirtualDavis346Backend`, else ``None``
            (other pyusb backends only have synchronous reads: use :meth:`read_data`).
        """
        self._check_open()
        backend = self.device.backend
        handle = self.device._ctx.handle  # pyusb's open handle (interface 0 is claimed)
        virtual_api = getattr(backend, "async_transfers", None)
        if callable(virtual_api):
            return virtual_api(handle)
        # pyusb's libusb1 backend (``usb.backend.libusb1._LibUSB``): the libusb-1.0 library it loaded, its context
        lib = getattr(backend, "lib", None)
        library_path = getattr(lib, "_name", None)
        context = getattr(backend, "ctx", None)
        if handle is None or not library_path or context is None or not hasattr(lib, "libusb_submit_transfer"):
            return None
        return LibusbAsyncApi(library_path, context.value, handle.handle.value)

    def read_debug(self, timeout_ms: int) -> bytes | None:
        """One interrupt read on the FX3 debug endpoint 0x81 (≤ 64 bytes).

        Args:
            timeout_ms: how long to wait, ms.

        Returns:
            The message bytes, or ``None`` if none arrived in time.

        Raises:
            DeviceDisconnectedError: the camera vanished.
            TransportError: any other USB failure (FX2 devices have no such endpoint).
        """
        self._check_open()
        try:
            data = self.device.read(DEBUG_ENDPOINT, DEBUG_MESSAGE_BYTES, timeout_ms)
        except usb.core.USBTimeoutError:
            return None
        except usb.core.USBError as exc:
            err = map_usb_error(exc, f"DAVIS {self.serial}: interrupt read on 0x{DEBUG_ENDPOINT:02x}")
            if isinstance(err, DeviceDisconnectedError):
                self._gone = True
            raise err from exc
        return data.tobytes()

    @property
    def disconnected(self) -> bool:
        """True once an operation found the camera gone."""
        return self._gone

    # --- closing ----------------------------------------------------------------------------------
    def close(self) -> None:
        """Release interface 0 and the device handle (idempotent; never raises for a vanished camera)."""
        if self._closed:
            return
        self._closed = True
        try:
            usb.util.release_interface(self.device, USB_INTERFACE)
        except usb.core.USBError:
            pass  # the device may be gone already; the handle is freed below either way
        usb.util.dispose_resources(self.device)

    def __enter__(self) -> "UsbTransport":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def run_config_steps(transport: UsbTransport, steps: Iterable[Any], sleep: Any) -> None:
    """Execute a :mod:`davis_rig.protocol.sequences` step list on a transport.

    Args:
        transport: the open camera.
        steps: ``ConfigWrite`` / ``MultipleWrite`` / ``Sleep`` / ``ClearHalt`` steps.
        sleep: ``sleep(seconds)`` callable (``time.sleep``; tests inject a recorder).
    """
    from davis_rig.protocol.sequences import ClearHalt, MultipleWrite, Sleep

    for step in steps:
        if isinstance(step, Sleep):
            sleep(step.duration_us / 1e6)
        elif isinstance(step, ClearHalt):
            transport.clear_halt(step.endpoint)
        elif isinstance(step, MultipleWrite):
            transport.config_write_multiple(step.writes)
        else:
            transport.config_write(step.module, step.param, step.value)
