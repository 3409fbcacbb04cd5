"""The emulated libusb-1.0 (tests/helpers/libusb_emu): that it behaves like libusb where the capture path depends on it,
that it counts misuse of the transfer API, and the start/read/stop stress of the capture path on it."""

from __future__ import annotations

import ctypes
import threading
import time

import pytest

from tests.helpers import libusb_emu
from davis_rig.device.camera import Davis346
from davis_rig.protocol.config import Dvs, Module, Mux, Usb
from davis_rig.usb.async_bulk import (
    LIBUSB_ERROR_NOT_FOUND,
    LIBUSB_TRANSFER_CANCELLED,
    LIBUSB_TRANSFER_COMPLETED,
    LIBUSB_TRANSFER_TIMED_OUT,
    LIBUSB_TRANSFER_TYPE_BULK,
    LIBUSB_TRANSFER_TYPE_INTERRUPT,
    LibusbAsyncApi,
    TransferCallback,
)
from davis_rig.usb.sources import TransferListSource
from davis_rig.usb.transport import UsbTransport, list_devices
from davis_rig.usb.virtual import VirtualDavis346

from tests.helpers.libusb_emu import EmuFaults, EmulatedLibusb, EmulatorUnavailable, start_stop_cycles


@pytest.fixture
def emu():
    emulated = libusb_emu.emulated_libusb_or_skip()
    emulated.remove_devices()
    emulated.reset_counters()
    yield emulated
    emulated.remove_devices()


class Transfers:
    """Raw libusb transfers on an open emulated camera: the API the ring uses, driven by hand."""

    def __init__(self, emu, device, faults=EmuFaults(), stream=True):
        emu.remove_devices()  # only this camera on the bus
        self.transport = UsbTransport.open(backend=emu.plug(device, faults))
        if stream:
            for module, param in ((Module.USB, Usb.RUN), (Module.MUX, Mux.RUN), (Module.DVS, Dvs.RUN)):
                self.transport.config_write(module, param, 1)
        self.api = self.transport.async_transfers()
        assert isinstance(self.api, LibusbAsyncApi)
        self.completed = []  # (transfer address, status, bytes, thread id)
        self._callback = TransferCallback(self._done)
        self._buffers = []

    def _done(self, pointer):
        f = pointer.contents
        self.completed.append((ctypes.addressof(f), f.status, ctypes.string_at(f.buffer, f.actual_length),
                               threading.get_ident()))

    def new(self, endpoint=0x82, size=1024, timeout_ms=0, kind=LIBUSB_TRANSFER_TYPE_BULK):
        transfer = self.api.alloc_transfer()
        buffer = (ctypes.c_ubyte * size)()
        self._buffers.append(buffer)
        f = transfer.contents
        f.dev_handle, f.endpoint, f.type, f.timeout = self.api.dev_handle, endpoint, kind, timeout_ms
        f.length, f.callback, f.buffer = size, self._callback, ctypes.addressof(buffer)
        return transfer

    def handle_until(self, count, limit_s=5.0):
        deadline = time.monotonic() + limit_s
        while len(self.completed) < count:
            assert time.monotonic() < deadline, f"only {len(self.completed)} of {count} completions"
            self.api.handle_events(10)

    def close(self):
        self.transport.close()


def test_pyusb_sees_one_davis346_with_its_descriptors(emu):
    device = VirtualDavis346(serial="EMU00001")
    backend = emu.plug(device)
    assert [(d.serial, d.product_id, d.firmware_version) for d in list_devices(backend)] == [("EMU00001", 0x841A, 6)]
    import usb.core

    dev = usb.core.find(backend=backend, idVendor=0x152A)
    endpoints = [(e.bEndpointAddress, e.bmAttributes, e.wMaxPacketSize) for e in dev[0][(0, 0)]]
    assert endpoints == [(0x82, 2, 1024), (0x81, 3, 64)]
    assert type(backend).__module__ == "_davis_rig_emulated_libusb1"  # pyusb's own libusb1 code, its own instance


def test_completions_run_in_the_thread_that_handles_events_in_submission_order(emu):
    device = VirtualDavis346(source=TransferListSource([b"first", b"second", b"third"]))
    t = Transfers(emu, device)
    for _ in range(3):
        assert t.api.submit_transfer(t.new()) == 0
    t.handle_until(3)
    assert [(status, data) for _, status, data, _ in t.completed] == [
        (LIBUSB_TRANSFER_COMPLETED, b"first"), (LIBUSB_TRANSFER_COMPLETED, b"second"),
        (LIBUSB_TRANSFER_COMPLETED, b"third"),
    ]  # fmt: skip
    assert {thread for *_, thread in t.completed} == {threading.get_ident()}
    t.close()


def test_a_cancel_of_a_completed_but_unreaped_transfer_is_not_found_and_it_comes_back_completed(emu):
    device = VirtualDavis346(source=TransferListSource([b"late data"]))
    t = Transfers(emu, device, EmuFaults(completion_delay_us=300_000))
    transfer = t.new()
    t.api.submit_transfer(transfer)
    deadline = time.monotonic() + 5
    while emu.counters()["completions"] < 1:  # the device has answered; not reapable before 300 ms
        assert time.monotonic() < deadline
        time.sleep(0.001)
    assert t.api.cancel_transfer(transfer) == LIBUSB_ERROR_NOT_FOUND
    t.handle_until(1)
    assert [(status, data) for _, status, data, _ in t.completed] == [(LIBUSB_TRANSFER_COMPLETED, b"late data")]
    t.close()


def test_cancel_completes_cancelled_or_loses_the_race_to_data(emu):
    idle = VirtualDavis346()
    t = Transfers(emu, idle)
    transfer = t.new()
    t.api.submit_transfer(transfer)
    assert t.api.cancel_transfer(transfer) == 0
    assert t.api.cancel_transfer(transfer) == LIBUSB_ERROR_NOT_FOUND  # already cancelling
    t.handle_until(1)
    assert t.completed[0][1:3] == (LIBUSB_TRANSFER_CANCELLED, b"")
    t.close()
    racing = VirtualDavis346(source=TransferListSource([b"raced"]))
    t = Transfers(emu, racing, EmuFaults(cancel_race_every=1, poll_ms=2000), stream=False)
    transfer = t.new()
    t.api.submit_transfer(transfer)
    assert t.api.cancel_transfer(transfer) == 0  # loses the race: the device polls once more for data...
    for module, param in ((Module.USB, Usb.RUN), (Module.MUX, Mux.RUN), (Module.DVS, Dvs.RUN)):
        t.transport.config_write(module, param, 1)  # ...which now comes
    t.handle_until(1)
    assert t.completed[0][1:3] == (LIBUSB_TRANSFER_COMPLETED, b"raced")
    assert emu.counters()["cancel_races"] == 1
    t.close()


def test_a_transfer_timeout_and_an_interrupt_endpoint(emu):
    device = VirtualDavis346()
    t = Transfers(emu, device)
    t.api.submit_transfer(t.new(timeout_ms=30))
    debug = t.new(endpoint=0x81, size=64, kind=LIBUSB_TRANSFER_TYPE_INTERRUPT)
    t.api.submit_transfer(debug)
    t.handle_until(1)
    assert t.completed[0][1] == LIBUSB_TRANSFER_TIMED_OUT
    device.push_debug_message(b"\x00\x01\x02\x03\x04\x05hello")
    t.handle_until(2)
    assert t.completed[1][1:3] == (LIBUSB_TRANSFER_COMPLETED, b"\x00\x01\x02\x03\x04\x05hello")
    t.close()


def test_misuse_of_the_transfer_api_is_counted(emu):
    t = Transfers(emu, VirtualDavis346())
    freed = t.new()
    t.api.free_transfer(freed)
    t.api.free_transfer(freed)
    assert t.api.cancel_transfer(freed) == LIBUSB_ERROR_NOT_FOUND
    assert t.api.submit_transfer(freed) != 0
    in_flight = t.new()
    t.api.submit_transfer(in_flight)
    assert t.api.submit_transfer(in_flight) != 0
    t.close()  # with a transfer in flight
    t.api.free_transfer(in_flight)
    assert emu.misuse() == {
        "double_free": 1, "use_after_free": 2, "submit_in_flight": 1, "close_in_flight": 1, "free_in_flight": 1,
    }  # fmt: skip
    emu.reset_counters()


def test_the_ring_and_the_camera_use_the_api_correctly(emu):
    device = VirtualDavis346(source=TransferListSource([bytes.fromhex("64800a101430")] * 30))
    with Davis346.open(backend=emu.plug(device), sleep=lambda s: None) as camera:
        camera.start()
        while not device.drained:
            camera.read(0.05)
        camera.stop()
        assert camera.reader_kind == "ring"
    counters = emu.counters()
    assert emu.misuse() == {} and emu.in_flight == 0
    assert counters["allocated"] == counters["freed"] == 8 + 4  # the data ring and the 0x81 debug transfers
    assert counters["callbacks"] == counters["submits"] == counters["completions"]


def test_without_a_compiler_the_emulation_is_unavailable_with_the_reason(monkeypatch, tmp_path):
    monkeypatch.setattr(libusb_emu.shutil, "which", lambda name: None)
    with pytest.raises(EmulatorUnavailable, match="no C compiler"):
        libusb_emu.build_library(tmp_path)


def test_a_compiler_error_is_reported(monkeypatch, tmp_path):
    broken = tmp_path / "broken.c"
    broken.write_text("this is not C\n")
    monkeypatch.setattr(libusb_emu, "SOURCE", broken)
    try:
        with pytest.raises(EmulatorUnavailable, match="failed"):
            libusb_emu.build_library(tmp_path)
    except EmulatorUnavailable as exc:  # no compiler at all: the other test covers it
        pytest.skip(str(exc))


def test_the_library_is_built_once_per_source(tmp_path):
    try:
        first = libusb_emu.build_library(tmp_path)
    except EmulatorUnavailable as exc:
        pytest.skip(str(exc))
    mtime = first.stat().st_mtime_ns
    assert libusb_emu.build_library(tmp_path) == first and first.stat().st_mtime_ns == mtime
    assert isinstance(EmulatedLibusb, type)


#: Cycles of the default suite's stress (tools/usb_stop_stress.py runs 500 per setting).
STRESS_CYCLES = 120
STRESS_FAULTS = {
    "plain": EmuFaults(),
    "late-and-racing": EmuFaults(completion_delay_us=1000, cancel_delay_us=500, cancel_race_every=3, poll_ms=1),
}


@pytest.mark.parametrize("level", ["camera", "ring"])
@pytest.mark.parametrize("faults", STRESS_FAULTS.values(), ids=STRESS_FAULTS.keys())
def test_start_read_stop_cycles_with_data_flowing(emu, level, faults):
    result = start_stop_cycles(emu, STRESS_CYCLES, level=level, faults=faults)
    assert result.exceptions == {} and result.misuse == {} and result.in_flight_after == 0
    assert result.counters["cancels"] > 0 and result.bytes > STRESS_CYCLES * 8192
    assert emu.host_errors == []
