"""The DAVIS346 camera: open, configure, start/stop, decoded data (``Davis346``), device description, reader thread."""

from davis_rig.device.camera import CameraStats, Davis346
from davis_rig.device.debug import DebugMessage
from davis_rig.device.info import DeviceInfo, read_device_info
from davis_rig.device.reader import ReaderStats, TransferReader

__all__ = ["CameraStats", "Davis346", "DebugMessage", "DeviceInfo", "ReaderStats", "TransferReader", "read_device_info"]
