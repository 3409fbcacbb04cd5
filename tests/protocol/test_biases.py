"""Bias encodings (PROTOCOL.md §6.1) and the 28 DAVIS346 defaults of §6.2, value by value."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from davis_rig.errors import ProtocolError
from davis_rig.protocol.biases import (
    DAVIS346_BIAS_PARAMS,
    DAVIS346_DEFAULT_BIASES,
    CoarseFineBias,
    ShiftedSourceBias,
    VdacBias,
    bias_kind,
    bias_param,
    decode_bias,
)

# (param, name, register value) copied from the table in PROTOCOL.md §6.2, in libcaer's write order.
TABLE_6_2 = [
    (0, "APSOVERFLOWLEVEL", 0x019B), (1, "APSCAS", 0x0195), (2, "ADCREFHIGH", 0x01E0), (3, "ADCREFLOW", 0x01C1),
    (4, "ADCTESTVOLTAGE", 0x01D5), (8, "LOCALBUFBN", 0x5A4F), (9, "PADFOLLBN", 0x7D7E), (10, "DIFFBN", 0x427F),
    (11, "ONBN", 0x5FFF), (12, "OFFBN", 0x401F), (13, "PIXINVBN", 0x690F), (14, "PRBP", 0x23AD),
    (15, "PRSFBP", 0x110D), (16, "REFRBP", 0x419D), (17, "READOUTBUFBP", 0x614D), (18, "APSROSFBN", 0x6DBF),
    (19, "ADCCOMPBP", 0x514D), (20, "COLSELLOWBN", 0x001F), (21, "DACBUFBP", 0x63CD), (22, "LCOLTIMEOUTBN", 0x531F),
    (23, "AEPDBN", 0x65BF), (24, "AEPUXBP", 0x450D), (25, "AEPUYBP", 0x798D), (26, "IFREFRBN", 0x5FFF),
    (27, "IFTHRBN", 0x5FFF), (34, "BIASBUFFER", 0x5FEF), (35, "SSP", 0x8410), (36, "SSN", 0x8410),
]


def test_defaults_have_28_entries_in_libcaer_order():
    assert len(DAVIS346_DEFAULT_BIASES) == 28
    assert [(e.param, e.name) for e in DAVIS346_DEFAULT_BIASES] == [(p, n) for p, n, _ in TABLE_6_2]


@pytest.mark.parametrize("param,name,value", TABLE_6_2, ids=[n for _, n, _ in TABLE_6_2])
def test_every_default_bias_encodes_to_the_documented_hex(param, name, value):
    entry = {e.name: e for e in DAVIS346_DEFAULT_BIASES}[name]
    assert entry.param == param == DAVIS346_BIAS_PARAMS[name] == bias_param(name.lower())
    assert entry.bias.encode() == value
    assert decode_bias(param, value) == entry.bias


def test_vdac_fields():
    assert VdacBias(27, 6).encode() == 27 | 6 << 6
    assert VdacBias.decode(0x01E0) == VdacBias(voltage=32, current=7)
    assert VdacBias(32, 7).voltage_v == pytest.approx(1.65)


def test_coarse_fine_flag_bits():
    assert CoarseFineBias(0, 0, enabled=True, sex_n=False, type_normal=False, current_level_normal=False).encode() == 1
    assert CoarseFineBias(0, 0, enabled=False, sex_n=True, type_normal=False, current_level_normal=False).encode() == 2
    assert CoarseFineBias(0, 0, enabled=False, sex_n=False, type_normal=True, current_level_normal=False).encode() == 4
    assert CoarseFineBias(0, 0, enabled=False, sex_n=False, type_normal=False, current_level_normal=True).encode() == 8
    assert CoarseFineBias(7, 255, False, False, False, False).encode() == 0x7FF0
    assert CoarseFineBias(5, 255).current_pa == pytest.approx(387500.0)


def test_shifted_source_fields():
    ss = ShiftedSourceBias(ref_value=1, reg_value=33)
    assert ss.encode() == 0x8410
    assert ShiftedSourceBias(0, 0, operating_mode=2, voltage_level=1).encode() == 0b0110
    assert ShiftedSourceBias.decode(0xFFFA) == ShiftedSourceBias(63, 63, operating_mode=2, voltage_level=2)
    with pytest.raises(ProtocolError, match="voltage level must be an integer in 0..2, got 3"):
        ShiftedSourceBias.decode(0xFFFE)


def test_bias_kinds_and_validation():
    assert bias_kind(4) is VdacBias
    assert bias_kind(34) is CoarseFineBias
    assert bias_kind(35) is ShiftedSourceBias
    with pytest.raises(ProtocolError, match="not a DAVIS346 bias address: 5"):
        bias_kind(5)
    with pytest.raises(ProtocolError, match="unknown DAVIS346 bias"):
        bias_param("NOPE")
    with pytest.raises(ProtocolError, match="0..63"):
        VdacBias(64, 0)
    with pytest.raises(ProtocolError, match="0..255"):
        CoarseFineBias(0, 256)
    with pytest.raises(ProtocolError, match="0..511"):
        VdacBias.decode(0x200)


@given(st.integers(0, 63), st.integers(0, 7))
def test_vdac_round_trip(voltage, current):
    bias = VdacBias(voltage, current)
    assert VdacBias.decode(bias.encode()) == bias and bias.encode() < 1 << 9


@given(st.integers(0, 7), st.integers(0, 255), st.booleans(), st.booleans(), st.booleans(), st.booleans())
def test_coarse_fine_round_trip(coarse, fine, enabled, sex_n, type_normal, level_normal):
    bias = CoarseFineBias(coarse, fine, enabled, sex_n, type_normal, level_normal)
    assert CoarseFineBias.decode(bias.encode()) == bias and bias.encode() < 1 << 15


@given(st.integers(0, 63), st.integers(0, 63), st.integers(0, 2), st.integers(0, 2))
def test_shifted_source_round_trip(ref, reg, mode, level):
    bias = ShiftedSourceBias(ref, reg, mode, level)
    assert ShiftedSourceBias.decode(bias.encode()) == bias and bias.encode() < 1 << 16
