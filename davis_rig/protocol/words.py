"""The DAVIS (logic 18) 16-bit USB word format: codes, sub-codes, masks and word builders.

The bulk stream of a DAVIS camera is a sequence of little-endian 16-bit words (PROTOCOL.md §8):

* bit 15 set: **timestamp word**, bits 14-0 = time in µs relative to the current wrap base;
* bit 15 clear: **event word**, bits 14-12 = code (0-7), bits 11-0 = data.

Builders return plain ``int`` (one word) or, for the ``*_words`` helpers, ``uint16`` arrays; they validate their
arguments and raise :class:`~davis_rig.errors.ProtocolError` on values that do not fit their field.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Final

import numpy as np

from davis_rig.errors import ProtocolError

__all__ = [
    "Code",
    "CODE_SPECIAL",
    "CODE_Y_ADDR",
    "CODE_ADC_SAMPLE",
    "CODE_MISC8",
    "CODE_MISC10",
    "CODE_TS_WRAP",
    "Special",
    "Misc8",
    "SpecialType",
    "TIMESTAMP_FLAG",
    "TIMESTAMP_MASK",
    "CODE_SHIFT",
    "DATA_MASK",
    "MISC8_SUB_SHIFT",
    "MISC8_SUB_MASK",
    "MISC8_BYTE_MASK",
    "MISC10_SUB_SHIFT",
    "MISC10_SUB_MASK",
    "MISC10_VALUE_MASK",
    "WRAP_TICKS_US",
    "WRAP_MAX_MULTIPLIER",
    "OVERFLOW_SHIFT",
    "APS_ADC_DEPTH",
    "APS_PIXEL_SHIFT",
    "APS_RESET_MIN",
    "APS_PIXEL_MAX",
    "IMU_TOTAL_COUNT",
    "timestamp_word",
    "wrap_word",
    "y_word",
    "x_word",
    "adc_word",
    "special_word",
    "misc8_word",
    "misc10_word",
    "words_to_bytes",
    "bytes_to_words",
]

#: Bit 15: the word is a timestamp word.
TIMESTAMP_FLAG: Final = 0x8000
#: Bits 14-0 of a timestamp word: µs relative to the wrap base.
TIMESTAMP_MASK: Final = 0x7FFF
#: Position of the 3-bit code in an event word.
CODE_SHIFT: Final = 12
#: Bits 11-0 of an event word: the data field.
DATA_MASK: Final = 0x0FFF
#: Position of the 4-bit sub-code in the data field of a misc 8-bit word (code 5).
MISC8_SUB_SHIFT: Final = 8
#: Largest misc 8-bit sub-code (4 bits).
MISC8_SUB_MASK: Final = 0xF
#: Bits 7-0 of a misc 8-bit word: the payload byte.
MISC8_BYTE_MASK: Final = 0xFF
#: Position of the 2-bit sub-code in the data field of a misc 10-bit word (code 6).
MISC10_SUB_SHIFT: Final = 10
#: Largest misc 10-bit sub-code (2 bits).
MISC10_SUB_MASK: Final = 0x3
#: Bits 9-0 of a misc 10-bit word: the payload.
MISC10_VALUE_MASK: Final = 0x3FF
#: One wrap-multiplier unit, µs (2**15).
WRAP_TICKS_US: Final = 0x8000
#: Largest wrap multiplier a code-7 word can carry (12-bit data field).
WRAP_MAX_MULTIPLIER: Final = 0x0FFF
#: libcaer's 64-bit time = (overflow << OVERFLOW_SHIFT) | 32-bit timestamp.
OVERFLOW_SHIFT: Final = 31
#: Bits per APS ADC sample.
APS_ADC_DEPTH: Final = 10
#: libcaer stores APS pixels as ``cds << APS_PIXEL_SHIFT`` (10-bit → 16-bit).
APS_PIXEL_SHIFT: Final = 16 - APS_ADC_DEPTH
#: Reset reads below this value force the pixel white (1023), libcaer's bright-light artefact rule.
APS_RESET_MIN: Final = 384
#: Largest CDS value (10 bits).
APS_PIXEL_MAX: Final = (1 << APS_ADC_DEPTH) - 1
#: Number of IMU data bytes in a complete IMU6 sample.
IMU_TOTAL_COUNT: Final = 14


class Code(IntEnum):
    """Event-word codes (bits 14-12 of a word whose bit 15 is clear)."""

    SPECIAL = 0
    Y_ADDR = 1
    X_ADDR_OFF = 2
    X_ADDR_ON = 3
    ADC_SAMPLE = 4
    MISC8 = 5
    MISC10 = 6
    TS_WRAP = 7


# Plain ints of the codes for the decoding loops: numpy compares an array with an IntEnum member as int64 (about 10x
# slower than with a plain int), and a per-word loop avoids enum attribute lookups.
CODE_SPECIAL: Final = int(Code.SPECIAL)
CODE_Y_ADDR: Final = int(Code.Y_ADDR)
CODE_ADC_SAMPLE: Final = int(Code.ADC_SAMPLE)
CODE_MISC8: Final = int(Code.MISC8)
CODE_MISC10: Final = int(Code.MISC10)
CODE_TS_WRAP: Final = int(Code.TS_WRAP)


class Special(IntEnum):
    """Wire sub-codes of special words (code 0) understood by logic 18 (PROTOCOL.md §8.1)."""

    RESERVED = 0
    TIMESTAMP_RESET = 1
    EXT_INPUT_FALLING = 2
    EXT_INPUT_RISING = 3
    EXT_INPUT_PULSE = 4
    IMU_START_6 = 5
    IMU_START_9 = 6  # old FPGA only; unhandled by libcaer 3.x
    IMU_END = 7
    APS_FRAME_START_GS = 8
    APS_FRAME_START_RS = 9
    APS_FRAME_END = 10
    APS_RESET_COLUMN_START = 11
    APS_SIGNAL_COLUMN_START = 12
    APS_COLUMN_END = 13
    APS_EXPOSURE_START = 14
    APS_EXPOSURE_END = 15
    EXT_GENERATOR_FALLING = 16
    EXT_GENERATOR_RISING = 17


class Misc8(IntEnum):
    """Sub-codes of misc 8-bit words (code 5, bits 11-8)."""

    IMU_DATA = 0
    APS_ROI_HIGH = 1
    APS_ROI_LOW = 2
    IMU_SCALE = 3


class SpecialType(IntEnum):
    """libcaer special-event *type* ids (``enum caer_special_event_types``), as reported by the decoder."""

    TIMESTAMP_WRAP = 0
    TIMESTAMP_RESET = 1
    EXTERNAL_INPUT_RISING_EDGE = 2
    EXTERNAL_INPUT_FALLING_EDGE = 3
    EXTERNAL_INPUT_PULSE = 4
    EXTERNAL_GENERATOR_RISING_EDGE = 12
    EXTERNAL_GENERATOR_FALLING_EDGE = 13
    APS_FRAME_START = 14
    APS_FRAME_END = 15
    APS_EXPOSURE_START = 16
    APS_EXPOSURE_END = 17


def _check(name: str, value: int, upper: int) -> int:
    value = int(value)
    if not 0 <= value <= upper:
        raise ProtocolError(f"{name}: expected 0..{upper}, got {value}")
    return value


def timestamp_word(t15_us: int) -> int:
    """Build a timestamp word.

    Args:
        t15_us: time relative to the wrap base, µs, 0..32767.

    Returns:
        The 16-bit word ``0x8000 | t15_us``.

    Raises:
        ProtocolError: ``t15_us`` outside 0..32767.
    """
    return TIMESTAMP_FLAG | _check("t15_us", t15_us, TIMESTAMP_MASK)


def _event_word(code: int, data: int) -> int:
    return (code << CODE_SHIFT) | data


def wrap_word(multiplier: int) -> int:
    """Build a timestamp-wrap word (code 7) adding ``multiplier × 32768`` µs to the wrap base.

    Args:
        multiplier: wrap count, 1..4095 (0 is legal on the wire but a no-op).

    Raises:
        ProtocolError: ``multiplier`` outside 0..4095.
    """
    return _event_word(Code.TS_WRAP, _check("multiplier", multiplier, WRAP_MAX_MULTIPLIER))


def y_word(y: int) -> int:
    """Build a DVS row-address word (code 1); ``y`` is the raw device row, 0..4095."""
    return _event_word(Code.Y_ADDR, _check("y", y, DATA_MASK))


def x_word(x: int, polarity: int) -> int:
    """Build a DVS column-address word (code 2 = OFF, 3 = ON); ``x`` is the raw device column, 0..4095.

    Args:
        x: raw device column.
        polarity: 0 (OFF) or 1 (ON).

    Raises:
        ProtocolError: ``x`` outside 0..4095 or ``polarity`` not in {0, 1}.
    """
    code = Code.X_ADDR_ON if _check("polarity", polarity, 1) else Code.X_ADDR_OFF
    return _event_word(code, _check("x", x, DATA_MASK))


def adc_word(value: int) -> int:
    """Build an APS ADC-sample word (code 4); ``value`` is the raw 10-bit sample (12 bits accepted)."""
    return _event_word(Code.ADC_SAMPLE, _check("value", value, DATA_MASK))


def special_word(sub_code: int) -> int:
    """Build a special word (code 0) with the given wire sub-code (see :class:`Special`), 0..4095."""
    return _event_word(Code.SPECIAL, _check("sub_code", sub_code, DATA_MASK))


def misc8_word(sub_code: int, byte: int) -> int:
    """Build a misc 8-bit word (code 5): sub-code 0..15 (see :class:`Misc8`), payload byte 0..255."""
    sub = _check("sub_code", sub_code, MISC8_SUB_MASK) << MISC8_SUB_SHIFT
    return _event_word(Code.MISC8, sub | _check("byte", byte, MISC8_BYTE_MASK))


def misc10_word(sub_code: int, value: int) -> int:
    """Build a misc 10-bit word (code 6): sub-code 0..3, payload 0..1023."""
    sub = _check("sub_code", sub_code, MISC10_SUB_MASK) << MISC10_SUB_SHIFT
    return _event_word(Code.MISC10, sub | _check("value", value, MISC10_VALUE_MASK))


def words_to_bytes(words) -> bytes:
    """Serialise 16-bit words to the little-endian byte stream the camera sends.

    Args:
        words: iterable of ints or an integer array, each 0..65535, shape [N].

    Returns:
        ``2 × N`` bytes.

    Raises:
        ProtocolError: a value outside 0..65535.
    """
    array = np.asarray(words if not isinstance(words, (list, tuple)) else np.array(words, dtype=np.int64))
    if array.size and (array.min() < 0 or array.max() > 0xFFFF):
        raise ProtocolError(f"words: expected values in 0..65535, got range {array.min()}..{array.max()}")
    return array.astype("<u2", copy=False).tobytes()


def bytes_to_words(data) -> np.ndarray:
    """View an even-length byte buffer as little-endian 16-bit words (zero-copy where possible).

    Args:
        data: bytes-like of even length.

    Returns:
        ``uint16`` array [len(data) // 2] (read-only when ``data`` is immutable).

    Raises:
        ProtocolError: odd length.
    """
    buffer = memoryview(data).cast("B")
    if len(buffer) % 2:
        raise ProtocolError(f"data: expected an even number of bytes, got {len(buffer)}")
    return np.frombuffer(buffer, dtype="<u2")
