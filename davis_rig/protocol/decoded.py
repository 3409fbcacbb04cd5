"""What the stream decoder delivers: the special and IMU6 record types, the decoded chunk and the loss counters.

:mod:`davis_rig.protocol.decoder` makes them (and exports them); the control-word pass
(:mod:`davis_rig.protocol.control_words`) and the APS/IMU assemblers count into the same :class:`DecoderStats`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Final

import numpy as np

from davis_rig.protocol.frames import ApsFrame
from davis_rig.types import EVENT_DTYPE

__all__ = ["IMU6_DTYPE", "SPECIAL_DTYPE", "DecodedChunk", "DecoderStats"]

#: A special event: time (µs, int64) and libcaer special type id (see :class:`~davis_rig.protocol.words.SpecialType`).
SPECIAL_DTYPE: Final = np.dtype([("t", "<i8"), ("type", "u1")])

#: One IMU6 sample: time µs; acceleration in g; angular rate in °/s; temperature in °C.
IMU6_DTYPE: Final = np.dtype(
    [
        ("t", "<i8"),
        ("accel_x_g", "<f4"),
        ("accel_y_g", "<f4"),
        ("accel_z_g", "<f4"),
        ("gyro_x_dps", "<f4"),
        ("gyro_y_dps", "<f4"),
        ("gyro_z_dps", "<f4"),
        ("temperature_c", "<f4"),
    ]
)


@dataclass
class DecoderStats:
    """Cumulative decoder counters (never reset by :meth:`~davis_rig.protocol.decoder.StreamDecoder.feed`).

    Attributes:
        words: 16-bit words decoded.
        odd_bytes_dropped: trailing bytes of odd-length transfers that were discarded (libcaer behaviour).
        unknown_words: words with an unhandled code/sub-code (reserved special 0, IMU9 start, specials ≥ 18,
            misc8 sub-codes ≥ 4, misc10 sub-codes ≠ 0).
        dvs_out_of_range: DVS address words outside the raw sensor size (Y ignored, X event dropped).
        aps_frames_dropped: frames started but never delivered (invalid column count at frame end, interrupted by a
            new frame start, a timestamp reset or a big wrap).
        aps_samples_dropped: ADC samples discarded (APS in ignore mode, or beyond the expected column/row counts).
        imu_samples_dropped: IMU samples started but not delivered (byte count ≠ 14 at IMU end, or interrupted).
        timestamp_resets: timestamp-reset specials seen.
        big_wraps: wraps that overflowed the 31-bit timestamp (libcaer TIMESTAMP_WRAP).
        non_monotonic_timestamps: DVS events earlier than the previous DVS event (a timestamp reset between the
            two restarts the comparison); the events are delivered unchanged.
    """

    words: int = 0
    odd_bytes_dropped: int = 0
    unknown_words: int = 0
    dvs_out_of_range: int = 0
    aps_frames_dropped: int = 0
    aps_samples_dropped: int = 0
    imu_samples_dropped: int = 0
    timestamp_resets: int = 0
    big_wraps: int = 0
    non_monotonic_timestamps: int = 0

    def copy(self) -> "DecoderStats":
        """Return an independent snapshot."""
        return DecoderStats(**self.as_dict())

    def as_dict(self) -> dict[str, int]:
        """Return the counters as a plain ``dict``."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class DecodedChunk:
    """Everything decoded from one :meth:`~davis_rig.protocol.decoder.StreamDecoder.feed` call.

    Attributes:
        events: DVS events, :data:`~davis_rig.types.EVENT_DTYPE` [N], in stream order.
        frames: completed valid APS frames, in order of their frame-end word.
        specials: :data:`SPECIAL_DTYPE` [M], in stream order.
        imu: :data:`IMU6_DTYPE` [K], in stream order.
    """

    events: np.ndarray = field(default_factory=lambda: np.empty(0, EVENT_DTYPE))
    frames: list[ApsFrame] = field(default_factory=list)
    specials: np.ndarray = field(default_factory=lambda: np.empty(0, SPECIAL_DTYPE))
    imu: np.ndarray = field(default_factory=lambda: np.empty(0, IMU6_DTYPE))

    def __len__(self) -> int:
        return int(self.events.shape[0])

    @staticmethod
    def concatenate(chunks) -> "DecodedChunk":
        """Join several chunks into one (arrays concatenated, frame lists joined)."""
        chunks = list(chunks)
        if not chunks:
            return DecodedChunk()
        return DecodedChunk(
            events=np.concatenate([c.events for c in chunks]),
            frames=[f for c in chunks for f in c.frames],
            specials=np.concatenate([c.specials for c in chunks]),
            imu=np.concatenate([c.imu for c in chunks]),
        )
