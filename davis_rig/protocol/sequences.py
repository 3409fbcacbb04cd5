"""libcaer's DAVIS346 configuration, start and stop sequences, as data.

A sequence is a list of steps: :class:`~davis_rig.protocol.config.ConfigWrite` (one ``0x40/0xBF`` request),
:class:`MultipleWrite` (one ``0x40/0xC2`` request), :class:`Sleep` and :class:`ClearHalt`. The device layer
executes them in order; tests compare them with what a virtual device recorded. Sources: PROTOCOL.md §6 (default
config, libcaer ``davisCommonSendDefaultChipConfig`` / ``...FPGAConfig``), §7.1 (``davisDataStart``), §7.2
(``davisDataStop``).
"""

from __future__ import annotations

from typing import Iterable, NamedTuple, Sequence, Union

from davis_rig.protocol.biases import DAVIS346_DEFAULT_BIASES, BiasEntry, check_bias_for
from davis_rig.protocol.config import (
    DATA_ENDPOINT,
    EARLY_PACKET_DELAY_UNIT_US,
    Aps,
    Chip,
    Clocks,
    ConfigWrite,
    DeviceFeatures,
    Dvs,
    ExtInput,
    Imu,
    Module,
    Mux,
    Usb,
    exposure_write,
    frame_interval_write,
)

#: libcaer defaults (§6.4): APS exposure and frame interval, µs; USB early packet delay, 125 µs units.
DEFAULT_EXPOSURE_US = 4000
DEFAULT_FRAME_INTERVAL_US = 40000
DEFAULT_EARLY_PACKET_DELAY = 8
#: External-input detector pulse length and generator interval/length defaults, µs.
DEFAULT_EXTINPUT_PULSE_LENGTH_US = 10
DEFAULT_GENERATOR_INTERVAL_US = 10
DEFAULT_GENERATOR_LENGTH_US = 5
#: Waits of ``davisDataStart`` (§7.1), µs.
START_BUFFER_CLEAR_SLEEP_US = 10_000
START_BIAS_SETTLE_SLEEP_US = 200_000
START_PRODUCERS_SLEEP_US = 50_000


class Sleep(NamedTuple):
    """Wait on the host before the next step."""

    duration_us: int


class ClearHalt(NamedTuple):
    """``CLEAR_FEATURE(ENDPOINT_HALT)`` on an endpoint (libcaer does it before submitting bulk transfers)."""

    endpoint: int = DATA_ENDPOINT


class MultipleWrite(NamedTuple):
    """Several register writes in one ``0xC2`` request (used for impulses: set, then clear)."""

    writes: tuple[ConfigWrite, ...]


Step = Union[ConfigWrite, MultipleWrite, Sleep, ClearHalt]


def _w(module: int, param: int, value: int | bool) -> ConfigWrite:
    return ConfigWrite(int(module), int(param), int(value))


def bias_writes(biases: Iterable[BiasEntry] = DAVIS346_DEFAULT_BIASES) -> list[ConfigWrite]:
    """Register writes for a list of biases, in the given order (§6.2).

    Args:
        biases: ``BiasEntry`` records (name, param, bias); defaults to libcaer's 28 DAVIS346 defaults.

    Returns:
        One ``ConfigWrite(BIAS, param, bias.encode())`` per entry.

    Raises:
        ProtocolError: an entry's bias kind does not match its register.
    """
    out = []
    for entry in biases:
        check_bias_for(entry.param, entry.bias)
        out.append(_w(Module.BIAS, entry.param, entry.bias.encode()))
    return out


def default_chip_config() -> list[ConfigWrite]:
    """DAVIS346 default chip configuration shift-register writes (module 5, params >= 128), §6.3.

    SPECIALPIXELCONTROL (139) is DAVIS240A/B-only and GLOBAL_SHUTTER (142) is written with the APS parameter,
    so neither appears here.
    """
    return [
        _w(Module.CHIP, Chip.DIGITALMUX0, 0),
        _w(Module.CHIP, Chip.DIGITALMUX1, 0),
        _w(Module.CHIP, Chip.DIGITALMUX2, 0),
        _w(Module.CHIP, Chip.DIGITALMUX3, 0),
        _w(Module.CHIP, Chip.ANALOGMUX0, 0),
        _w(Module.CHIP, Chip.ANALOGMUX1, 0),
        _w(Module.CHIP, Chip.ANALOGMUX2, 0),
        _w(Module.CHIP, Chip.BIASMUX0, 0),
        _w(Module.CHIP, Chip.RESETCALIBNEURON, 1),
        _w(Module.CHIP, Chip.TYPENCALIBNEURON, 0),
        _w(Module.CHIP, Chip.RESETTESTPIXEL, 1),
        _w(Module.CHIP, Chip.AERNAROW, 0),
        _w(Module.CHIP, Chip.USEAOUT, 0),
        _w(Module.CHIP, Chip.SELECTGRAYCOUNTER, 1),
        _w(Module.CHIP, Chip.TESTADC, 0),
    ]


def global_shutter_writes(enabled: bool, features: DeviceFeatures) -> list[ConfigWrite]:
    """APS global-shutter switch: CHIP 142 first, then APS 7; nothing if the sensor has no global shutter."""
    if not features.aps_has_global_shutter:
        return []
    return [_w(Module.CHIP, Chip.GLOBAL_SHUTTER, enabled), _w(Module.APS, Aps.GLOBAL_SHUTTER, enabled)]


def default_fpga_config(
    *,
    dvs_size_xy: tuple[int, int],
    aps_size_xy: tuple[int, int],
    features: DeviceFeatures,
    clocks: Clocks,
    imu_type: int,
    exposure_us: int = DEFAULT_EXPOSURE_US,
    frame_interval_us: int = DEFAULT_FRAME_INTERVAL_US,
) -> list[ConfigWrite]:
    """libcaer's default FPGA configuration for a DAVIS (§6.4), in wire order.

    Args:
        dvs_size_xy: user (post-inversion) DVS size ``(width, height)``, px.
        aps_size_xy: user (post-inversion) APS size ``(width, height)``, px.
        features: the device's ``HAS_*`` flags; absent features get no writes.
        clocks: device clocks (exposure/interval → ADC cycles, pulse lengths → logic cycles).
        imu_type: IMU 0 register; GYRO_DLPF is only written for type 2 (MPU-9250).
        exposure_us: APS exposure, µs (libcaer default 4000).
        frame_interval_us: APS frame interval, µs (libcaer default 40000).

    Returns:
        The register writes. MUX TIMESTAMP_RESET=false and the host-only AUTOEXPOSURE/FRAME_MODE produce no
        transfer, exactly as in libcaer.
    """
    return [
        *_dvs_fpga_writes(dvs_size_xy, features),
        *_aps_fpga_writes(aps_size_xy, features, clocks, exposure_us, frame_interval_us),
        *_imu_fpga_writes(imu_type),
        *_extinput_fpga_writes(features, clocks),
    ]


def _dvs_fpga_writes(dvs_size_xy: tuple[int, int], features: DeviceFeatures) -> list[ConfigWrite]:
    """MUX stall policy and the DVS part of :func:`default_fpga_config` (filters only where the device has them)."""
    dvs_w, dvs_h = (int(v) for v in dvs_size_xy)
    out = [
        _w(Module.MUX, Mux.DROP_EXTINPUT_ON_TRANSFER_STALL, 1),
        _w(Module.MUX, Mux.DROP_DVS_ON_TRANSFER_STALL, 1),
        _w(Module.DVS, Dvs.WAIT_ON_TRANSFER_STALL, 0),
        _w(Module.DVS, Dvs.EXTERNAL_AER_CONTROL, 0),
    ]
    if features.dvs_has_pixel_filter:
        for n in range(8):
            out.append(_w(Module.DVS, Dvs.FILTER_PIXEL_0_ROW + 2 * n, dvs_h))
            out.append(_w(Module.DVS, Dvs.FILTER_PIXEL_0_COLUMN + 2 * n, dvs_w))
    if features.dvs_has_background_activity_filter:
        out += [
            _w(Module.DVS, Dvs.FILTER_BACKGROUND_ACTIVITY, 1),
            _w(Module.DVS, Dvs.FILTER_BACKGROUND_ACTIVITY_TIME, 8),
            _w(Module.DVS, Dvs.FILTER_REFRACTORY_PERIOD, 0),
            _w(Module.DVS, Dvs.FILTER_REFRACTORY_PERIOD_TIME, 1),
        ]
    if features.dvs_has_roi_filter:
        out += [
            _w(Module.DVS, Dvs.FILTER_ROI_START_COLUMN, 0),
            _w(Module.DVS, Dvs.FILTER_ROI_START_ROW, 0),
            _w(Module.DVS, Dvs.FILTER_ROI_END_COLUMN, dvs_w - 1),
            _w(Module.DVS, Dvs.FILTER_ROI_END_ROW, dvs_h - 1),
        ]
    if features.dvs_has_skip_filter:
        out += [_w(Module.DVS, Dvs.FILTER_SKIP_EVENTS, 0), _w(Module.DVS, Dvs.FILTER_SKIP_EVENTS_EVERY, 5)]
    if features.dvs_has_polarity_filter:
        out += [
            _w(Module.DVS, Dvs.FILTER_POLARITY_FLATTEN, 0),
            _w(Module.DVS, Dvs.FILTER_POLARITY_SUPPRESS, 0),
            _w(Module.DVS, Dvs.FILTER_POLARITY_SUPPRESS_TYPE, 0),
        ]
    return out


def _aps_fpga_writes(aps_size_xy: tuple[int, int], features: DeviceFeatures, clocks: Clocks, exposure_us: int,
                     frame_interval_us: int) -> list[ConfigWrite]:
    """The APS part of :func:`default_fpga_config`: stall policy, global shutter, full-sensor ROI, timing."""
    aps_w, aps_h = (int(v) for v in aps_size_xy)
    return [
        _w(Module.APS, Aps.WAIT_ON_TRANSFER_STALL, 1),
        *global_shutter_writes(features.aps_has_global_shutter, features),
        _w(Module.APS, Aps.START_COLUMN_0, 0),
        _w(Module.APS, Aps.START_ROW_0, 0),
        _w(Module.APS, Aps.END_COLUMN_0, aps_w - 1),
        _w(Module.APS, Aps.END_ROW_0, aps_h - 1),
        exposure_write(exposure_us, clocks),
        frame_interval_write(frame_interval_us, clocks),
    ]


def _imu_fpga_writes(imu_type: int) -> list[ConfigWrite]:
    """The IMU part of :func:`default_fpga_config` (GYRO_DLPF only for type 2, the MPU-9250)."""
    out = [
        _w(Module.IMU, Imu.SAMPLE_RATE_DIVIDER, 0),
        _w(Module.IMU, Imu.ACCEL_DLPF, 1),
        _w(Module.IMU, Imu.ACCEL_FULL_SCALE, 1),
    ]
    if imu_type == 2:
        out.append(_w(Module.IMU, Imu.GYRO_DLPF, 1))
    out.append(_w(Module.IMU, Imu.GYRO_FULL_SCALE, 1))
    return out


def _extinput_fpga_writes(features: DeviceFeatures, clocks: Clocks) -> list[ConfigWrite]:
    """The external-input part of :func:`default_fpga_config`: pulse detector, and the generator if present."""
    out = [
        _w(Module.EXTINPUT, ExtInput.DETECT_RISING_EDGES, 0),
        _w(Module.EXTINPUT, ExtInput.DETECT_FALLING_EDGES, 0),
        _w(Module.EXTINPUT, ExtInput.DETECT_PULSES, 1),
        _w(Module.EXTINPUT, ExtInput.DETECT_PULSE_POLARITY, 1),
        _w(Module.EXTINPUT, ExtInput.DETECT_PULSE_LENGTH, clocks.logic_cycles(DEFAULT_EXTINPUT_PULSE_LENGTH_US)),
    ]
    if features.extinput_has_generator:
        out += [
            _w(Module.EXTINPUT, ExtInput.RUN_GENERATOR, 0),
            _w(Module.EXTINPUT, ExtInput.GENERATE_PULSE_POLARITY, 1),
            _w(Module.EXTINPUT, ExtInput.GENERATE_PULSE_INTERVAL, clocks.logic_cycles(DEFAULT_GENERATOR_INTERVAL_US)),
            _w(Module.EXTINPUT, ExtInput.GENERATE_PULSE_LENGTH, clocks.logic_cycles(DEFAULT_GENERATOR_LENGTH_US)),
            _w(Module.EXTINPUT, ExtInput.GENERATE_INJECT_ON_RISING_EDGE, 0),
            _w(Module.EXTINPUT, ExtInput.GENERATE_INJECT_ON_FALLING_EDGE, 0),
        ]
    return out


def early_packet_delay_write(delay_units: int, clocks: Clocks) -> ConfigWrite:
    """USB EARLY_PACKET_DELAY write: ``delay_units`` × 125 µs converted to USB-clock cycles."""
    return _w(Module.USB, Usb.EARLY_PACKET_DELAY, clocks.usb_cycles(delay_units * EARLY_PACKET_DELAY_UNIT_US))


def default_config_sequence(
    *,
    dvs_size_xy: tuple[int, int],
    aps_size_xy: tuple[int, int],
    features: DeviceFeatures,
    clocks: Clocks,
    imu_type: int,
    biases: Sequence[BiasEntry] = DAVIS346_DEFAULT_BIASES,
    exposure_us: int = DEFAULT_EXPOSURE_US,
    frame_interval_us: int = DEFAULT_FRAME_INTERVAL_US,
) -> list[Step]:
    """The full ``caerDeviceSendDefaultConfig`` for a DAVIS346: biases → chip → FPGA → USB delay (§6).

    Args:
        dvs_size_xy, aps_size_xy, features, clocks, imu_type, exposure_us, frame_interval_us:
            see :func:`default_fpga_config`.
        biases: bias entries to write first (default: libcaer's DAVIS346 defaults).

    Returns:
        The steps, all single ``ConfigWrite`` requests.
    """
    steps: list[Step] = []
    steps += bias_writes(biases)
    steps += default_chip_config()
    steps += default_fpga_config(
        dvs_size_xy=dvs_size_xy,
        aps_size_xy=aps_size_xy,
        features=features,
        clocks=clocks,
        imu_type=imu_type,
        exposure_us=exposure_us,
        frame_interval_us=frame_interval_us,
    )
    steps.append(early_packet_delay_write(DEFAULT_EARLY_PACKET_DELAY, clocks))
    return steps


def _producer_off_writes() -> list[ConfigWrite]:
    return [
        _w(Module.DVS, Dvs.RUN, 0),
        _w(Module.APS, Aps.RUN, 0),
        _w(Module.IMU, Imu.RUN_ACCELEROMETER, 0),
        _w(Module.IMU, Imu.RUN_GYROSCOPE, 0),
        _w(Module.IMU, Imu.RUN_TEMPERATURE, 0),
        _w(Module.EXTINPUT, ExtInput.RUN_DETECTOR, 0),
    ]


def start_sequence(*, dvs: bool = True, aps: bool = True, imu: bool = True, extinput: bool = True) -> list[Step]:
    """``davisDataStart`` on the wire (§7.1), with optional producers left off.

    With every producer enabled this is exactly libcaer's sequence: stop everything, sleep 10 ms, clear halt on
    0x82, RUN_CHIP, sleep 200 ms, USB RUN, TIMESTAMP_RUN, MUX RUN, sleep 50 ms, then DVS, APS, IMU ×3, EXTINPUT
    run flags. A disabled producer's run writes are omitted (its run flag stays 0 from the first block).

    Args:
        dvs, aps, imu, extinput: which producers to start.

    Returns:
        The steps.
    """
    steps: list[Step] = []
    steps += _producer_off_writes()
    steps += [
        _w(Module.MUX, Mux.RUN, 0),
        _w(Module.MUX, Mux.TIMESTAMP_RUN, 0),
        _w(Module.USB, Usb.RUN, 0),
        _w(Module.MUX, Mux.RUN_CHIP, 0),
        Sleep(START_BUFFER_CLEAR_SLEEP_US),
        ClearHalt(DATA_ENDPOINT),
        _w(Module.MUX, Mux.RUN_CHIP, 1),
        Sleep(START_BIAS_SETTLE_SLEEP_US),
        _w(Module.USB, Usb.RUN, 1),
        _w(Module.MUX, Mux.TIMESTAMP_RUN, 1),
        _w(Module.MUX, Mux.RUN, 1),
        Sleep(START_PRODUCERS_SLEEP_US),
    ]
    if dvs:
        steps.append(_w(Module.DVS, Dvs.RUN, 1))
    if aps:
        steps.append(_w(Module.APS, Aps.RUN, 1))
    if imu:
        steps += [
            _w(Module.IMU, Imu.RUN_ACCELEROMETER, 1),
            _w(Module.IMU, Imu.RUN_GYROSCOPE, 1),
            _w(Module.IMU, Imu.RUN_TEMPERATURE, 1),
        ]
    if extinput:
        steps.append(_w(Module.EXTINPUT, ExtInput.RUN_DETECTOR, 1))
    return steps


def stop_sequence() -> list[Step]:
    """``davisDataStop`` on the wire (§7.2): producers off, then MUX RUN, TIMESTAMP_RUN, USB RUN, RUN_CHIP off."""
    return _producer_off_writes() + [
        _w(Module.MUX, Mux.RUN, 0),
        _w(Module.MUX, Mux.TIMESTAMP_RUN, 0),
        _w(Module.USB, Usb.RUN, 0),
        _w(Module.MUX, Mux.RUN_CHIP, 0),
    ]


def timestamp_reset_pulse() -> MultipleWrite:
    """MUX TIMESTAMP_RESET impulse as libcaer sends it: one ``0xC2`` request with set then clear (§3)."""
    return MultipleWrite((_w(Module.MUX, Mux.TIMESTAMP_RESET, 1), _w(Module.MUX, Mux.TIMESTAMP_RESET, 0)))


def aps_snapshot_pulse() -> MultipleWrite:
    """APS snapshot impulse: one ``0xC2`` request with APS RUN set then cleared (§3)."""
    return MultipleWrite((_w(Module.APS, Aps.RUN, 1), _w(Module.APS, Aps.RUN, 0)))


def config_writes(steps: Iterable[Step]) -> list[ConfigWrite]:
    """Flatten a sequence to the register writes it sends (multiple writes expanded; sleeps/halts dropped)."""
    out: list[ConfigWrite] = []
    for step in steps:
        if isinstance(step, MultipleWrite):
            out += list(step.writes)
        elif isinstance(step, ConfigWrite):
            out.append(step)
    return out
