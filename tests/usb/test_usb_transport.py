"""UsbTransport over the real pyusb code path, driven by the virtual DAVIS346 backend."""

import errno

import pytest
import usb.core

from davis_rig.errors import (
    DeviceBusyError,
    DeviceDisconnectedError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceVersionError,
    TransportError,
)
from davis_rig.protocol.config import ConfigWrite
from davis_rig.usb.sources import Faults, TransferListSource
from davis_rig.usb.transport import UsbTransport, list_devices, map_usb_error, temporary_serial
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend, usb_error


def _run(dev):
    """Set the run flags the virtual device needs before it serves data (MUX, USB, DVS RUN)."""
    dev.registers.update({(0, 0): 1, (9, 0): 1, (1, 3): 1})


def test_list_devices_reports_serials_and_versions():
    a = VirtualDavis346(serial="AAA00001", address=5)
    b = VirtualDavis346(serial=None, bus=2, address=7, product_id=0x841B, firmware_version=4)
    entries = list_devices(VirtualDavis346Backend(a, b))
    assert [(e.serial, e.product_id, e.firmware_version, e.bus, e.address, e.error) for e in entries] == [
        ("AAA00001", 0x841A, 6, 1, 5, None),
        ("TMP00519", 0x841B, 4, 2, 7, None),  # libcaer fallback: TMP%05u of (bus << 8) | address = 519
    ]
    assert temporary_serial(2, 7) == "TMP00519"
    assert not a.claimed and not b.claimed  # discovery does not claim


def test_open_by_serial_configures_claims_and_reads_versions():
    a, b = VirtualDavis346(serial="AAA00001"), VirtualDavis346(serial="BBB00002", address=3)
    backend = VirtualDavis346Backend(a, b)
    with UsbTransport.open(serial="BBB00002", backend=backend) as t:
        assert (t.serial, t.firmware_version, t.logic_version, t.logic_patch) == ("BBB00002", 6, 18, 1)
        assert b.configuration == 1 and b.claimed and not a.claimed
        assert b.reads == [(6, 0), (6, 7)]  # matching reads: logic version, then patch
    assert not b.claimed
    assert backend.open_handles == 0


def test_open_errors_not_found():
    with pytest.raises(DeviceNotFoundError, match="no DAVIS camera found"):
        UsbTransport.open(backend=VirtualDavis346Backend())
    with pytest.raises(DeviceNotFoundError, match=r"serial 'NOPE'; found serials \['VIRT0001'\]"):
        UsbTransport.open(serial="NOPE", backend=VirtualDavis346Backend(VirtualDavis346()))


@pytest.mark.parametrize(
    "kwargs,message",
    [
        (dict(firmware_version=5), "firmware version 5 is too old, expected >= 6"),
        (dict(logic_version=17), "logic version 17 is not supported, expected exactly 18"),
        (dict(logic_version=19), "logic version 19 is not supported, expected exactly 18"),
        (dict(logic_patch=0), "patch level 0 is too old, expected >= 1"),
        (dict(product_id=0x841B, firmware_version=3), "firmware version 3 is too old, expected >= 4"),
    ],
)
def test_version_gates(kwargs, message):
    dev = VirtualDavis346(**kwargs)
    backend = VirtualDavis346Backend(dev)
    with pytest.raises(DeviceVersionError, match=message):
        UsbTransport.open(backend=backend)
    assert not dev.claimed and backend.open_handles == 0


def test_fx2_with_firmware_4_is_accepted():
    with UsbTransport.open(backend=VirtualDavis346Backend(VirtualDavis346(product_id=0x841B, firmware_version=4))) as t:
        assert t.product_id == 0x841B


def test_permission_denied_names_the_udev_rule():
    dev = VirtualDavis346(faults=Faults(open_errno=errno.EACCES))
    with pytest.raises(DevicePermissionError, match=r"firmware_notes/65-inivation\.rules.*udevadm"):
        UsbTransport.open(backend=VirtualDavis346Backend(dev))
    entry = list_devices(VirtualDavis346Backend(dev))[0]
    assert entry.serial is None and "65-inivation.rules" in entry.error


def test_busy_is_mapped():
    dev = VirtualDavis346(faults=Faults(claim_errno=errno.EBUSY))
    with pytest.raises(DeviceBusyError, match="busy"):
        UsbTransport.open(backend=VirtualDavis346Backend(dev))
    # and a second opener of a claimed camera
    other = VirtualDavis346()
    backend = VirtualDavis346Backend(other)
    with UsbTransport.open(backend=backend):
        with pytest.raises(DeviceBusyError):
            UsbTransport.open(backend=backend)


def test_open_skips_busy_camera_when_no_serial_given():
    busy = VirtualDavis346(serial="BUSY0001", faults=Faults(claim_errno=errno.EBUSY))
    free = VirtualDavis346(serial="FREE0002", address=3)
    with UsbTransport.open(backend=VirtualDavis346Backend(busy, free)) as t:
        assert t.serial == "FREE0002"


def test_register_access_on_the_wire():
    dev = VirtualDavis346()
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        assert t.config_read(1, 0) == 346 and t.config_read(1, 1) == 260 and t.config_read(6, 1) == 5
        t.config_write(1, 3, 1)
        t.config_write_multiple([ConfigWrite(0, 2, 1), ConfigWrite(0, 2, 0)])
        assert t.config_read(1, 3) == 1
    rec = [r for r in dev.control_log if r.request_type == 0x40]
    assert [(r.request, r.value, r.index, r.data) for r in rec] == [
        (0xBF, 1, 3, bytes([0, 0, 0, 1])),
        (0xC2, 2, 0, bytes.fromhex("000200000001000200000000")),
    ]
    reads = [r for r in dev.control_log if r.request_type == 0xC0]
    assert all(r.request == 0xBF and r.length == 4 for r in reads)


def test_read_data_timeout_stall_and_unplug():
    dev = VirtualDavis346(source=TransferListSource([b"\x01\x80", b"\x02\x80", b"\x03\x80"]), faults=Faults(stall_every=3))
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        assert t.read_data(8192, 10) is None  # not running yet: no data, a timeout
        _run(dev)
        t.clear_halt()
        assert t.read_data(8192, 10) == b"\x01\x80"
        assert t.read_data(8192, 10) is None and t.stalls == 1  # stalled, cleared, no data lost
        assert dev.clear_halts == [0x82, 0x82]
        assert t.read_data(8192, 10) == b"\x02\x80"
        dev.unplug()
        with pytest.raises(DeviceDisconnectedError):
            t.read_data(8192, 10)
        assert t.disconnected
        with pytest.raises(DeviceDisconnectedError):
            t.config_write(1, 3, 0)
    # close after unplug does not raise


def test_map_usb_error_table():
    assert type(map_usb_error(usb_error(errno.EACCES), "x")) is DevicePermissionError
    assert type(map_usb_error(usb_error(errno.EBUSY), "x")) is DeviceBusyError
    assert type(map_usb_error(usb_error(errno.ENODEV), "x")) is DeviceDisconnectedError
    timeout = map_usb_error(usb_error(errno.ETIMEDOUT), "read")
    assert type(timeout) is TransportError and "timed out" in str(timeout) and timeout.backend_error_code == -7
    other = map_usb_error(usb.core.USBError("boom", -1, errno.EIO), "x")
    assert type(other) is TransportError and other.backend_error_code == -1
