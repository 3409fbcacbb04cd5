"""Test helper: an emulated libusb-1.0 below pyusb, playing ``VirtualDavis346`` cameras (``libusb_emu.c``).

The C part (built here with the system C compiler, cached by source hash) owns libusb's semantics: transfer
lifetimes, per-endpoint device threads that complete transfers, completions delivered in whichever thread handles
events (the ring's, another ring's, or a synchronous transfer's, as libusb does), cancels racing with completions,
late completions, and counters of misuse (use after free, double free, free or close with transfers in flight).
The device model stays the Python :class:`~davis_rig.usb.virtual.VirtualDavis346`, reached through one ctypes
callback and :class:`~davis_rig.usb.virtual.VirtualDavis346Backend`'s request handling, so every register, RUN flag,
data source and fault (``Faults``: stall, timeout, disconnect, short/odd transfers, garbage, EACCES/EBUSY) is the
same model the virtual backend serves, and tests can assert on ``dev.writes`` / ``dev.clear_halts`` either way.

pyusb's ``libusb1`` backend module is loaded as a separate module instance for the emulation (same file, unmodified
code, its own module-level library), so the real libusb-1.0 backend of the process is never replaced.

Typical use::

    emu = EmulatedLibusb.load()               # or the `emulated_libusb` fixture
    dev = VirtualDavis346(source=...)
    backend = emu.plug(dev, EmuFaults(completion_delay_us=2000))
    with Davis346.open(backend=backend) as cam: ...
    assert emu.misuse() == {}
    emu.close()
"""

from __future__ import annotations

import ctypes
import hashlib
import importlib.util
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import pytest
import usb.core

from davis_rig.usb.sources import DataSource
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

SOURCE = Path(__file__).with_name("libusb_emu.c")
#: Compiler flags of the emulated library.
CFLAGS = ("-O2", "-g", "-Wall", "-Wextra", "-shared", "-fPIC", "-pthread")
#: Counters that are misuse of libusb's API (each must stay 0).
MISUSE_COUNTERS = (
    "use_after_free",
    "unknown_transfer",
    "double_free",
    "free_in_flight",
    "submit_in_flight",
    "close_in_flight",
    "bad_handle",
    "dropped_completions",
)
LIBUSB_ERROR_NO_DEVICE = -4
LIBUSB_ERROR_OTHER = -99

# host operations (EMU_OP_* in libusb_emu.c)
OP_PRESENT, OP_OPEN, OP_CLOSE, OP_GET_CONFIG, OP_SET_CONFIG, OP_CLAIM, OP_RELEASE = range(7)
OP_CONTROL, OP_BULK_IN, OP_INTR_IN, OP_CLEAR_HALT = range(7, 11)

HostFunction = ctypes.CFUNCTYPE(
    ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int,
    ctypes.c_void_p, ctypes.c_int, ctypes.c_uint,
)  # fmt: skip


class EmulatorUnavailable(RuntimeError):
    """The emulated libusb cannot be built or loaded here (the message says why; tests skip with it)."""


@dataclass(frozen=True)
class EmuFaults:
    """libusb-level faults of one emulated device (device-model faults stay in ``VirtualDavis346.faults``).

    Attributes:
        completion_delay_us: a transfer the device has finished is reaped only this much later, µs (late
            completion: a cancel in that window gets ``LIBUSB_ERROR_NOT_FOUND`` and the transfer comes back COMPLETED).
        cancel_delay_us: a cancelled transfer comes back this much later, µs.
        cancel_race_every: every n-th cancel races with a completion: the transfer stays with the device for one
            more poll, and if data comes in it, it comes back COMPLETED with that data (0 = never).
        poll_ms: how long one device-model call may wait for data, ms (bounds how late a cancel takes effect).
    """

    completion_delay_us: int = 0
    cancel_delay_us: int = 0
    cancel_race_every: int = 0
    poll_ms: int = 10


def build_library(cache_dir: Path | None = None) -> Path:
    """Compile ``libusb_emu.c`` into a shared library, or reuse the one already built from the same source.

    Args:
        cache_dir: where built libraries are kept (default: ``<tempdir>/davis_rig_libusb_emu``); the file name
            carries a hash of the source, the compiler and the flags.

    Returns:
        Path of the shared library.

    Raises:
        EmulatorUnavailable: no C compiler, or the build failed (with the compiler's message).
    """
    compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc") or shutil.which("clang")
    if compiler is None:
        raise EmulatorUnavailable("no C compiler (cc/gcc/clang) to build the emulated libusb-1.0")
    source = SOURCE.read_bytes()
    digest = hashlib.sha256(source + compiler.encode() + " ".join(CFLAGS).encode()).hexdigest()[:16]
    cache_dir = Path(cache_dir or Path(tempfile.gettempdir()) / "davis_rig_libusb_emu")
    target = cache_dir / f"libusb-1.0-emu-{digest}.so"
    if target.exists():
        return target
    cache_dir.mkdir(parents=True, exist_ok=True)
    partial = cache_dir / f".{target.name}.{os.getpid()}.{threading.get_ident()}"
    result = subprocess.run([compiler, *CFLAGS, "-o", str(partial), str(SOURCE)], capture_output=True, text=True)
    if result.returncode != 0:
        partial.unlink(missing_ok=True)
        raise EmulatorUnavailable(f"building the emulated libusb-1.0 with {compiler} failed: {result.stderr.strip()}")
    os.replace(partial, target)  # atomic: a concurrent build of the same source writes the same bytes
    return target


def _fresh_libusb1_module():
    """pyusb's ``usb.backend.libusb1`` executed as a separate module object (its own cached library and context)."""
    import usb.backend.libusb1 as installed

    spec = importlib.util.spec_from_file_location("_davis_rig_emulated_libusb1", installed.__file__)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _error_code(exc: usb.core.USBError) -> int:
    code = getattr(exc, "backend_error_code", None)
    return int(code) if isinstance(code, int) and code < 0 else LIBUSB_ERROR_OTHER


class EmulatedLibusb:
    """The emulated libusb-1.0, loaded once per process; :meth:`plug` cameras into it.

    Use :meth:`load`. Only one instance at a time drives the library (it has one host callback).

    Attributes:
        path: the shared library.
        host_errors: exceptions raised by the device model other than USB errors (each is a test failure: the
            callback answered ``LIBUSB_ERROR_OTHER``).
    """

    _lock = threading.Lock()

    def __init__(self, path: Path):
        self.path = Path(path)
        lib = ctypes.CDLL(str(self.path))
        lib.emu_set_host.argtypes = [HostFunction]
        lib.emu_set_host.restype = None
        lib.emu_add_device.argtypes = [ctypes.c_int] * 6
        lib.emu_add_device.restype = ctypes.c_int
        lib.emu_set_faults.argtypes = [ctypes.c_int, ctypes.c_long, ctypes.c_long, ctypes.c_int, ctypes.c_int]
        lib.emu_set_faults.restype = ctypes.c_int
        lib.emu_unplug.argtypes = [ctypes.c_int]
        lib.emu_unplug.restype = None
        lib.emu_remove_all.argtypes = []
        lib.emu_remove_all.restype = ctypes.c_int
        lib.emu_in_flight.argtypes = []
        lib.emu_in_flight.restype = ctypes.c_int
        lib.emu_counter_count.restype = ctypes.c_int
        lib.emu_counter_name.argtypes = [ctypes.c_int]
        lib.emu_counter_name.restype = ctypes.c_char_p
        lib.emu_counter.argtypes = [ctypes.c_int]
        lib.emu_counter.restype = ctypes.c_longlong
        lib.emu_reset_counters.restype = None
        lib.emu_set_sync_event_handling.argtypes = [ctypes.c_int]
        lib.emu_set_sync_event_handling.restype = None
        self._lib = lib
        self._names = [lib.emu_counter_name(i).decode() for i in range(lib.emu_counter_count())]
        self._host = HostFunction(self._request)  # kept alive while the library may call it
        self._devices: dict[int, VirtualDavis346] = {}
        self._models: dict[int, VirtualDavis346Backend] = {}
        self._handles: dict[int, object] = {}
        self.host_errors: list[BaseException] = []
        self._libusb1 = _fresh_libusb1_module()
        self._backend = None
        lib.emu_set_host(self._host)
        lib.emu_reset_counters()

    @classmethod
    def load(cls, cache_dir: Path | None = None) -> "EmulatedLibusb":
        """Build (or reuse) and load the library.

        Raises:
            EmulatorUnavailable: it cannot be built or pyusb cannot load it.
        """
        instance = cls(build_library(cache_dir))
        instance.backend()
        return instance

    def backend(self):
        """pyusb's libusb1 backend (``_LibUSB``) on the emulated library."""
        if self._backend is None:
            self._backend = self._libusb1.get_backend(find_library=lambda _name: str(self.path))
            if self._backend is None:
                raise EmulatorUnavailable(f"pyusb's libusb1 backend could not load {self.path}")
        return self._backend

    # --- devices ------------------------------------------------------------------------------------
    def plug(self, device: VirtualDavis346, faults: EmuFaults = EmuFaults()):
        """Plug a camera model in; returns the pyusb backend to pass as ``backend=``.

        Args:
            device: the device model (registers, data source, device faults).
            faults: libusb-level faults of this device.
        """
        descriptor = device.device_descriptor()
        number = self._lib.emu_add_device(
            descriptor.idVendor, descriptor.idProduct, descriptor.bcdDevice, descriptor.bus, descriptor.address,
            descriptor.iSerialNumber,
        )  # fmt: skip
        if number < 0:
            raise RuntimeError("the emulated libusb has no device numbers left in this process")
        self._devices[number] = device
        self._models[number] = VirtualDavis346Backend(device)
        self.set_faults(device, faults)
        return self.backend()

    def _number(self, device: VirtualDavis346) -> int:
        return next(n for n, d in self._devices.items() if d is device)

    def set_faults(self, device: VirtualDavis346, faults: EmuFaults) -> None:
        """Change the libusb-level faults of a plugged camera (takes effect for the next transfers)."""
        self._lib.emu_set_faults(
            self._number(device), faults.completion_delay_us, faults.cancel_delay_us, faults.cancel_race_every,
            faults.poll_ms,
        )  # fmt: skip

    def unplug(self, device: VirtualDavis346) -> None:
        """Pull the cable now: the model answers ENODEV, queued transfers come back ``NO_DEVICE``."""
        device.unplug()
        self._lib.emu_unplug(self._number(device))

    def set_sync_event_handling(self, enabled: bool) -> None:
        """Whether synchronous transfers reap other transfers' completions when the event lock is free (libusb
        does; on by default)."""
        self._lib.emu_set_sync_event_handling(int(bool(enabled)))

    # --- observation --------------------------------------------------------------------------------
    def counters(self) -> dict[str, int]:
        """Every counter of the emulation (misuse, submissions, cancels, callbacks, ...)."""
        return {name: int(self._lib.emu_counter(i)) for i, name in enumerate(self._names)}

    def misuse(self) -> dict[str, int]:
        """The misuse counters that are not zero (``{}`` when the API was used correctly)."""
        counters = self.counters()
        return {name: counters[name] for name in MISUSE_COUNTERS if counters[name]}

    @property
    def in_flight(self) -> int:
        """Transfers submitted and not yet reaped."""
        return int(self._lib.emu_in_flight())

    def reset_counters(self) -> None:
        self._lib.emu_reset_counters()

    def remove_devices(self) -> int:
        """Unplug every camera and stop the device threads; returns the transfers left in flight."""
        left = int(self._lib.emu_remove_all())
        self._devices.clear()
        self._models.clear()
        self._handles.clear()
        return left

    def close(self) -> None:
        """Remove the cameras and detach the host callback (the library stays loaded in the process)."""
        self.remove_devices()
        self._lib.emu_set_sync_event_handling(1)

    # --- the host callback (any thread: device threads, event handlers, the caller's) -----------------
    def _request(self, number, op, a, b, c, d, buffer, length, timeout_ms):
        model = self._models.get(number)
        if model is None:
            return LIBUSB_ERROR_NO_DEVICE
        device = model.devices[0]
        try:
            if op == OP_PRESENT:
                return 0 if device.unplugged else 1
            if op == OP_OPEN:
                self._handles[a] = model.open_device(device)
                return 0
            handle = self._handles.get(a)
            if handle is None:
                return LIBUSB_ERROR_NO_DEVICE
            if op == OP_CLOSE:
                model.close_device(self._handles.pop(a))
                return 0
            if op == OP_GET_CONFIG:
                return model.get_configuration(handle)
            if op == OP_SET_CONFIG:
                model.set_configuration(handle, b)
                return 0
            if op == OP_CLAIM:
                model.claim_interface(handle, b)
                return 0
            if op == OP_RELEASE:
                model.release_interface(handle, b)
                return 0
            if op == OP_CLEAR_HALT:
                model.clear_halt(handle, b)
                return 0
            data = (ctypes.c_ubyte * length).from_address(buffer) if length > 0 else (ctypes.c_ubyte * 0)()
            if op == OP_CONTROL:
                return int(model.ctrl_transfer(handle, b & 0xFF, b >> 8, c, d, data, timeout_ms))
            if op == OP_BULK_IN:
                return int(model.bulk_read(handle, b, 0, data, timeout_ms))
            if op == OP_INTR_IN:
                return int(model.intr_read(handle, b, 0, data, timeout_ms))
        except usb.core.USBError as exc:
            return _error_code(exc)
        except BaseException as exc:  # a model bug must not unwind into C
            self.host_errors.append(exc)
            return LIBUSB_ERROR_OTHER
        self.host_errors.append(ValueError(f"unknown emulator operation {op}"))
        return LIBUSB_ERROR_OTHER


_loaded: EmulatedLibusb | None = None


#: Set (to anything but "" or "0") where the emulation must run, e.g. in CI: then it failing to build fails the test.
REQUIRE_VARIABLE = "DAVIS_RIG_REQUIRE_LIBUSB_EMU"


def emulated_libusb_or_skip() -> EmulatedLibusb:
    """The process's :class:`EmulatedLibusb` (loaded on first use), or ``pytest.skip`` with the reason
    (``pytest.fail`` when :data:`REQUIRE_VARIABLE` is set)."""
    global _loaded
    if _loaded is None:
        try:
            _loaded = EmulatedLibusb.load()
        except EmulatorUnavailable as exc:
            if os.environ.get(REQUIRE_VARIABLE, "") not in ("", "0"):
                pytest.fail(f"{exc} ({REQUIRE_VARIABLE} is set)")
            pytest.skip(str(exc))
    return _loaded


class UsbBackends:
    """What the ``usb_backend`` fixture gives a test: ``plug(device)`` → a pyusb backend serving that camera model.

    Attributes:
        kind: ``"virtual"`` (:class:`VirtualDavis346Backend`) or ``"libusb-emu"`` (pyusb's libusb1 backend on the
            emulated libusb-1.0).
        emu: the :class:`EmulatedLibusb` (``None`` for ``"virtual"``).
    """

    def __init__(self, kind: str, emu: EmulatedLibusb | None):
        self.kind = kind
        self.emu = emu
        self.left_in_flight = 0

    def plug(self, device: VirtualDavis346, faults: EmuFaults = EmuFaults()):
        """A backend with only ``device`` on its bus (cameras plugged before are removed; ``faults`` apply to the
        emulated libusb only)."""
        if self.emu is None:
            return VirtualDavis346Backend(device)
        self.left_in_flight += self.emu.remove_devices()
        return self.emu.plug(device, faults)


def _backends(kind: str):
    """Set-up and teardown of the ``usb_backend`` fixtures (a generator yielding :class:`UsbBackends`)."""
    if kind == "virtual":
        yield UsbBackends("virtual", None)
        return
    emu = emulated_libusb_or_skip()
    emu.remove_devices()
    emu.reset_counters()
    errors_before = len(emu.host_errors)
    backends = UsbBackends("libusb-emu", emu)
    yield backends
    left = backends.left_in_flight + emu.remove_devices()
    assert emu.host_errors[errors_before:] == [], "the device model raised inside the emulated libusb"
    assert emu.misuse() == {}, f"libusb API misuse: {emu.misuse()}"
    assert left == 0, f"{left} transfers were still in flight after the test"


@pytest.fixture(params=["virtual", "libusb-emu"])
def usb_backend(request):
    """Fixture (import it into a test module): the test runs on the virtual backend and on the emulated libusb-1.0;
    on the latter it fails if libusb's API was misused or transfers were left in flight."""
    yield from _backends(request.param)


@pytest.fixture
def emulated_usb_backend():
    """Fixture: like ``usb_backend``, on the emulated libusb-1.0 only (skipped, with the reason, where it cannot be
    built)."""
    yield from _backends("libusb-emu")


# --- start/read/stop stress (tests/usb/test_libusb_emulation.py, tools/usb_stop_stress.py) ---------------------------
class EndlessSource(DataSource):
    """A device data source that never runs dry: the same transfer again and again, one per ``interval_us`` of
    device streaming time (0 = all at once).

    Args:
        transfer: the bytes of every device transfer.
        interval_us: device time between two transfers, µs.
    """

    def __init__(self, transfer: bytes, interval_us: float = 0.0):
        super().__init__()
        self._transfer = bytes(transfer)
        self._interval_us = float(interval_us)
        self._served = 0

    def peek_release_us(self) -> float:
        return self._served * self._interval_us

    def pop(self) -> bytes:
        self._served += 1
        return self._transfer

    def __len__(self) -> int:
        return 1


#: One 8 KiB device transfer of DVS events (timestamp word, row, column+polarity words) for the stress runs.
STRESS_TRANSFER = bytes.fromhex("64800a101430") * 1365 + bytes.fromhex("6480")
#: Device time between two stress transfers, µs: 8 KiB per 250 µs = 33 MB/s, about the DAVIS346's peak data rate.
STRESS_INTERVAL_US = 250.0


@dataclass
class StressResult:
    """What :func:`start_stop_cycles` saw.

    Attributes:
        cycles: start/read/stop cycles run.
        exceptions: ``"Type: message"`` → how many cycles raised it.
        misuse: the emulation's misuse counters that are not zero.
        counters: every counter of the emulation after the run.
        in_flight_after: transfers still in flight after the camera was closed.
        bytes: bytes the consumer received.
        seconds: wall-clock time of the cycles, s.
    """

    cycles: int
    exceptions: Counter
    misuse: dict
    counters: dict
    in_flight_after: int
    bytes: int
    seconds: float

    @property
    def failed_cycles(self) -> int:
        return sum(self.exceptions.values())


def start_stop_cycles(
    emu: EmulatedLibusb,
    cycles: int,
    *,
    level: str = "camera",
    faults: EmuFaults = EmuFaults(),
    reads_per_cycle: int = 3,
    interval_us: float = STRESS_INTERVAL_US,
) -> StressResult:
    """Run ``cycles`` start / read / stop cycles on one emulated camera with data flowing, counting what goes wrong.

    Args:
        emu: the emulated libusb (counters are reset first).
        cycles: number of cycles.
        level: ``"camera"``: ``Davis346.start()`` / ``read()`` / ``stop()`` (the stop sequence runs before the ring
            stops, as libcaer does); ``"ring"``: ``RingReader.start()`` / ``get()`` / ``stop()`` on a device that keeps
            streaming, so transfers complete with data while the ring stops.
        faults: libusb-level faults of the device.
        reads_per_cycle: transfers (ring) or chunks (camera) read before each stop.
        interval_us: device time between two 8 KiB device transfers, µs (0: as fast as they are taken).
    """
    from davis_rig.device.camera import Davis346
    from davis_rig.device.reader import RingReader
    from davis_rig.protocol.config import Dvs, Module, Mux, Usb
    from davis_rig.usb.transport import UsbTransport

    if level not in ("camera", "ring"):
        raise ValueError(f"level must be 'camera' or 'ring', got {level!r}")
    emu.remove_devices()
    emu.reset_counters()
    device = VirtualDavis346(source=EndlessSource(STRESS_TRANSFER, interval_us))
    backend = emu.plug(device, faults)
    exceptions: Counter = Counter()
    received = 0
    start = time.monotonic()
    if level == "camera":
        with Davis346.open(backend=backend, sleep=lambda seconds: None) as camera:
            camera.send_default_config()
            for _ in range(cycles):
                try:
                    camera.start()
                    for _ in range(reads_per_cycle):
                        camera.read(5.0)
                    camera.stop()
                    while camera.read(1.0) is not None:  # what arrived while stopping
                        pass
                except Exception as exc:  # counted: the point of the run
                    exceptions[f"{type(exc).__name__}: {exc}"] += 1
                    camera.stop()
                received += camera.stats.bytes
    else:
        with UsbTransport.open(backend=backend) as transport:
            for module, param in ((Module.USB, Usb.RUN), (Module.MUX, Mux.RUN), (Module.DVS, Dvs.RUN)):
                transport.config_write(module, param, 1)
            for _ in range(cycles):
                reader = RingReader(transport.async_transfers(), transport.clear_halt)
                try:
                    reader.start()
                    for _ in range(reads_per_cycle):
                        received += len(reader.get(5.0) or b"")
                    reader.stop()
                    while (data := reader.get(1.0)) is not None:  # what arrived while stopping
                        received += len(data)
                except Exception as exc:
                    exceptions[f"{type(exc).__name__}: {exc}"] += 1
                    reader.stop()
    seconds = time.monotonic() - start
    in_flight = emu.in_flight
    emu.remove_devices()
    return StressResult(cycles, exceptions, emu.misuse(), emu.counters(), in_flight, received, seconds)
