"""Config encodings: 0xBF values, 0xC2 records, µs → cycles (PROTOCOL.md §3-§4)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from davis_rig.errors import ProtocolError
from davis_rig.protocol.config import (
    Aps,
    Clocks,
    ConfigWrite,
    Module,
    Mux,
    SysInfo,
    cycles_to_us,
    decode_multiple,
    decode_value,
    encode_multiple,
    encode_value,
    exposure_write,
    frame_interval_write,
    us_to_cycles,
)


def test_module_addresses_match_logic18():
    assert [Module.MUX, Module.DVS, Module.APS, Module.IMU, Module.EXTINPUT, Module.BIAS, Module.SYSINFO, Module.USB] == [
        0, 1, 2, 3, 4, 5, 6, 9]
    assert Module.CHIP == Module.BIAS == 5
    assert (SysInfo.LOGIC_VERSION, SysInfo.CHIP_IDENTIFIER, SysInfo.CLOCK_DEVIATION, SysInfo.LOGIC_PATCH) == (0, 1, 6, 7)
    assert (Aps.EXPOSURE, Aps.FRAME_INTERVAL, Aps.SNAPSHOT) == (12, 13, 100)


def test_encode_value_is_big_endian_worked_example():
    # §3: enable DVS -> data 00 00 00 01; logic version read returns 00 00 00 12 (= 18)
    assert encode_value(1) == bytes([0, 0, 0, 1])
    assert encode_value(True) == bytes([0, 0, 0, 1])
    assert encode_value(0x12345678) == bytes.fromhex("12345678")
    assert decode_value(bytes.fromhex("00000012")) == 18


def test_encode_value_rejects_out_of_range():
    with pytest.raises(ProtocolError, match="32-bit"):
        encode_value(-1)
    with pytest.raises(ProtocolError, match="32-bit"):
        encode_value(1 << 32)
    with pytest.raises(ProtocolError, match="expected 4 bytes, got 3"):
        decode_value(b"\x00\x00\x01")


def test_encode_multiple_timestamp_reset_pulse_worked_example():
    data = encode_multiple([ConfigWrite(Module.MUX, Mux.TIMESTAMP_RESET, 1), ConfigWrite(0, 2, 0)])
    assert data == bytes.fromhex("000200000001" "000200000000")
    assert decode_multiple(data, count=2) == [ConfigWrite(0, 2, 1), ConfigWrite(0, 2, 0)]


def test_encode_multiple_errors():
    with pytest.raises(ProtocolError, match="at least one"):
        encode_multiple([])
    with pytest.raises(ProtocolError, match="0..255"):
        encode_multiple([ConfigWrite(0, 256, 1)])
    with pytest.raises(ProtocolError, match="multiple of 6"):
        decode_multiple(b"\x00" * 7)
    with pytest.raises(ProtocolError, match="wValue says 3"):
        decode_multiple(b"\x00" * 12, count=3)


def test_us_to_cycles_matches_libcaer_float32_roundf():
    assert us_to_cycles(4000, 30) == 120000
    assert us_to_cycles(40000, 30) == 1200000
    # deviation: actual = nominal * dev / 1000
    assert us_to_cycles(1000, 30, 1010) == 30300
    # libcaer multiplies in float32: 8388607 * 30 = 251658210 is not representable, float32 gives 251658208
    assert us_to_cycles(8388607, 30) == int(np.float32(8388607) * np.float32(30.0)) == 251658208
    # round half away from zero (roundf), not banker's rounding: 0.5 us at 1 MHz -> 1 cycle, 2.5 -> 3
    assert us_to_cycles(0.5, 1) == 1
    assert us_to_cycles(2.5, 1) == 3
    assert cycles_to_us(120000, 30) == 4000


def test_us_to_cycles_rejects_bad_inputs():
    with pytest.raises(ProtocolError, match=">= 0"):
        us_to_cycles(-1, 30)
    with pytest.raises(ProtocolError, match="> 0 MHz"):
        us_to_cycles(1, 0)


def test_exposure_and_interval_writes_use_adc_clock_and_ranges():
    clocks = Clocks(logic_mhz=104, adc_mhz=30, usb_mhz=80, deviation=1000)
    assert exposure_write(4000, clocks) == ConfigWrite(2, 12, 120000)
    assert frame_interval_write(40000, clocks) == ConfigWrite(2, 13, 1200000)
    with pytest.raises(ProtocolError, match="0..4194303"):
        exposure_write(4194304, clocks)
    with pytest.raises(ProtocolError, match="0..8388607"):
        frame_interval_write(-1, clocks)
    with pytest.raises(ProtocolError, match="adc_mhz must be > 0"):
        Clocks(logic_mhz=1, adc_mhz=0, usb_mhz=1)


@given(st.lists(st.tuples(st.integers(0, 255), st.integers(0, 255), st.integers(0, 2**32 - 1)), min_size=1, max_size=20))
def test_multiple_write_round_trip(records):
    writes = [ConfigWrite(*r) for r in records]
    data = encode_multiple(writes)
    assert len(data) == 6 * len(writes)
    assert decode_multiple(data, len(writes)) == writes


@given(st.integers(0, 2**32 - 1))
def test_value_round_trip(value):
    assert decode_value(encode_value(value)) == value


@given(st.integers(0, 4_194_303), st.sampled_from([30, 50, 64]), st.integers(900, 1100))
def test_us_to_cycles_matches_float32_reference(us, clock_mhz, deviation):
    actual = np.float32(clock_mhz * (deviation / 1000.0))
    expected = int(np.floor(np.float64(np.float32(us) * actual) + 0.5))
    assert us_to_cycles(us, clock_mhz, deviation) == expected
