"""The pyusb side of the virtual DAVIS346: :class:`VirtualDavis346Backend`, a real ``usb.backend.IBackend`` that
answers descriptor and standard requests and routes vendor control transfers and bulk/interrupt reads to the
:class:`~davis_rig.usb.virtual.device.VirtualDavis346` device models on its "bus"."""

from __future__ import annotations

import errno as errno_mod
import struct
import threading

import usb.backend

from davis_rig.protocol.config import DATA_ENDPOINT, DEBUG_ENDPOINT
from davis_rig.usb.virtual.device import MAX_PACKET_BYTES, Descriptor, VirtualDavis346, copy_into, usb_error
from davis_rig.usb.virtual.transfers import VirtualAsyncTransfers

__all__ = ["VirtualDavis346Backend"]

_CONFIG_DESC = dict(
    bLength=9,
    bDescriptorType=2,
    wTotalLength=9 + 9 + 7 + 7,
    bNumInterfaces=1,
    bConfigurationValue=1,
    iConfiguration=0,
    bmAttributes=0x80,
    bMaxPower=112,
    extra_descriptors=[],
)
_INTERFACE_DESC = dict(
    bLength=9,
    bDescriptorType=4,
    bInterfaceNumber=0,
    bAlternateSetting=0,
    bNumEndpoints=2,
    bInterfaceClass=0xFF,
    bInterfaceSubClass=0,
    bInterfaceProtocol=0,
    iInterface=0,
    extra_descriptors=[],
)
_ENDPOINT_DESCS = (
    dict(bLength=7, bDescriptorType=5, bEndpointAddress=DATA_ENDPOINT, bmAttributes=0x02, wMaxPacketSize=MAX_PACKET_BYTES,
         bInterval=0, bRefresh=0, bSynchAddress=0, extra_descriptors=[]),
    dict(bLength=7, bDescriptorType=5, bEndpointAddress=DEBUG_ENDPOINT, bmAttributes=0x03, wMaxPacketSize=64,
         bInterval=4, bRefresh=0, bSynchAddress=0, extra_descriptors=[]),
)


class _Handle:
    def __init__(self, device: VirtualDavis346, number: int):
        self.device = device
        self.number = number


class VirtualDavis346Backend(usb.backend.IBackend):
    """pyusb backend serving one or more :class:`VirtualDavis346` devices.

    Args:
        *devices: the virtual cameras on this "bus" (enumeration order = argument order).

    Attributes:
        devices: the device models.
        open_handles: number of currently open device handles.
    """

    def __init__(self, *devices: VirtualDavis346):
        self.devices = list(devices)
        self._handles = 0
        self.open_handles = 0
        self._lock = threading.Lock()

    def add_device(self, device: VirtualDavis346) -> None:
        """Plug in another virtual camera."""
        self.devices.append(device)

    # enumeration and descriptors
    def enumerate_devices(self):
        return [d for d in self.devices if not d.unplugged]

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        return dev.device_descriptor()

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(f"configuration index {config} out of range")
        return Descriptor(**_CONFIG_DESC)

    def get_interface_descriptor(self, dev, intf, alt, config):
        if config != 0 or intf != 0 or alt != 0:
            raise IndexError(f"interface ({intf}, {alt}) out of range")
        return Descriptor(**_INTERFACE_DESC)

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if config != 0 or intf != 0 or alt != 0 or not 0 <= ep < len(_ENDPOINT_DESCS):
            raise IndexError(f"endpoint {ep} out of range")
        return Descriptor(**_ENDPOINT_DESCS[ep])

    # handles, configuration, interfaces
    def open_device(self, dev):
        dev.check_present()
        if dev.faults.open_errno is not None:
            raise usb_error(dev.faults.open_errno)
        with self._lock:
            self._handles += 1
            self.open_handles += 1
            return _Handle(dev, self._handles)

    def close_device(self, dev_handle):
        with self._lock:
            self.open_handles -= 1

    def set_configuration(self, dev_handle, config_value):
        dev_handle.device.check_present()
        if config_value not in (0, 1):
            raise usb_error(errno_mod.EIO)
        dev_handle.device.configuration = int(config_value)

    def get_configuration(self, dev_handle):
        dev_handle.device.check_present()
        return dev_handle.device.configuration

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        dev_handle.device.check_present()

    def claim_interface(self, dev_handle, intf):
        dev = dev_handle.device
        dev.check_present()
        if dev.faults.claim_errno is not None:
            raise usb_error(dev.faults.claim_errno)
        if dev.claimed:
            raise usb_error(errno_mod.EBUSY)
        dev.claimed = True

    def release_interface(self, dev_handle, intf):
        dev = dev_handle.device
        dev.claimed = False
        dev.check_present()

    # transfers
    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        return dev_handle.device.bulk_read(ep, buff, timeout)

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        dev_handle.device.check_present()
        raise usb_error(errno_mod.EPIPE)  # the DAVIS has no OUT data endpoint

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        return dev_handle.device.intr_read(ep, buff, timeout)

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        dev = dev_handle.device
        if (bmRequestType & 0x60) == 0x00:  # standard request
            return self._standard_request(dev, bmRequestType, bRequest, wValue, wIndex, data)
        reply = dev.control(bmRequestType, bRequest, wValue, wIndex, data)
        if bmRequestType & 0x80:
            memoryview(data).cast("B")[: len(reply)] = reply
            return len(reply)
        return reply

    def _standard_request(self, dev, bmRequestType, bRequest, wValue, wIndex, data):
        dev.check_present()
        if bmRequestType == 0x80 and bRequest == 6 and (wValue >> 8) == 3:  # GET_DESCRIPTOR(STRING)
            index = wValue & 0xFF
            if index == 0:
                payload = struct.pack("<BBH", 4, 3, 0x0409)
            else:
                text = dev.strings().get(index)
                if text is None:
                    raise usb_error(errno_mod.EPIPE)
                encoded = text.encode("utf-16-le")
                payload = struct.pack("<BB", 2 + len(encoded), 3) + encoded
            return copy_into(data, payload)
        raise usb_error(errno_mod.EPIPE)

    def clear_halt(self, dev_handle, ep):
        dev_handle.device.clear_halt(ep)

    def async_transfers(self, dev_handle) -> VirtualAsyncTransfers:
        """libusb's asynchronous transfer API for an open handle (what ``LibusbAsyncApi`` is on real hardware)."""
        return VirtualAsyncTransfers(dev_handle.device)

    def reset_device(self, dev_handle):
        dev_handle.device.check_present()

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def detach_kernel_driver(self, dev_handle, intf):
        return None

    def attach_kernel_driver(self, dev_handle, intf):
        return None
