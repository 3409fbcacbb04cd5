"""DAVIS346 wire protocol, pure (no USB, no torch): 16-bit word format, sensor layout, stream decoder and encoder.

Public API::

    from davis_rig.protocol import SensorLayout, StreamDecoder, StreamEncoder, ApsFrame

    decoder = StreamDecoder(SensorLayout.davis346())
    chunk = decoder.feed(transfer_bytes)      # DecodedChunk: events, frames, specials, imu
    chunk = decoder.feed_many(transfers)      # same result as feeding one by one, less per-call overhead

    data = StreamEncoder(layout).encode(events, frames)   # the exact word stream a DAVIS346 would send
    transfers = split_transfers(data, 8192)
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
