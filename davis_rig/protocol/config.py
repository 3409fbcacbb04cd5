"""DAVIS FPGA configuration addresses (logic 18) and their wire encodings.

Everything here is pure data and arithmetic: module/parameter numbers (PROTOCOL.md §4, after libcaer
``include/libcaer/devices/davis.h``), the vendor request codes and value encodings of §3, and the host-side
unit conversions (µs → clock cycles) of §4. Nothing here talks to USB.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Iterable, NamedTuple

import numpy as np

from davis_rig.errors import ProtocolError

# --- USB identity and vendor requests (§1-§3) -------------------------------------------------
#: USB vendor id of every iniVation/libcaer device.
INIVATION_VID = 0x152A
#: FX3-based DAVIS (DAVIS346 and friends).
DAVIS_FX3_PID = 0x841A
#: FX2-based DAVIS (DAVIS240 boards); same request codes, endpoint and event format.
DAVIS_FX2_PID = 0x841B
#: Minimum firmware version (bcdDevice low byte) per product id.
REQUIRED_FIRMWARE_VERSION = {DAVIS_FX3_PID: 6, DAVIS_FX2_PID: 4}
#: The only supported FPGA logic version (SYSINFO 0) and the minimum patch level (SYSINFO 7).
REQUIRED_LOGIC_VERSION = 18
REQUIRED_LOGIC_PATCH = 1

#: Bulk IN endpoint that carries the 16-bit event word stream.
DATA_ENDPOINT = 0x82
#: FX3-only interrupt IN endpoint carrying debug/error messages.
DEBUG_ENDPOINT = 0x81
#: Configuration value and interface number libcaer uses.
USB_CONFIGURATION = 1
USB_INTERFACE = 0

#: ``bmRequestType`` of a vendor request to the device, host → device / device → host.
REQUEST_TYPE_VENDOR_OUT = 0x40
REQUEST_TYPE_VENDOR_IN = 0xC0
#: Write or read one FPGA register (4-byte big-endian value).
VR_FPGA_CONFIG = 0xBF
#: Write many FPGA registers in one request (N packed 6-byte records, wValue = N).
VR_FPGA_CONFIG_MULTIPLE = 0xC2
#: Size of one ``VR_FPGA_CONFIG_MULTIPLE`` record: module u8, param u8, value u32 big-endian.
MULTIPLE_RECORD_BYTES = 6


# --- module and parameter addresses (§4) ------------------------------------------------------
class Module(IntEnum):
    """FPGA configuration module addresses (sent as ``wValue``)."""

    MUX = 0
    DVS = 1
    APS = 2
    IMU = 3
    EXTINPUT = 4
    BIAS = 5
    CHIP = 5
    SYSINFO = 6
    USB = 9


class Mux(IntEnum):
    """MUX module (0) parameters."""

    RUN = 0
    TIMESTAMP_RUN = 1
    TIMESTAMP_RESET = 2
    RUN_CHIP = 3
    DROP_EXTINPUT_ON_TRANSFER_STALL = 4
    DROP_DVS_ON_TRANSFER_STALL = 5
    HAS_STATISTICS = 80
    STATISTICS_EXTINPUT_DROPPED = 81
    STATISTICS_DVS_DROPPED = 83


class Dvs(IntEnum):
    """DVS module (1) parameters."""

    SIZE_COLUMNS = 0
    SIZE_ROWS = 1
    ORIENTATION_INFO = 2
    RUN = 3
    WAIT_ON_TRANSFER_STALL = 4
    EXTERNAL_AER_CONTROL = 5
    HAS_PIXEL_FILTER = 10
    FILTER_PIXEL_0_ROW = 11
    FILTER_PIXEL_0_COLUMN = 12
    FILTER_PIXEL_1_ROW = 13
    FILTER_PIXEL_1_COLUMN = 14
    FILTER_PIXEL_2_ROW = 15
    FILTER_PIXEL_2_COLUMN = 16
    FILTER_PIXEL_3_ROW = 17
    FILTER_PIXEL_3_COLUMN = 18
    FILTER_PIXEL_4_ROW = 19
    FILTER_PIXEL_4_COLUMN = 20
    FILTER_PIXEL_5_ROW = 21
    FILTER_PIXEL_5_COLUMN = 22
    FILTER_PIXEL_6_ROW = 23
    FILTER_PIXEL_6_COLUMN = 24
    FILTER_PIXEL_7_ROW = 25
    FILTER_PIXEL_7_COLUMN = 26
    HAS_BACKGROUND_ACTIVITY_FILTER = 30
    FILTER_BACKGROUND_ACTIVITY = 31
    FILTER_BACKGROUND_ACTIVITY_TIME = 32
    FILTER_REFRACTORY_PERIOD = 33
    FILTER_REFRACTORY_PERIOD_TIME = 34
    HAS_ROI_FILTER = 40
    FILTER_ROI_START_COLUMN = 41
    FILTER_ROI_START_ROW = 42
    FILTER_ROI_END_COLUMN = 43
    FILTER_ROI_END_ROW = 44
    HAS_SKIP_FILTER = 50
    FILTER_SKIP_EVENTS = 51
    FILTER_SKIP_EVENTS_EVERY = 52
    HAS_POLARITY_FILTER = 60
    FILTER_POLARITY_FLATTEN = 61
    FILTER_POLARITY_SUPPRESS = 62
    FILTER_POLARITY_SUPPRESS_TYPE = 63
    HAS_STATISTICS = 80
    STATISTICS_EVENTS_ROW = 81
    STATISTICS_EVENTS_COLUMN = 83
    STATISTICS_EVENTS_DROPPED = 85
    STATISTICS_FILTERED_PIXELS = 87
    STATISTICS_FILTERED_BACKGROUND_ACTIVITY = 89
    STATISTICS_FILTERED_REFRACTORY_PERIOD = 91


class Aps(IntEnum):
    """APS module (2) parameters (the DAVIS640H-only timings 14-19 are omitted)."""

    SIZE_COLUMNS = 0
    SIZE_ROWS = 1
    ORIENTATION_INFO = 2
    COLOR_FILTER = 3
    RUN = 4
    WAIT_ON_TRANSFER_STALL = 5
    HAS_GLOBAL_SHUTTER = 6
    GLOBAL_SHUTTER = 7
    START_COLUMN_0 = 8
    START_ROW_0 = 9
    END_COLUMN_0 = 10
    END_ROW_0 = 11
    EXPOSURE = 12
    FRAME_INTERVAL = 13
    SNAPSHOT = 100


class Imu(IntEnum):
    """IMU module (3) parameters."""

    TYPE = 0
    ORIENTATION_INFO = 1
    RUN_ACCELEROMETER = 2
    RUN_GYROSCOPE = 3
    RUN_TEMPERATURE = 4
    SAMPLE_RATE_DIVIDER = 5
    ACCEL_DLPF = 6
    ACCEL_FULL_SCALE = 7
    GYRO_DLPF = 9
    GYRO_FULL_SCALE = 10


class ExtInput(IntEnum):
    """EXTINPUT module (4) parameters."""

    RUN_DETECTOR = 0
    DETECT_RISING_EDGES = 1
    DETECT_FALLING_EDGES = 2
    DETECT_PULSES = 3
    DETECT_PULSE_POLARITY = 4
    DETECT_PULSE_LENGTH = 5
    HAS_GENERATOR = 10
    RUN_GENERATOR = 11
    GENERATE_PULSE_POLARITY = 12
    GENERATE_PULSE_INTERVAL = 13
    GENERATE_PULSE_LENGTH = 14
    GENERATE_INJECT_ON_RISING_EDGE = 15
    GENERATE_INJECT_ON_FALLING_EDGE = 16


class Chip(IntEnum):
    """CHIP configuration of a DAVIS346 (module 5, params >= 128)."""

    DIGITALMUX0 = 128
    DIGITALMUX1 = 129
    DIGITALMUX2 = 130
    DIGITALMUX3 = 131
    ANALOGMUX0 = 132
    ANALOGMUX1 = 133
    ANALOGMUX2 = 134
    BIASMUX0 = 135
    RESETCALIBNEURON = 136
    TYPENCALIBNEURON = 137
    RESETTESTPIXEL = 138
    AERNAROW = 140
    USEAOUT = 141
    GLOBAL_SHUTTER = 142
    SELECTGRAYCOUNTER = 143
    TESTADC = 144


class SysInfo(IntEnum):
    """SYSINFO module (6) parameters, all read-only."""

    LOGIC_VERSION = 0
    CHIP_IDENTIFIER = 1
    DEVICE_IS_MASTER = 2
    LOGIC_CLOCK = 3
    ADC_CLOCK = 4
    USB_CLOCK = 5
    CLOCK_DEVIATION = 6
    LOGIC_PATCH = 7


class Usb(IntEnum):
    """USB module (9) parameters."""

    RUN = 0
    EARLY_PACKET_DELAY = 1


#: Chip identifiers (SYSINFO 1) of the DAVIS346 variants A, B and C (BSI).
DAVIS346_CHIP_IDS = frozenset({4, 5, 9})

#: Documented ranges of the APS timing parameters, µs (PROTOCOL.md §4).
MAX_EXPOSURE_US = 4_194_303
MAX_FRAME_INTERVAL_US = 8_388_607
#: One USB early-packet-delay unit, µs.
EARLY_PACKET_DELAY_UNIT_US = 125


class ConfigWrite(NamedTuple):
    """One FPGA register write: ``(module, param, value)``; value is the raw unsigned 32-bit word."""

    module: int
    param: int
    value: int


def _check_u32(value: int, what: str = "value") -> int:
    value = int(value)
    if not 0 <= value <= 0xFFFF_FFFF:
        raise ProtocolError(f"{what} must fit in an unsigned 32-bit word (0..4294967295), got {value}")
    return value


def encode_value(value: int) -> bytes:
    """Encode one register value as the 4-byte big-endian data stage of a ``0xBF`` request.

    Args:
        value: unsigned 32-bit register value (bools are accepted as 0/1).

    Returns:
        4 bytes, big-endian.

    Raises:
        ProtocolError: value outside 0..2**32-1.
    """
    return struct.pack(">I", _check_u32(value))


def decode_value(data: bytes | bytearray | memoryview) -> int:
    """Decode the 4-byte big-endian data stage of a ``0xBF`` read.

    Args:
        data: exactly 4 bytes as returned by the device.

    Returns:
        The unsigned 32-bit value.

    Raises:
        ProtocolError: ``data`` is not exactly 4 bytes long (libcaer requires exactly 4).
    """
    data = bytes(data)
    if len(data) != 4:
        raise ProtocolError(f"config read: expected 4 bytes, got {len(data)}")
    return struct.unpack(">I", data)[0]


def encode_multiple(writes: Iterable[ConfigWrite]) -> bytes:
    """Pack writes into the data stage of one ``0xC2`` request (6-byte records).

    Args:
        writes: ``ConfigWrite`` records; module and param must fit in one byte each.

    Returns:
        ``len(writes) * 6`` bytes: ``[module u8][param u8][value u32 big-endian]`` per record.

    Raises:
        ProtocolError: a module/param does not fit in a byte, a value does not fit in 32 bits, or no writes.
    """
    out = bytearray()
    for write in writes:
        module, param, value = int(write[0]), int(write[1]), write[2]
        if not (0 <= module <= 0xFF and 0 <= param <= 0xFF):
            raise ProtocolError(f"multiple write: module/param must be 0..255, got ({module}, {param})")
        out += struct.pack(">BBI", module, param, _check_u32(value))
    if not out:
        raise ProtocolError("multiple write: expected at least one record, got 0")
    return bytes(out)


def decode_multiple(data: bytes | bytearray | memoryview, count: int | None = None) -> list[ConfigWrite]:
    """Unpack the data stage of a ``0xC2`` request into ``ConfigWrite`` records.

    Args:
        data: packed 6-byte records.
        count: expected number of records (the request's ``wValue``), or ``None`` to skip the check.

    Returns:
        The records in wire order.

    Raises:
        ProtocolError: the length is not a multiple of 6 or does not match ``count``.
    """
    data = bytes(data)
    if len(data) % MULTIPLE_RECORD_BYTES:
        raise ProtocolError(f"multiple write: length must be a multiple of 6, got {len(data)}")
    n = len(data) // MULTIPLE_RECORD_BYTES
    if count is not None and n != count:
        raise ProtocolError(f"multiple write: wValue says {count} records, data holds {n}")
    return [ConfigWrite(*struct.unpack_from(">BBI", data, 6 * i)) for i in range(n)]


# --- clocks and unit conversions ---------------------------------------------------------------
def _round_half_away(x: float) -> int:
    """C ``roundf`` semantics (half away from zero)."""
    return int(math.floor(x + 0.5)) if x >= 0 else -int(math.floor(-x + 0.5))


def actual_clock_mhz(clock_mhz: float, deviation: int) -> float:
    """Actual clock in MHz as libcaer stores it: ``float32(clock × (deviation / 1000))`` (double math, float32 result).

    Args:
        clock_mhz: nominal clock, MHz (SYSINFO 3/4/5).
        deviation: SYSINFO 6 clock deviation factor (1000 = exact).

    Returns:
        The actual clock, MHz, rounded to float32 like libcaer's ``xxxClockActual``.
    """
    return float(np.float32(float(clock_mhz) * (float(deviation) / 1000.0)))


def us_to_cycles(us: float, clock_mhz: float, deviation: int = 1000) -> int:
    """Convert a duration in µs to clock cycles exactly as libcaer does before a register write.

    libcaer computes ``roundf((float) us * clockActual)`` in single precision; this reproduces it bit for bit
    (float32 product, then round half away from zero).

    Args:
        us: duration, µs (>= 0).
        clock_mhz: nominal clock of the register's domain, MHz (SYSINFO 3/4/5).
        deviation: SYSINFO 6 clock deviation factor (1000 = exact).

    Returns:
        Clock cycles (unsigned 32-bit).

    Raises:
        ProtocolError: negative duration, non-positive clock/deviation, or a result beyond 32 bits.
    """
    if us < 0:
        raise ProtocolError(f"duration must be >= 0 µs, got {us}")
    if clock_mhz <= 0 or deviation <= 0:
        raise ProtocolError(f"clock must be > 0 MHz and deviation > 0, got {clock_mhz} MHz, deviation {deviation}")
    product = np.float32(us) * np.float32(actual_clock_mhz(clock_mhz, deviation))
    return _check_u32(_round_half_away(float(product)), "cycles")


def cycles_to_us(cycles: int, clock_mhz: float, deviation: int = 1000) -> int:
    """Inverse of :func:`us_to_cycles`: register value in cycles → µs (rounded), as libcaer reports reads.

    Args:
        cycles: register value, clock cycles.
        clock_mhz: nominal clock, MHz.
        deviation: SYSINFO 6 deviation factor.

    Returns:
        Duration, µs.

    Raises:
        ProtocolError: non-positive clock/deviation.
    """
    if clock_mhz <= 0 or deviation <= 0:
        raise ProtocolError(f"clock must be > 0 MHz and deviation > 0, got {clock_mhz} MHz, deviation {deviation}")
    return _round_half_away(float(cycles) / actual_clock_mhz(clock_mhz, deviation))


@dataclass(frozen=True)
class Clocks:
    """Device clocks as read from SYSINFO 3-6.

    Attributes:
        logic_mhz: FPGA logic clock, MHz (SYSINFO 3).
        adc_mhz: APS ADC clock, MHz (SYSINFO 4); exposure and frame interval are counted in it.
        usb_mhz: USB clock, MHz (SYSINFO 5).
        deviation: clock deviation factor (SYSINFO 6), actual = nominal × deviation / 1000.
    """

    logic_mhz: int
    adc_mhz: int
    usb_mhz: int
    deviation: int = 1000

    def __post_init__(self) -> None:
        for name in ("logic_mhz", "adc_mhz", "usb_mhz", "deviation"):
            if int(getattr(self, name)) <= 0:
                raise ProtocolError(f"clocks: {name} must be > 0, got {getattr(self, name)}")

    def logic_cycles(self, us: float) -> int:
        """µs → logic-clock cycles (EXTINPUT pulse lengths/intervals)."""
        return us_to_cycles(us, self.logic_mhz, self.deviation)

    def adc_cycles(self, us: float) -> int:
        """µs → ADC-clock cycles (APS exposure and frame interval)."""
        return us_to_cycles(us, self.adc_mhz, self.deviation)

    def usb_cycles(self, us: float) -> int:
        """µs → USB-clock cycles (USB early packet delay)."""
        return us_to_cycles(us, self.usb_mhz, self.deviation)


@dataclass(frozen=True)
class DeviceFeatures:
    """Optional FPGA features reported by the device's read-only ``HAS_*`` registers (§5 step 2).

    They decide which default-config writes are sent (§6.4).
    """

    dvs_has_pixel_filter: bool = False
    dvs_has_background_activity_filter: bool = False
    dvs_has_roi_filter: bool = False
    dvs_has_skip_filter: bool = False
    dvs_has_polarity_filter: bool = False
    dvs_has_statistics: bool = False
    aps_has_global_shutter: bool = False
    extinput_has_generator: bool = False
    mux_has_statistics: bool = False


#: The read-only registers a camera reports at open (PROTOCOL.md §5 steps 2-3, without libcaer's repeated reads),
#: in wire order, each with the field it fills: ``layout.<key>`` (a ``SensorLayout`` mapping key),
#: ``clocks.<field>`` (:class:`Clocks`), ``features.<field>`` (:class:`DeviceFeatures`) or ``is_master``. The
#: host decodes them (``davis_rig.device.info``) and the virtual camera answers them (``davis_rig.usb.virtual``)
#: from this one table.
DEVICE_INFO_REGISTERS: tuple[tuple[Module, int, str], ...] = (
    (Module.SYSINFO, SysInfo.CHIP_IDENTIFIER, "layout.chip_id"),
    (Module.SYSINFO, SysInfo.DEVICE_IS_MASTER, "is_master"),
    (Module.DVS, Dvs.HAS_PIXEL_FILTER, "features.dvs_has_pixel_filter"),
    (Module.DVS, Dvs.HAS_BACKGROUND_ACTIVITY_FILTER, "features.dvs_has_background_activity_filter"),
    (Module.DVS, Dvs.HAS_ROI_FILTER, "features.dvs_has_roi_filter"),
    (Module.DVS, Dvs.HAS_SKIP_FILTER, "features.dvs_has_skip_filter"),
    (Module.DVS, Dvs.HAS_POLARITY_FILTER, "features.dvs_has_polarity_filter"),
    (Module.DVS, Dvs.HAS_STATISTICS, "features.dvs_has_statistics"),
    (Module.APS, Aps.COLOR_FILTER, "layout.aps_color_filter"),
    (Module.APS, Aps.HAS_GLOBAL_SHUTTER, "features.aps_has_global_shutter"),
    (Module.EXTINPUT, ExtInput.HAS_GENERATOR, "features.extinput_has_generator"),
    (Module.MUX, Mux.HAS_STATISTICS, "features.mux_has_statistics"),
    (Module.DVS, Dvs.SIZE_COLUMNS, "layout.dvs_size_columns"),
    (Module.DVS, Dvs.SIZE_ROWS, "layout.dvs_size_rows"),
    (Module.DVS, Dvs.ORIENTATION_INFO, "layout.dvs_orientation_info"),
    (Module.APS, Aps.SIZE_COLUMNS, "layout.aps_size_columns"),
    (Module.APS, Aps.SIZE_ROWS, "layout.aps_size_rows"),
    (Module.APS, Aps.ORIENTATION_INFO, "layout.aps_orientation_info"),
    (Module.IMU, Imu.TYPE, "layout.imu_type"),
    (Module.SYSINFO, SysInfo.LOGIC_CLOCK, "clocks.logic_mhz"),
    (Module.SYSINFO, SysInfo.ADC_CLOCK, "clocks.adc_mhz"),
    (Module.SYSINFO, SysInfo.USB_CLOCK, "clocks.usb_mhz"),
    (Module.SYSINFO, SysInfo.CLOCK_DEVIATION, "clocks.deviation"),
    (Module.IMU, Imu.ORIENTATION_INFO, "layout.imu_orientation_info"),
)


def device_info_fields(values: dict[str, int], group: str) -> dict[str, int]:
    """The ``group`` (``"layout"``, ``"clocks"``, ``"features"``) entries of ``{field: value}``, without the prefix.

    Example: ``device_info_fields({"clocks.adc_mhz": 30, "is_master": 1}, "clocks") == {"adc_mhz": 30}``.
    """
    prefix = group + "."
    return {field[len(prefix):]: value for field, value in values.items() if field.startswith(prefix)}


def exposure_write(exposure_us: int, clocks: Clocks) -> ConfigWrite:
    """The APS EXPOSURE register write for an exposure in µs (converted to ADC cycles).

    Args:
        exposure_us: exposure time, µs, 0..4194303.
        clocks: the device clocks.

    Returns:
        ``ConfigWrite(APS, EXPOSURE, cycles)``.

    Raises:
        ProtocolError: exposure outside the documented range.
    """
    return _aps_time_write(Aps.EXPOSURE, "exposure", exposure_us, MAX_EXPOSURE_US, clocks)


def frame_interval_write(frame_interval_us: int, clocks: Clocks) -> ConfigWrite:
    """The APS FRAME_INTERVAL register write for an interval in µs (converted to ADC cycles).

    Args:
        frame_interval_us: time between frame starts, µs, 0..8388607.
        clocks: the device clocks.

    Returns:
        ``ConfigWrite(APS, FRAME_INTERVAL, cycles)``.

    Raises:
        ProtocolError: interval outside the documented range.
    """
    return _aps_time_write(Aps.FRAME_INTERVAL, "frame interval", frame_interval_us, MAX_FRAME_INTERVAL_US, clocks)


def _aps_time_write(param: Aps, what: str, value_us: int, max_us: int, clocks: Clocks) -> ConfigWrite:
    """An APS time register write: ``value_us`` checked against 0..``max_us`` µs, sent in ADC-clock cycles."""
    if not 0 <= value_us <= max_us:
        raise ProtocolError(f"{what} must be 0..{max_us} µs, got {value_us}")
    return ConfigWrite(Module.APS, param, clocks.adc_cycles(value_us))
