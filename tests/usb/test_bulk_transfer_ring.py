"""BulkTransferRing: transfers in flight, order, resubmission, cancel on stop, stall recovery, errors, libusb ABI.

The same behaviours twice: on a scripted API (exact statuses), and on a device — the virtual backend's API and
pyusb's libusb1 backend on the emulated libusb-1.0 (``usb_backend`` fixture, which also fails a test that misuses
libusb's transfer API or leaves transfers in flight).
"""

import ctypes
import ctypes.util
import errno
import sys
import threading
import time

import pytest

from davis_rig.errors import DeviceDisconnectedError, TransportError
from davis_rig.protocol.config import Dvs, Module, Mux, Usb
from davis_rig.usb.async_bulk import (
    LIBUSB_ERROR_NO_DEVICE,
    LIBUSB_ERROR_NOT_FOUND,
    LIBUSB_TRANSFER_CANCELLED,
    LIBUSB_TRANSFER_COMPLETED,
    LIBUSB_TRANSFER_NO_DEVICE,
    LIBUSB_TRANSFER_OVERFLOW,
    LIBUSB_TRANSFER_STALL,
    LIBUSB_TRANSFER_TYPE_BULK,
    BulkTransferRing,
    LibusbAsyncApi,
    LibusbTransfer,
)
from davis_rig.usb.sources import Faults, TransferListSource
from davis_rig.usb.transport import UsbTransport
from davis_rig.usb.virtual import VirtualDavis346, usb_error

from tests.helpers.libusb_emu import (  # noqa: F401  (usb_backend, emulated_usb_backend: fixtures)
    STRESS_TRANSFER,
    EmuFaults,
    EndlessSource,
    emulated_usb_backend,
    usb_backend,
)


class ScriptedApi:
    """libusb's asynchronous API completing transfers in submission order from a script.

    Each script item is ``(status, bytes)`` for the oldest transfer in flight; a cancelled transfer comes back with
    ``CANCELLED`` and ``partial_on_cancel`` bytes. Counts submissions, cancels, frees and the most in flight.
    """

    dev_handle = 0x1234

    def __init__(self, script, partial_on_cancel=b"", fail_submit_at=None):
        self.script = list(script)
        self.partial_on_cancel = partial_on_cancel
        self.fail_submit_at = fail_submit_at
        self.queue = []
        self.cancelled = set()
        self.submits = self.cancels = self.frees = self.max_in_flight = 0
        self.fields_seen = []
        self.lock = threading.Lock()

    def alloc_transfer(self):
        return ctypes.pointer(LibusbTransfer())

    def free_transfer(self, transfer):
        self.frees += 1

    def submit_transfer(self, transfer):
        with self.lock:
            self.submits += 1
            if self.fail_submit_at is not None and self.submits == self.fail_submit_at:
                return LIBUSB_ERROR_NO_DEVICE
            f = transfer.contents
            self.fields_seen.append((f.dev_handle, f.endpoint, f.type, f.timeout, f.length, f.num_iso_packets))
            self.queue.append(transfer)
            self.max_in_flight = max(self.max_in_flight, len(self.queue))
        return 0

    def cancel_transfer(self, transfer):
        with self.lock:
            key = ctypes.addressof(transfer.contents)
            if key in self.cancelled or key not in [ctypes.addressof(t.contents) for t in self.queue]:
                return LIBUSB_ERROR_NOT_FOUND  # libusb: not in flight, or already cancelled
            self.cancels += 1
            self.cancelled.add(key)
        return 0

    def handle_events(self, timeout_ms):
        with self.lock:
            head = self.queue[0] if self.queue else None
            if head is not None and ctypes.addressof(head.contents) in self.cancelled:
                status, data = LIBUSB_TRANSFER_CANCELLED, self.partial_on_cancel
            elif head is not None and self.script:
                status, data = self.script.pop(0)
            else:
                head = None
            if head is not None:
                self.queue.pop(0)
                self.cancelled.discard(ctypes.addressof(head.contents))
        if head is None:
            time.sleep(0.001)
            return 0
        f = head.contents
        ctypes.memmove(f.buffer, data, len(data))
        f.status, f.actual_length = status, len(data)
        f.callback(head)
        return 0


class Collector:
    def __init__(self):
        self.data = []
        self.ends = []
        self.ended = threading.Event()
        self.halts = 0

    def on_data(self, data):
        self.data.append(data)

    def on_end(self, error):
        self.ends.append(error)
        self.ended.set()

    def clear_halt(self):
        self.halts += 1


def make_ring(api, sink, **kwargs):
    kwargs.setdefault("transfers", 4)
    kwargs.setdefault("transfer_bytes", 64)
    return BulkTransferRing(api, 0x82, sink.on_data, sink.on_end, sink.clear_halt, describe="DAVIS test", **kwargs)


def wait_for(condition, limit_s=5.0):
    deadline = time.monotonic() + limit_s
    while not condition():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.002)


def ok(data):
    return (LIBUSB_TRANSFER_COMPLETED, data)


@pytest.mark.skipif(ctypes.sizeof(ctypes.c_void_p) != 8 or sys.platform == "win32", reason="offsets are for LP64")
def test_transfer_struct_matches_libusb_h_on_lp64():
    # struct libusb_transfer (libusb.h): pointer, 3 × uint8, unsigned int, 3 × int, 3 pointers, int
    offsets = {name: getattr(LibusbTransfer, name).offset for name, _ in LibusbTransfer._fields_}
    assert offsets == {
        "dev_handle": 0, "flags": 8, "endpoint": 9, "type": 10, "timeout": 12, "status": 16, "length": 20,
        "actual_length": 24, "callback": 32, "user_data": 40, "buffer": 48, "num_iso_packets": 56,
    }  # fmt: skip


def test_keeps_every_transfer_in_flight_and_delivers_in_submission_order():
    script = [ok(b"%02d" % i) for i in range(20)]
    api, sink = ScriptedApi(script), Collector()
    ring = make_ring(api, sink).start()
    wait_for(lambda: not api.script and len(sink.data) == 20)
    wait_for(lambda: ring.in_flight == 4)  # every completed transfer was resubmitted
    assert sink.data == [b"%02d" % i for i in range(20)]
    assert api.max_in_flight == 4 and api.submits == 4 + 20
    assert set(api.fields_seen) == {(0x1234, 0x82, LIBUSB_TRANSFER_TYPE_BULK, 0, 64, 0)}
    ring.stop()
    assert sink.ends == [None] and not ring.running
    assert api.cancels == 4 and api.frees == 4 and ring.in_flight == 0


def test_empty_completions_are_counted_not_delivered():
    api, sink = ScriptedApi([ok(b"ab"), ok(b""), ok(b"cd")]), Collector()
    ring = make_ring(api, sink).start()
    wait_for(lambda: not api.script and len(sink.data) == 2)
    ring.stop()
    assert sink.data == [b"ab", b"cd"] and ring.stats.empty_completions == 1


def test_stop_delivers_the_bytes_of_cancelled_transfers():
    api, sink = ScriptedApi([ok(b"ab")], partial_on_cancel=b"xy"), Collector()
    ring = make_ring(api, sink, transfers=3).start()
    wait_for(lambda: sink.data == [b"ab"])
    ring.stop()
    assert sink.data == [b"ab"] + [b"xy"] * 3 and sink.ends == [None]


def test_unplug_ends_with_disconnected_after_the_data_and_resubmits_nothing():
    api, sink = ScriptedApi([ok(b"1"), ok(b"2"), (LIBUSB_TRANSFER_NO_DEVICE, b"")]), Collector()
    ring = make_ring(api, sink).start()
    assert sink.ended.wait(5.0)
    assert sink.data == [b"1", b"2"]
    assert len(sink.ends) == 1 and isinstance(sink.ends[0], DeviceDisconnectedError)
    assert "disconnected" in str(sink.ends[0])
    assert api.submits == 4 + 2 and api.cancels == 3 and api.frees == 4 and not ring.running


def test_transfer_error_ends_the_stream_with_a_transport_error():
    api, sink = ScriptedApi([ok(b"1"), (LIBUSB_TRANSFER_OVERFLOW, b"")]), Collector()
    make_ring(api, sink).start()
    assert sink.ended.wait(5.0)
    assert sink.data == [b"1"]
    assert type(sink.ends[0]) is TransportError and "overflow" in str(sink.ends[0])


def test_stall_cancels_the_others_clears_the_halt_and_resubmits_the_ring():
    api, sink = ScriptedApi([ok(b"a"), (LIBUSB_TRANSFER_STALL, b""), ok(b"b"), ok(b"c")]), Collector()
    ring = make_ring(api, sink).start()
    wait_for(lambda: len(sink.data) == 3 and ring.in_flight == 4)
    assert sink.data == [b"a", b"b", b"c"]
    assert sink.halts == 1 and ring.stats.stalls == 1 and api.cancels == 3
    ring.stop()
    assert sink.ends == [None]


def test_stall_on_a_vanished_camera_ends_with_the_clear_halt_error():
    api, sink = ScriptedApi([(LIBUSB_TRANSFER_STALL, b"")]), Collector()
    sink.clear_halt = lambda: (_ for _ in ()).throw(DeviceDisconnectedError("gone while clearing"))
    make_ring(api, sink).start()
    assert sink.ended.wait(5.0)
    assert isinstance(sink.ends[0], DeviceDisconnectedError) and "gone while clearing" in str(sink.ends[0])


def test_failed_first_submission_raises_and_leaves_nothing_in_flight():
    api, sink = ScriptedApi([], fail_submit_at=1), Collector()
    ring = make_ring(api, sink)
    with pytest.raises(DeviceDisconnectedError, match="could not be submitted"):
        ring.start()
    assert ring.in_flight == 0 and api.cancels == 0 and api.frees == 4 and not ring.running and sink.ends == []


def test_failed_later_submission_ends_the_started_stream_after_the_data():
    # The camera is unplugged while the ring is being filled: the two transfers in flight come back cancelled with
    # the bytes they hold, and those bytes are delivered before the stream ends.
    api, sink = ScriptedApi([], partial_on_cancel=b"part", fail_submit_at=3), Collector()
    ring = make_ring(api, sink).start()
    assert sink.ended.wait(5.0)
    ring.stop()
    assert sink.data == [b"part", b"part"] and api.cancels == 2
    assert len(sink.ends) == 1 and isinstance(sink.ends[0], DeviceDisconnectedError)
    assert "could not be submitted" in str(sink.ends[0])
    assert api.submits == 3 and api.frees == 4 and ring.in_flight == 0 and not ring.running


def test_a_failing_consumer_ends_the_stream_with_its_error():
    api, sink = ScriptedApi([ok(b"1"), ok(b"2")]), Collector()

    def on_data(data):
        raise ValueError("consumer broke")

    ring = BulkTransferRing(api, 0x82, on_data, sink.on_end, sink.clear_halt, transfers=2, transfer_bytes=8)
    ring.start()
    assert sink.ended.wait(5.0)
    assert isinstance(sink.ends[0], ValueError) and not ring.running


def test_invalid_sizes_are_refused():
    with pytest.raises(ValueError, match="transfers must be >= 1"):
        make_ring(ScriptedApi([]), Collector(), transfers=0)
    with pytest.raises(ValueError, match="transfer_bytes must be >= 1"):
        make_ring(ScriptedApi([]), Collector(), transfer_bytes=0)


LIBUSB = ctypes.util.find_library("usb-1.0")


@pytest.mark.skipif(LIBUSB is None, reason="libusb-1.0 is not installed (apt install libusb-1.0-0)")
def test_libusb_api_binds_the_real_library_on_pyusbs_context():
    from usb.backend import libusb1

    backend = libusb1.get_backend()
    api = LibusbAsyncApi(backend.lib._name, backend.ctx.value, 0)
    transfer = api.alloc_transfer()
    transfer.contents.length = 8192
    assert transfer.contents.length == 8192
    assert api.cancel_transfer(transfer) == LIBUSB_ERROR_NOT_FOUND  # never submitted
    api.free_transfer(transfer)
    start = time.monotonic()
    assert api.handle_events(20) == 0  # nothing in flight: returns after the timeout
    assert 0.01 < time.monotonic() - start < 2.0


# --- on a device: the virtual backend's API and the emulated libusb-1.0 ---------------------------------------------
def streaming_transport(usb_backend, device, faults=EmuFaults()):
    """Open ``device`` and switch its data on (USB RUN, MUX RUN, DVS RUN) without a ring."""
    transport = UsbTransport.open(backend=usb_backend.plug(device, faults))
    for module, param in ((Module.USB, Usb.RUN), (Module.MUX, Mux.RUN), (Module.DVS, Dvs.RUN)):
        transport.config_write(module, param, 1)
    return transport


def device_ring(transport, sink, api=None, **kwargs):
    kwargs.setdefault("transfers", 4)
    kwargs.setdefault("transfer_bytes", 1024)
    return BulkTransferRing(api or transport.async_transfers(), 0x82, sink.on_data, sink.on_end,
                            transport.clear_halt, describe="DAVIS test", **kwargs)


def numbered(n, size=100):
    """``n`` distinct short transfers (< 1024 bytes: each ends a bulk read)."""
    return [bytes([i % 256]) * (size + i % 7) for i in range(n)]


def test_device_keeps_transfers_in_flight_and_delivers_in_order(usb_backend):
    transfers = numbered(60)
    device = VirtualDavis346(source=TransferListSource(transfers))
    sink = Collector()
    with streaming_transport(usb_backend, device) as transport:
        ring = device_ring(transport, sink).start()
        wait_for(lambda: len(sink.data) == 60)
        wait_for(lambda: ring.in_flight == 4)
        ring.stop()
    assert sink.data == transfers and sink.ends == [None] and not ring.running and ring.in_flight == 0
    if usb_backend.emu is not None:
        counters = usb_backend.emu.counters()
        assert counters["allocated"] == counters["freed"] == 4
        assert counters["submits"] == 4 + 60 and counters["callbacks"] == counters["submits"]


def test_device_empty_transfers_are_counted_not_delivered(usb_backend):
    device = VirtualDavis346(source=TransferListSource([b"ab", b"", b"cd"]))
    sink = Collector()
    with streaming_transport(usb_backend, device) as transport:
        ring = device_ring(transport, sink).start()
        wait_for(lambda: len(sink.data) == 2 and device.drained)
        ring.stop()
    assert sink.data == [b"ab", b"cd"] and ring.stats.empty_completions == 1


def test_device_unplug_ends_with_disconnected_after_the_data(usb_backend):
    transfers = numbered(3)
    device = VirtualDavis346(source=TransferListSource(transfers), faults=Faults(disconnect_after_transfers=2))
    sink = Collector()
    with streaming_transport(usb_backend, device) as transport:
        ring = device_ring(transport, sink).start()
        assert sink.ended.wait(5.0)
        ring.stop()
    assert sink.data == transfers[:2]
    assert len(sink.ends) == 1 and isinstance(sink.ends[0], DeviceDisconnectedError) and not ring.running


class _FailingDevice(VirtualDavis346):
    """Serves ``good`` bulk reads, then fails every read with EIO (a USB error other than stall or unplug)."""

    def __init__(self, good, **kwargs):
        super().__init__(**kwargs)
        self.good = good

    def bulk_read(self, endpoint, buff, timeout_ms):
        if self.transfers_served >= self.good:
            raise usb_error(errno.EIO)
        return super().bulk_read(endpoint, buff, timeout_ms)


def test_device_transfer_error_ends_the_stream_with_a_transport_error(usb_backend):
    device = _FailingDevice(1, source=TransferListSource(numbered(3)))
    sink = Collector()
    with streaming_transport(usb_backend, device) as transport:
        device_ring(transport, sink).start()
        assert sink.ended.wait(5.0)
    assert sink.data == numbered(1)
    assert type(sink.ends[0]) is TransportError and "failed (error)" in str(sink.ends[0])


def test_device_stalls_are_cleared_and_lose_nothing(usb_backend):
    transfers = numbered(12)
    device = VirtualDavis346(source=TransferListSource(transfers), faults=Faults(stall_every=3))
    sink = Collector()
    with streaming_transport(usb_backend, device) as transport:
        ring = device_ring(transport, sink).start()
        wait_for(lambda: len(sink.data) == 12)
        ring.stop()
    assert sink.data == transfers and sink.ends == [None]
    assert ring.stats.stalls >= 1 and device.clear_halts == [0x82] * ring.stats.stalls


class _VanishOnClearHalt(VirtualDavis346):
    def clear_halt(self, endpoint):
        self.unplug()
        super().clear_halt(endpoint)


def test_device_stall_on_a_vanished_camera_ends_with_disconnected(usb_backend):
    device = _VanishOnClearHalt(source=TransferListSource(numbered(2)), faults=Faults(stall_every=1))
    sink = Collector()
    with streaming_transport(usb_backend, device) as transport:
        device_ring(transport, sink).start()
        assert sink.ended.wait(5.0)
    assert isinstance(sink.ends[0], DeviceDisconnectedError) and sink.data == []


def test_device_submission_to_an_unplugged_camera_raises_and_leaves_nothing(usb_backend):
    device = VirtualDavis346()
    sink = Collector()
    with streaming_transport(usb_backend, device) as transport:
        api = transport.async_transfers()
        device.unplug()
        ring = device_ring(transport, sink, api=api)
        with pytest.raises(DeviceDisconnectedError, match="could not be submitted"):
            ring.start()
    assert ring.in_flight == 0 and not ring.running and sink.ends == []
    if usb_backend.emu is not None:
        counters = usb_backend.emu.counters()
        assert counters["allocated"] == counters["freed"] == 4 and counters["submits"] == 0


def test_device_failing_consumer_ends_the_stream_with_its_error(usb_backend):
    device = VirtualDavis346(source=TransferListSource(numbered(5)))
    sink = Collector()

    def on_data(data):
        raise ValueError("consumer broke")

    with streaming_transport(usb_backend, device) as transport:
        ring = BulkTransferRing(transport.async_transfers(), 0x82, on_data, sink.on_end, transport.clear_halt,
                                transfers=2, transfer_bytes=1024)
        ring.start()
        assert sink.ended.wait(5.0)
    assert isinstance(sink.ends[0], ValueError) and not ring.running


STOP_FAULTS = {
    "prompt": EmuFaults(),
    "late-completions": EmuFaults(completion_delay_us=3000, cancel_delay_us=2000),
    "cancel-races": EmuFaults(cancel_race_every=1, poll_ms=1),
}


@pytest.mark.parametrize("faults", STOP_FAULTS.values(), ids=STOP_FAULTS.keys())
def test_device_stop_while_data_flows_loses_no_byte_the_device_sent(usb_backend, faults):
    device = VirtualDavis346(source=EndlessSource(STRESS_TRANSFER, interval_us=250))
    with streaming_transport(usb_backend, device, faults) as transport:
        for _ in range(20):
            sink = Collector()
            ring = device_ring(transport, sink, transfers=8, transfer_bytes=32768).start()
            wait_for(lambda: len(sink.data) >= 2)
            ring.stop()  # the device keeps streaming: transfers complete (with data) while the ring stops
            assert sink.ends == [None] and not ring.running and ring.in_flight == 0
    assert sum(len(d) for d in sink.data) > 0
    if usb_backend.emu is not None and faults.cancel_race_every:
        assert usb_backend.emu.counters()["cancel_races"] > 0  # some cancels lost the race: data came back


def test_device_bytes_received_equal_bytes_served_across_stops(usb_backend):
    device = VirtualDavis346(source=EndlessSource(STRESS_TRANSFER, interval_us=250))
    received = 0
    with streaming_transport(usb_backend, device, EmuFaults(completion_delay_us=1000, cancel_race_every=2)) as tr:
        for _ in range(10):
            sink = Collector()
            ring = device_ring(tr, sink, transfers=8, transfer_bytes=32768).start()
            wait_for(lambda: len(sink.data) >= 3)
            ring.stop()
            received += sum(len(d) for d in sink.data)
        tr.config_write(Module.DVS, Dvs.RUN, 0)
    assert received == device.bytes_served


class _SlowEventHandling:
    """The emulated libusb's API with the ring's own event handling slowed down, so that other threads (here a
    synchronous control transfer) usually find libusb's event lock free and run the ring's callbacks."""

    def __init__(self, api):
        self._api = api
        self.dev_handle = api.dev_handle

    def __getattr__(self, name):
        return getattr(self._api, name)

    def handle_events(self, timeout_ms):
        time.sleep(0.005)
        return self._api.handle_events(1)


def test_callbacks_run_by_a_synchronous_transfer_keep_order_and_lose_nothing(emulated_usb_backend):
    usb_backend = emulated_usb_backend  # the virtual backend runs callbacks in the ring's thread only
    transfers = numbered(400)
    device = VirtualDavis346(source=TransferListSource(transfers))
    sink = Collector()
    with streaming_transport(usb_backend, device) as transport:
        ring = device_ring(transport, sink, api=_SlowEventHandling(transport.async_transfers())).start()
        deadline = time.monotonic() + 20
        while len(sink.data) < 400 and time.monotonic() < deadline:
            transport.config_read(6, 0)  # libusb_control_transfer handles events when the event lock is free
        ring.stop()
    assert sink.data == transfers and sink.ends == [None]
    assert usb_backend.emu.counters()["sync_callbacks"] > 0


def test_a_transfer_error_on_a_vanished_camera_ends_disconnected():
    from davis_rig.usb.async_bulk import LIBUSB_TRANSFER_ERROR

    api, sink = ScriptedApi([ok(b"1"), (LIBUSB_TRANSFER_ERROR, b"")]), Collector()
    sink.clear_halt = lambda: (_ for _ in ()).throw(TransportError("clear halt failed (No such device)"))
    make_ring(api, sink).start()
    assert sink.ended.wait(5.0)
    assert sink.data == [b"1"]
    assert type(sink.ends[0]) is DeviceDisconnectedError and "could not be recovered" in str(sink.ends[0])


def test_a_transfer_error_on_a_live_camera_stays_a_transport_error():
    from davis_rig.usb.async_bulk import LIBUSB_TRANSFER_ERROR

    api, sink = ScriptedApi([ok(b"1"), (LIBUSB_TRANSFER_ERROR, b"")]), Collector()
    make_ring(api, sink).start()
    assert sink.ended.wait(5.0)
    assert type(sink.ends[0]) is TransportError and "(error)" in str(sink.ends[0]) and sink.halts == 1


def test_libusbs_event_handling_errors_raise_but_an_interrupted_wait_does_not():
    from davis_rig.usb.async_bulk import LIBUSB_ERROR_INTERRUPTED

    api = LibusbAsyncApi.__new__(LibusbAsyncApi)  # only handle_events: the C call replaced by its return codes
    api._context = None
    for code, raises in ((0, False), (LIBUSB_ERROR_INTERRUPTED, False), (LIBUSB_ERROR_NO_DEVICE, True)):
        api._handle = lambda context, timeout, completed, code=code: code
        if raises:
            with pytest.raises(TransportError, match=f"libusb error {code}"):
                api.handle_events(10)
        else:
            assert api.handle_events(10) == 0
