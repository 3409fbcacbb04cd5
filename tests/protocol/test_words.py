"""Word builders and byte/word conversion (PROTOCOL.md §8 quick reference)."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import ProtocolError
from davis_rig.protocol.words import (
    adc_word,
    bytes_to_words,
    misc8_word,
    misc10_word,
    special_word,
    timestamp_word,
    words_to_bytes,
    wrap_word,
    x_word,
    y_word,
)


def test_builders_match_quick_reference():
    assert timestamp_word(100) == 0x8064
    assert timestamp_word(32767) == 0xFFFF
    assert y_word(259) == 0x1103
    assert x_word(345, 0) == 0x2159
    assert x_word(20, 1) == 0x3014
    assert adc_word(600) == 0x4258
    assert misc8_word(3, 0xE5) == 0x53E5
    assert misc8_word(2, 0x0A) == 0x520A
    assert misc10_word(0, 176) == 0x60B0
    assert misc10_word(3, 5) == 0x6C05
    assert wrap_word(4095) == 0x7FFF
    assert special_word(17) == 0x0011


@pytest.mark.parametrize(
    "call",
    [
        lambda: timestamp_word(32768),
        lambda: timestamp_word(-1),
        lambda: y_word(4096),
        lambda: x_word(1, 2),
        lambda: misc8_word(16, 0),
        lambda: misc8_word(0, 256),
        lambda: misc10_word(4, 0),
        lambda: wrap_word(4096),
    ],
)
def test_builders_reject_out_of_field_values(call):
    with pytest.raises(ProtocolError, match="expected"):
        call()


def test_little_endian_round_trip():
    data = words_to_bytes([0x8064, 0x100A, 0x3014])
    assert data == bytes.fromhex("6480" "0a10" "1430")
    assert bytes_to_words(data).tolist() == [0x8064, 0x100A, 0x3014]
    assert bytes_to_words(bytearray(data)).dtype == np.dtype("<u2")
    with pytest.raises(ProtocolError, match="even"):
        bytes_to_words(data[:-1])
    with pytest.raises(ProtocolError, match="0..65535"):
        words_to_bytes([70000])
