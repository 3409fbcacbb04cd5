"""IMU6 sample assembly from the stream's control words (PROTOCOL.md §12).

A sample starts with the IMU_START_6 special, carries a misc8 scale byte (which sensors are present, their full
scales) and 14 data bytes (big-endian signed 16-bit pairs: accelerometer x/y/z, temperature, gyroscope x/y/z; absent
sensors' bytes are skipped), and ends with the IMU_END special. :class:`ImuAssembler` keeps that state between
transfers for :mod:`davis_rig.protocol.control_words`.
"""

from __future__ import annotations

from typing import Final

from davis_rig.protocol.layout import SensorLayout
from davis_rig.protocol.words import IMU_TOTAL_COUNT, MISC8_BYTE_MASK

__all__ = ["ImuAssembler"]

# IMU present-sensor bits of the misc8 scale byte (bits 7-5 → values 4/2/1).
_IMU_ACCEL: Final = 4
_IMU_GYRO: Final = 2
_IMU_TEMP: Final = 1
#: IMU values arrive as big-endian byte pairs (misc8 payloads) of signed 16-bit integers.
_BYTE_BITS: Final = MISC8_BYTE_MASK.bit_length()
_INT16_SPAN: Final = 1 << 16


class ImuAssembler:
    """The IMU6 sample in progress, and the sensor's scales and orientation.

    Args:
        layout: the device's IMU type and axis flips.
        stats: the decoder's :class:`~davis_rig.protocol.decoded.DecoderStats` (``imu_samples_dropped`` counts
            here).
    """

    def __init__(self, layout: SensorLayout, stats):
        self.stats = stats
        self.ignore = True
        self.in_sample = False
        self.count = 0
        self.present = 0
        self.high_byte = 0
        self.values = [0.0] * 7  # ax, ay, az, temp, gx, gy, gz
        self.accel_lsb_per_g = 65536.0 / (4 * 2)
        self.gyro_lsb_per_dps = 65536.0 / (500 * 2)
        if layout.imu_type == 2:
            self.temp_scale, self.temp_offset = 333.87, 21.0
        else:
            self.temp_scale, self.temp_offset = 340.0, 35.0
        self.flip = (
            -1.0 if layout.imu_flip_x else 1.0,
            -1.0 if layout.imu_flip_y else 1.0,
            -1.0 if layout.imu_flip_z else 1.0,
        )

    def start(self) -> None:
        """IMU_START_6: a sample still in progress is dropped; the new one starts empty."""
        if self.in_sample and not self.ignore:
            self.stats.imu_samples_dropped += 1
        self.ignore = False
        self.in_sample = True
        self.count = 0
        self.present = 0
        self.values = [0.0] * 7

    def end(self, t: int) -> tuple | None:
        """IMU_END at stream time ``t`` µs: the sample as an :data:`~davis_rig.protocol.decoded.IMU6_DTYPE` row if
        exactly :data:`~davis_rig.protocol.words.IMU_TOTAL_COUNT` bytes came, else ``None`` (a drop is counted)."""
        if self.ignore:
            return None
        row = None
        if self.count == IMU_TOTAL_COUNT:
            v = self.values
            row = (t, v[0], v[1], v[2], v[4], v[5], v[6], v[3])
        else:
            self.stats.imu_samples_dropped += 1
        self.in_sample = False
        return row

    def interrupt(self) -> None:
        """Timestamp reset or big wrap: drop the sample in progress and ignore bytes until the next start."""
        if self.in_sample and not self.ignore:
            self.stats.imu_samples_dropped += 1
        self.ignore = True
        self.in_sample = False

    def scale(self, byte: int) -> None:
        """The misc8 scale byte: present sensors (bits 7-5), accelerometer (bits 3-2) and gyro (bits 1-0) ranges."""
        self.present = (byte >> 5) & 7
        accel_fs = (byte >> 2) & 3
        gyro_fs = byte & 3
        self.accel_lsb_per_g = 65536.0 / (4 * (1 << accel_fs))
        self.gyro_lsb_per_dps = 65536.0 / (500 * (1 << gyro_fs))
        if self.present & _IMU_ACCEL:
            self.count = 0
        elif self.present & _IMU_TEMP:
            self.count = 6
        elif self.present & _IMU_GYRO:
            self.count = 8
        else:
            self.count = IMU_TOTAL_COUNT

    def data(self, byte: int) -> None:
        """One data byte: the high byte of a value, or the low byte that completes it (scaled, axis-flipped)."""
        count = self.count
        if count >= IMU_TOTAL_COUNT:
            self.count = count + 1
            return
        if count % 2 == 0:
            self.high_byte = byte
        else:
            raw = (self.high_byte << _BYTE_BITS) | byte
            if raw >= _INT16_SPAN >> 1:  # signed 16-bit
                raw -= _INT16_SPAN
            slot = count // 2  # 0-2 accel, 3 temperature, 4-6 gyro
            if slot < 3:
                self.values[slot] = self.flip[slot] * raw / self.accel_lsb_per_g
                if slot == 2 and not self.present & _IMU_TEMP:
                    count += 2 if self.present & _IMU_GYRO else 8
            elif slot == 3:
                self.values[3] = raw / self.temp_scale + self.temp_offset
                if not self.present & _IMU_GYRO:
                    count += 6
            else:
                self.values[slot] = self.flip[slot - 4] * raw / self.gyro_lsb_per_dps
        self.count = count + 1
