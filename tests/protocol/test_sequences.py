"""Default config / start / stop sequences equal the documented libcaer ones (PROTOCOL.md §6.3, §6.4, §7)."""

from davis_rig.protocol.config import Clocks, ConfigWrite, DeviceFeatures
from davis_rig.protocol.sequences import (
    ClearHalt,
    MultipleWrite,
    Sleep,
    aps_snapshot_pulse,
    config_writes,
    default_chip_config,
    default_config_sequence,
    default_fpga_config,
    start_sequence,
    stop_sequence,
    timestamp_reset_pulse,
)

W = ConfigWrite
CLOCKS = Clocks(logic_mhz=100, adc_mhz=30, usb_mhz=80, deviation=1000)
ALL_FEATURES = DeviceFeatures(
    dvs_has_pixel_filter=True,
    dvs_has_background_activity_filter=True,
    dvs_has_roi_filter=True,
    dvs_has_skip_filter=True,
    dvs_has_polarity_filter=True,
    aps_has_global_shutter=True,
    extinput_has_generator=True,
)


def test_chip_config_matches_6_3():
    assert default_chip_config() == [
        W(5, 128, 0), W(5, 129, 0), W(5, 130, 0), W(5, 131, 0), W(5, 132, 0), W(5, 133, 0), W(5, 134, 0),
        W(5, 135, 0), W(5, 136, 1), W(5, 137, 0), W(5, 138, 1), W(5, 140, 0), W(5, 141, 0), W(5, 143, 1),
        W(5, 144, 0),
    ]


def test_fpga_config_with_every_feature_matches_6_4():
    got = default_fpga_config(
        dvs_size_xy=(346, 260), aps_size_xy=(346, 260), features=ALL_FEATURES, clocks=CLOCKS, imu_type=2
    )
    pixel_filter = []
    for n in range(8):
        pixel_filter += [W(1, 11 + 2 * n, 260), W(1, 12 + 2 * n, 346)]
    expected = (
        [W(0, 4, 1), W(0, 5, 1), W(1, 4, 0), W(1, 5, 0)]
        + pixel_filter
        + [W(1, 31, 1), W(1, 32, 8), W(1, 33, 0), W(1, 34, 1)]
        + [W(1, 41, 0), W(1, 42, 0), W(1, 43, 345), W(1, 44, 259)]
        + [W(1, 51, 0), W(1, 52, 5)]
        + [W(1, 61, 0), W(1, 62, 0), W(1, 63, 0)]
        + [W(2, 5, 1), W(5, 142, 1), W(2, 7, 1), W(2, 8, 0), W(2, 9, 0), W(2, 10, 345), W(2, 11, 259)]
        + [W(2, 12, 4000 * 30), W(2, 13, 40000 * 30)]
        + [W(3, 5, 0), W(3, 6, 1), W(3, 7, 1), W(3, 9, 1), W(3, 10, 1)]
        + [W(4, 1, 0), W(4, 2, 0), W(4, 3, 1), W(4, 4, 1), W(4, 5, 10 * 100)]
        + [W(4, 11, 0), W(4, 12, 1), W(4, 13, 10 * 100), W(4, 14, 5 * 100), W(4, 15, 0), W(4, 16, 0)]
    )
    assert got == expected


def test_fpga_config_without_optional_features_sends_no_optional_writes():
    got = default_fpga_config(
        dvs_size_xy=(346, 260), aps_size_xy=(346, 260), features=DeviceFeatures(), clocks=CLOCKS, imu_type=1
    )
    assert got == (
        [W(0, 4, 1), W(0, 5, 1), W(1, 4, 0), W(1, 5, 0)]
        + [W(2, 5, 1), W(2, 8, 0), W(2, 9, 0), W(2, 10, 345), W(2, 11, 259), W(2, 12, 120000), W(2, 13, 1200000)]
        + [W(3, 5, 0), W(3, 6, 1), W(3, 7, 1), W(3, 10, 1)]  # GYRO_DLPF (3, 9) only for IMU type 2
        + [W(4, 1, 0), W(4, 2, 0), W(4, 3, 1), W(4, 4, 1), W(4, 5, 1000)]
    )


def test_full_default_config_order_biases_chip_fpga_usb():
    steps = default_config_sequence(
        dvs_size_xy=(346, 260), aps_size_xy=(346, 260), features=DeviceFeatures(), clocks=CLOCKS, imu_type=1
    )
    assert all(isinstance(s, ConfigWrite) for s in steps)
    assert steps[0] == W(5, 0, 0x019B)
    assert steps[27] == W(5, 36, 0x8410)
    assert steps[28:43] == default_chip_config()
    # USB early packet delay: 8 x 125 us at the 80 MHz USB clock
    assert steps[-1] == W(9, 1, 8 * 125 * 80)
    assert len(steps) == 28 + 15 + 20 + 1


def test_start_sequence_matches_7_1():
    assert start_sequence() == [
        W(1, 3, 0), W(2, 4, 0), W(3, 2, 0), W(3, 3, 0), W(3, 4, 0), W(4, 0, 0), W(0, 0, 0), W(0, 1, 0), W(9, 0, 0),
        W(0, 3, 0),
        Sleep(10_000),
        ClearHalt(0x82),
        W(0, 3, 1), Sleep(200_000), W(9, 0, 1), W(0, 1, 1), W(0, 0, 1), Sleep(50_000),
        W(1, 3, 1), W(2, 4, 1), W(3, 2, 1), W(3, 3, 1), W(3, 4, 1), W(4, 0, 1),
    ]


def test_start_sequence_without_imu_omits_only_imu_run_writes():
    full = start_sequence()
    no_imu = start_sequence(imu=False)
    assert [s for s in full if not (isinstance(s, ConfigWrite) and s[:2] in {(3, 2), (3, 3), (3, 4)} and s[2] == 1)] == no_imu


def test_stop_sequence_matches_7_2():
    assert stop_sequence() == [
        W(1, 3, 0), W(2, 4, 0), W(3, 2, 0), W(3, 3, 0), W(3, 4, 0), W(4, 0, 0), W(0, 0, 0), W(0, 1, 0), W(9, 0, 0),
        W(0, 3, 0),
    ]


def test_pulses_are_single_multiple_writes():
    assert timestamp_reset_pulse() == MultipleWrite((W(0, 2, 1), W(0, 2, 0)))
    assert aps_snapshot_pulse() == MultipleWrite((W(2, 4, 1), W(2, 4, 0)))
    assert config_writes([timestamp_reset_pulse(), Sleep(5), W(1, 3, 1)]) == [W(0, 2, 1), W(0, 2, 0), W(1, 3, 1)]
