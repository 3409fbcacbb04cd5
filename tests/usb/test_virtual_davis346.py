"""The virtual DAVIS346 is a faithful pyusb backend: descriptors, strings, run flags, pacing and faults."""

import errno
import json
from pathlib import Path

import numpy as np
import pytest
import usb.core
import usb.util

from davis_rig.usb.sources import DataSource, Faults, TransferListSource
from davis_rig.usb.transport import UsbTransport
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

VECTORS = json.loads((Path(__file__).resolve().parents[1] / "fixtures" / "davis346_test_vectors.json").read_text())["vectors"]


def vector_device(vector, **kwargs) -> VirtualDavis346:
    """A virtual camera reporting a vector's device_info and serving its transfers exactly."""
    return VirtualDavis346(layout=vector["device_info"], source=TransferListSource.from_hex(vector["transfers_hex"]), **kwargs)


def _start(t):
    for module, param in ((9, 0), (0, 1), (0, 0), (1, 3)):
        t.config_write(module, param, 1)


def _drain(t, size=8192, timeout_ms=20):
    out = []
    while (data := t.read_data(size, timeout_ms)) is not None:
        out.append(data)
    return out


def test_unmodified_pyusb_sees_descriptors_and_strings():
    backend = VirtualDavis346Backend(VirtualDavis346(serial="SER12345"))
    dev = usb.core.find(idVendor=0x152A, idProduct=0x841A, backend=backend)
    assert dev is not None
    assert dev.bcdDevice & 0xFF == 6 and dev.bNumConfigurations == 1
    assert dev.serial_number == "SER12345" and dev.manufacturer == "iniVation"
    cfg = dev[0]
    assert cfg.bConfigurationValue == 1
    intf = cfg[(0, 0)]
    eps = {e.bEndpointAddress: usb.util.endpoint_type(e.bmAttributes) for e in intf}
    assert eps == {0x82: usb.util.ENDPOINT_TYPE_BULK, 0x81: usb.util.ENDPOINT_TYPE_INTR}
    usb.util.dispose_resources(dev)


def test_no_data_before_run_flags():
    dev = VirtualDavis346(source=TransferListSource([b"\x00\x80"]))
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        t.config_write(0, 0, 1)  # MUX RUN only
        t.config_write(9, 0, 1)  # + USB RUN, still no producer
        assert t.read_data(8192, 10) is None
        t.config_write(2, 4, 1)  # APS RUN is a producer too
        assert t.read_data(8192, 10) == b"\x00\x80"
    assert dev.streaming


@pytest.mark.parametrize("vector", VECTORS, ids=[v["id"] for v in VECTORS])
def test_vectors_are_served_exactly_through_pyusb(vector):
    dev = vector_device(vector)
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        _start(t)
        got = _drain(t)
    # every transfer exactly, a zero-length one included (it completes with no data)
    assert got == [bytes.fromhex(h) for h in vector["transfers_hex"]]


def test_small_host_buffer_gets_the_rest_on_the_next_read():
    dev = VirtualDavis346(source=TransferListSource([bytes(range(10))]))
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        _start(t)
        assert t.read_data(4, 20) == bytes(range(4))
        assert not dev.drained  # the rest is pending in the device FIFO
        assert _drain(t, size=4) == [bytes(range(4, 8)), bytes(range(8, 10))]
        assert dev.drained


def test_whole_packet_transfers_run_on_until_a_short_packet():
    full = bytes(range(256)) * 8  # 2048 bytes = two 1024-byte packets, no short packet at its end
    dev = VirtualDavis346(source=TransferListSource([full, full, b"\x01\x02", full, b"", full]))
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        _start(t)
        got = _drain(t, size=65536)
        assert got == [full + full + b"\x01\x02", full, full]  # short packet / zero-length packet end a read
    with UsbTransport.open(backend=VirtualDavis346Backend(VirtualDavis346(source=TransferListSource([full] * 3)))) as t:
        _start(t)
        assert _drain(t, size=3072) == [full + full[:1024], full[1024:] + full]  # a full buffer ends a read


def test_fault_short_and_odd_transfers():
    dev = VirtualDavis346(
        source=TransferListSource([bytes(range(6)), bytes(range(6, 10))]),
        faults=Faults(short_transfer_bytes=4, odd_length=2),
    )
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        _start(t)
        # 2nd transfer taken from the source gets a trailing 0xA5; every piece is at most 4 bytes
        assert _drain(t) == [bytes(range(4)), bytes([4, 5]), bytes([6, 7, 8, 9]), b"\xa5"]


def test_fault_timeouts_and_garbage_are_deterministic():
    data = bytes(4096)

    def serve(seed):
        dev = VirtualDavis346(source=TransferListSource([data]), faults=Faults(garbage_rate=0.1, seed=seed, timeout_every=1))
        with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
            _start(t)
            assert t.read_data(8192, 10) is None  # every read times out: no data is lost or served
        dev.faults = Faults(garbage_rate=0.1, seed=seed)
        dev._rng = np.random.default_rng(seed)
        with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
            return _drain(t)[0]

    a, b = serve(1), serve(1)
    assert a == b and len(a) == 4096
    changed = np.count_nonzero(np.frombuffer(a, np.uint8))
    assert 250 < changed < 500  # ~10 % of 4096 bytes replaced (a few land on 0 again)


def test_fault_disconnect_after_transfers():
    dev = VirtualDavis346(source=TransferListSource([b"\x01\x80", b"\x02\x80", b"\x03\x80"]), faults=Faults(disconnect_after_transfers=2))
    backend = VirtualDavis346Backend(dev)
    with UsbTransport.open(backend=backend) as t:
        _start(t)
        assert t.read_data(8192, 10) == b"\x01\x80"
        assert t.read_data(8192, 10) == b"\x02\x80"
        with pytest.raises(Exception) as info:
            t.read_data(8192, 10)
        assert type(info.value).__name__ == "DeviceDisconnectedError"
    assert list(backend.enumerate_devices()) == []
    with pytest.raises(usb.core.USBError) as raw:
        dev.control(0xC0, 0xBF, 6, 0, bytearray(4))
    assert raw.value.errno == errno.ENODEV and raw.value.backend_error_code == -4


class _ManualClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_pacing_releases_transfers_on_the_device_clock():
    clock = _ManualClock()
    source = DataSource()
    source._push(0.0, b"\x00\x80")
    source._push(5000.0, b"\x01\x80")  # 5 ms after the stream started
    dev = VirtualDavis346(source=source, clock=clock)
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        _start(t)
        assert t.read_data(8192, 10) == b"\x00\x80"
        clock.now += 0.004
        assert t.read_data(8192, 10) is None  # device clock at 4 ms: not released yet
        clock.now += 0.002
        assert t.read_data(8192, 10) == b"\x01\x80"


def test_pacing_clock_pauses_while_the_device_is_stopped():
    clock = _ManualClock()
    source = DataSource()
    source._push(3000.0, b"\x00\x80")
    dev = VirtualDavis346(source=source, clock=clock)
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        _start(t)
        clock.now += 0.002  # 2 ms streamed
        t.config_write(0, 0, 0)  # MUX RUN off: device stopped
        clock.now += 10.0  # a long pause does not count
        t.config_write(0, 0, 1)
        assert t.read_data(8192, 10) is None  # device time 2 ms < 3 ms
        clock.now += 0.001
        assert t.read_data(8192, 10) == b"\x00\x80"


def test_read_only_registers_ignore_writes_and_writes_are_recorded():
    dev = VirtualDavis346()
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        t.config_write(1, 0, 999)
        assert t.config_read(1, 0) == 346
    assert dev.writes[-1] == (1, 0, 999)
