"""DAVIS346 wire protocol, pure (no USB, no torch): 16-bit word format, sensor layout, stream decoder and encoder.

Public API::

    from davis_rig.protocol import SensorLayout, StreamDecoder, StreamEncoder, ApsFrame

    decoder = StreamDecoder(SensorLayout.davis346())
    chunk = decoder.feed(transfer_bytes)      # DecodedChunk: events, frames, specials, imu
"""

from davis_rig.protocol.decoder import IMU6_DTYPE, SPECIAL_DTYPE, DecodedChunk, DecoderStats, StreamDecoder
from davis_rig.protocol.encoder import StreamEncoder, split_transfers
from davis_rig.protocol.frames import ApsFrame
from davis_rig.protocol.layout import SensorLayout
from davis_rig.protocol.words import SpecialType

__all__ = [
    "ApsFrame",
    "DecodedChunk",
    "DecoderStats",
    "IMU6_DTYPE",
    "SPECIAL_DTYPE",
    "SensorLayout",
    "SpecialType",
    "StreamDecoder",
    "StreamEncoder",
    "split_transfers",
]
