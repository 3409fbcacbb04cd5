"""What a DAVIS camera reports about itself when opened (PROTOCOL.md §5)."""

from __future__ import annotations

from dataclasses import dataclass

from davis_rig.protocol.config import (
    DAVIS346_CHIP_IDS,
    DEVICE_INFO_REGISTERS,
    Clocks,
    DeviceFeatures,
    device_info_fields,
)
from davis_rig.protocol.layout import SensorLayout

#: The read-only registers read at open, in wire order (§5 steps 2-3 without libcaer's repeated reads).
DEVICE_INFO_READS: tuple[tuple[int, int], ...] = tuple((int(m), int(p)) for m, p, _ in DEVICE_INFO_REGISTERS)


@dataclass(frozen=True)
class DeviceInfo:
    """Identity, versions, geometry, clocks and features of an opened DAVIS camera.

    Attributes:
        serial: USB serial string (or libcaer's ``TMPnnnnn`` fallback).
        product_id: USB PID (0x841A = FX3 / DAVIS346).
        firmware_version: bcdDevice low byte.
        logic_version: FPGA logic version (SYSINFO 0), 18.
        logic_patch: FPGA logic patch level (SYSINFO 7).
        chip_id: SYSINFO 1 (DAVIS346: 4 A, 5 B, 9 C).
        is_master: SYSINFO 2 (timestamp master in a synchronised rig).
        layout: raw geometry/orientation read-outs; ``layout.dvs_width``/``dvs_height`` are the user sizes.
        clocks: SYSINFO 3-6.
        features: ``HAS_*`` flags.
    """

    serial: str
    product_id: int
    firmware_version: int
    logic_version: int
    logic_patch: int
    chip_id: int
    is_master: bool
    layout: SensorLayout
    clocks: Clocks
    features: DeviceFeatures

    @property
    def is_davis346(self) -> bool:
        """Whether the chip id is one of the DAVIS346 variants."""
        return self.chip_id in DAVIS346_CHIP_IDS

    @property
    def dvs_size_xy(self) -> tuple[int, int]:
        """User (post-inversion) DVS size ``(width, height)``, px."""
        return (self.layout.dvs_width, self.layout.dvs_height)

    @property
    def aps_size_xy(self) -> tuple[int, int]:
        """User (post-inversion) APS size ``(width, height)``, px."""
        return (self.layout.aps_width, self.layout.aps_height)

    def to_dict(self) -> dict:
        """JSON-friendly dict (used in replay headers and session metadata)."""
        return {
            "serial": self.serial,
            "product_id": self.product_id,
            "firmware_version": self.firmware_version,
            "logic_version": self.logic_version,
            "logic_patch": self.logic_patch,
            "chip_id": self.chip_id,
            "is_master": self.is_master,
            "device_info": self.layout.to_dict(),
            "clocks": {
                "logic_mhz": self.clocks.logic_mhz,
                "adc_mhz": self.clocks.adc_mhz,
                "usb_mhz": self.clocks.usb_mhz,
                "deviation": self.clocks.deviation,
            },
            "features": {k: bool(v) for k, v in vars(self.features).items()},
        }


def read_device_info(transport) -> DeviceInfo:
    """Read the §5 registers from an open transport and build a :class:`DeviceInfo`.

    Args:
        transport: an open :class:`~davis_rig.usb.transport.UsbTransport` (versions already checked).

    Returns:
        The device description.

    Raises:
        TransportError / DeviceDisconnectedError: a read failed.
        ProtocolError: the read-outs are inconsistent (e.g. zero sizes, zero clocks).
    """
    values = {field: transport.config_read(int(m), int(p)) for m, p, field in DEVICE_INFO_REGISTERS}
    layout = SensorLayout.from_mapping(device_info_fields(values, "layout"))
    clocks = Clocks(**device_info_fields(values, "clocks"))
    features = DeviceFeatures(**{k: bool(v) for k, v in device_info_fields(values, "features").items()})
    return DeviceInfo(
        serial=transport.serial,
        product_id=transport.product_id,
        firmware_version=transport.firmware_version,
        logic_version=transport.logic_version,
        logic_patch=transport.logic_patch,
        chip_id=values["layout.chip_id"],
        is_master=bool(values["is_master"]),
        layout=layout,
        clocks=clocks,
        features=features,
    )
