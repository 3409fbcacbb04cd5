"""DAVIS bias generator encodings (VDAC, coarse-fine, shifted-source) and the DAVIS346 defaults.

PROTOCOL.md §6.1-§6.2 (libcaer ``src/davis.c`` bias generators, ``src/davis_common.h`` defaults). Each bias
encodes to a 16-bit number that is written as the 32-bit value of register ``(BIAS=5, param)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Union

from davis_rig.errors import ProtocolError

#: Nominal coarse currents of the coarse-fine bias generator, pA, indexed by coarse value 0..7.
COARSE_CURRENTS_PA = (11, 94, 756, 6054, 48437, 387500, 3100000, 24800000)

#: Shifted-source operating modes and voltage levels.
SS_MODE_SHIFTED_SOURCE, SS_MODE_HI_Z, SS_MODE_TIED_TO_RAIL = 0, 1, 2
SS_LEVEL_SPLIT_GATE, SS_LEVEL_SINGLE_DIODE, SS_LEVEL_DOUBLE_DIODE = 0, 1, 2


def _check_range(name: str, value: int, low: int, high: int) -> int:
    if isinstance(value, bool) or int(value) != value or not low <= value <= high:
        raise ProtocolError(f"{name} must be an integer in {low}..{high}, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class VdacBias:
    """Voltage (VDAC) bias: voltage in 1/64 of 3.3 V steps, output current level.

    Attributes:
        voltage: 0..63 (bits 0-5).
        current: 0..7 (bits 6-8).
    """

    voltage: int
    current: int

    def __post_init__(self) -> None:
        _check_range("VDAC voltage", self.voltage, 0, 63)
        _check_range("VDAC current", self.current, 0, 7)

    def encode(self) -> int:
        """Return the 16-bit register value."""
        return (self.voltage & 0x3F) | ((self.current & 0x07) << 6)

    @classmethod
    def decode(cls, value: int) -> "VdacBias":
        """Build from a register value (bits above 8 must be zero)."""
        value = _check_range("VDAC register value", value, 0, 0x1FF)
        return cls(voltage=value & 0x3F, current=(value >> 6) & 0x07)

    @property
    def voltage_v(self) -> float:
        """Output voltage, V (voltage/64 × 3.3 V)."""
        return self.voltage / 64.0 * 3.3


@dataclass(frozen=True)
class CoarseFineBias:
    """Current (coarse-fine) bias.

    Attributes:
        coarse: 0..7 (bits 12-14), selects the coarse current of :data:`COARSE_CURRENTS_PA`.
        fine: 0..255 (bits 4-11), fraction fine/255 of the coarse current.
        enabled: bit 0.
        sex_n: bit 1, True = N-type, False = P-type.
        type_normal: bit 2, True = normal, False = cascode.
        current_level_normal: bit 3, True = normal, False = low.
    """

    coarse: int
    fine: int
    enabled: bool = True
    sex_n: bool = True
    type_normal: bool = True
    current_level_normal: bool = True

    def __post_init__(self) -> None:
        _check_range("coarse", self.coarse, 0, 7)
        _check_range("fine", self.fine, 0, 255)

    def encode(self) -> int:
        """Return the 16-bit register value."""
        return (
            int(bool(self.enabled))
            | int(bool(self.sex_n)) << 1
            | int(bool(self.type_normal)) << 2
            | int(bool(self.current_level_normal)) << 3
            | (self.fine & 0xFF) << 4
            | (self.coarse & 0x07) << 12
        )

    @classmethod
    def decode(cls, value: int) -> "CoarseFineBias":
        """Build from a register value (bit 15 must be zero)."""
        value = _check_range("coarse-fine register value", value, 0, 0x7FFF)
        return cls(
            coarse=(value >> 12) & 0x07,
            fine=(value >> 4) & 0xFF,
            enabled=bool(value & 0x1),
            sex_n=bool(value & 0x2),
            type_normal=bool(value & 0x4),
            current_level_normal=bool(value & 0x8),
        )

    @property
    def current_pa(self) -> float:
        """Approximate nominal current, pA (coarse current × fine / 255)."""
        return COARSE_CURRENTS_PA[self.coarse] * self.fine / 255.0


@dataclass(frozen=True)
class ShiftedSourceBias:
    """Shifted-source bias.

    Attributes:
        ref_value: 0..63 (bits 4-9).
        reg_value: 0..63 (bits 10-15).
        operating_mode: bits 0-1; 0 shifted source, 1 high impedance, 2 tied to rail.
        voltage_level: bits 2-3; 0 split gate, 1 single diode, 2 double diode.
    """

    ref_value: int
    reg_value: int
    operating_mode: int = SS_MODE_SHIFTED_SOURCE
    voltage_level: int = SS_LEVEL_SPLIT_GATE

    def __post_init__(self) -> None:
        _check_range("shifted-source ref value", self.ref_value, 0, 63)
        _check_range("shifted-source reg value", self.reg_value, 0, 63)
        _check_range("shifted-source operating mode", self.operating_mode, 0, 2)
        _check_range("shifted-source voltage level", self.voltage_level, 0, 2)

    def encode(self) -> int:
        """Return the 16-bit register value."""
        return (
            (self.operating_mode & 0x3)
            | (self.voltage_level & 0x3) << 2
            | (self.ref_value & 0x3F) << 4
            | (self.reg_value & 0x3F) << 10
        )

    @classmethod
    def decode(cls, value: int) -> "ShiftedSourceBias":
        """Build from a register value."""
        value = _check_range("shifted-source register value", value, 0, 0xFFFF)
        return cls(
            ref_value=(value >> 4) & 0x3F,
            reg_value=(value >> 10) & 0x3F,
            operating_mode=value & 0x3,
            voltage_level=(value >> 2) & 0x3,
        )


Bias = Union[VdacBias, CoarseFineBias, ShiftedSourceBias]


def n_type(coarse: int, fine: int) -> CoarseFineBias:
    """libcaer's "N" preset: enabled, N-type, normal, normal current level."""
    return CoarseFineBias(coarse, fine, enabled=True, sex_n=True)


def p_type(coarse: int, fine: int) -> CoarseFineBias:
    """libcaer's "P" preset: enabled, P-type, normal, normal current level."""
    return CoarseFineBias(coarse, fine, enabled=True, sex_n=False)


def n_type_off(coarse: int, fine: int) -> CoarseFineBias:
    """libcaer's "N_OFF" preset: disabled, N-type, normal, normal current level."""
    return CoarseFineBias(coarse, fine, enabled=False, sex_n=True)


class BiasEntry(NamedTuple):
    """One named bias of a chip: register ``(BIAS, param)`` and its value."""

    name: str
    param: int
    bias: Bias


#: DAVIS346 bias register addresses (module 5), name → param (PROTOCOL.md §4).
DAVIS346_BIAS_PARAMS: dict[str, int] = {
    "APSOVERFLOWLEVEL": 0,
    "APSCAS": 1,
    "ADCREFHIGH": 2,
    "ADCREFLOW": 3,
    "ADCTESTVOLTAGE": 4,
    "LOCALBUFBN": 8,
    "PADFOLLBN": 9,
    "DIFFBN": 10,
    "ONBN": 11,
    "OFFBN": 12,
    "PIXINVBN": 13,
    "PRBP": 14,
    "PRSFBP": 15,
    "REFRBP": 16,
    "READOUTBUFBP": 17,
    "APSROSFBN": 18,
    "ADCCOMPBP": 19,
    "COLSELLOWBN": 20,
    "DACBUFBP": 21,
    "LCOLTIMEOUTBN": 22,
    "AEPDBN": 23,
    "AEPUXBP": 24,
    "AEPUYBP": 25,
    "IFREFRBN": 26,
    "IFTHRBN": 27,
    "BIASBUFFER": 34,
    "SSP": 35,
    "SSN": 36,
}

_VDAC_PARAMS = frozenset(range(0, 5))
_SHIFTED_SOURCE_PARAMS = frozenset({35, 36})

#: libcaer's DAVIS346 default biases, in the order ``sendDefaultConfig`` writes them (§6.2, 28 entries).
DAVIS346_DEFAULT_BIASES: tuple[BiasEntry, ...] = (
    BiasEntry("APSOVERFLOWLEVEL", 0, VdacBias(27, 6)),
    BiasEntry("APSCAS", 1, VdacBias(21, 6)),
    BiasEntry("ADCREFHIGH", 2, VdacBias(32, 7)),
    BiasEntry("ADCREFLOW", 3, VdacBias(1, 7)),
    BiasEntry("ADCTESTVOLTAGE", 4, VdacBias(21, 7)),
    BiasEntry("LOCALBUFBN", 8, n_type(5, 164)),
    BiasEntry("PADFOLLBN", 9, n_type_off(7, 215)),
    BiasEntry("DIFFBN", 10, n_type(4, 39)),
    BiasEntry("ONBN", 11, n_type(5, 255)),
    BiasEntry("OFFBN", 12, n_type(4, 1)),
    BiasEntry("PIXINVBN", 13, n_type(6, 144)),
    BiasEntry("PRBP", 14, p_type(2, 58)),
    BiasEntry("PRSFBP", 15, p_type(1, 16)),
    BiasEntry("REFRBP", 16, p_type(4, 25)),
    BiasEntry("READOUTBUFBP", 17, p_type(6, 20)),
    BiasEntry("APSROSFBN", 18, n_type(6, 219)),
    BiasEntry("ADCCOMPBP", 19, p_type(5, 20)),
    BiasEntry("COLSELLOWBN", 20, n_type(0, 1)),
    BiasEntry("DACBUFBP", 21, p_type(6, 60)),
    BiasEntry("LCOLTIMEOUTBN", 22, n_type(5, 49)),
    BiasEntry("AEPDBN", 23, n_type(6, 91)),
    BiasEntry("AEPUXBP", 24, p_type(4, 80)),
    BiasEntry("AEPUYBP", 25, p_type(7, 152)),
    BiasEntry("IFREFRBN", 26, n_type(5, 255)),
    BiasEntry("IFTHRBN", 27, n_type(5, 255)),
    BiasEntry("BIASBUFFER", 34, n_type(5, 254)),
    BiasEntry("SSP", 35, ShiftedSourceBias(ref_value=1, reg_value=33)),
    BiasEntry("SSN", 36, ShiftedSourceBias(ref_value=1, reg_value=33)),
)


def bias_kind(param: int) -> type:
    """The bias class a DAVIS346 bias register uses.

    Args:
        param: bias register address (module 5, 0..36).

    Returns:
        ``VdacBias``, ``CoarseFineBias`` or ``ShiftedSourceBias``.

    Raises:
        ProtocolError: ``param`` is not a DAVIS346 bias address.
    """
    if param not in DAVIS346_BIAS_PARAMS.values():
        raise ProtocolError(
            f"not a DAVIS346 bias address: {param} (expected one of {sorted(DAVIS346_BIAS_PARAMS.values())})"
        )
    if param in _VDAC_PARAMS:
        return VdacBias
    if param in _SHIFTED_SOURCE_PARAMS:
        return ShiftedSourceBias
    return CoarseFineBias


def bias_param(name: str) -> int:
    """DAVIS346 bias register address for a bias name (case-insensitive, e.g. ``"ONBN"``).

    Raises:
        ProtocolError: unknown name.
    """
    key = name.upper()
    if key not in DAVIS346_BIAS_PARAMS:
        raise ProtocolError(f"unknown DAVIS346 bias {name!r}; expected one of {', '.join(DAVIS346_BIAS_PARAMS)}")
    return DAVIS346_BIAS_PARAMS[key]


def decode_bias(param: int, value: int) -> Bias:
    """Decode a DAVIS346 bias register value into its bias object.

    Args:
        param: bias register address (module 5).
        value: register value (16 significant bits).

    Returns:
        The decoded bias; ``decode_bias(p, b.encode()) == b`` for every valid bias ``b`` of register ``p``.

    Raises:
        ProtocolError: unknown address or a value with bits the encoding does not use.
    """
    return bias_kind(param).decode(value)


def check_bias_for(param: int, bias: Bias) -> None:
    """Raise :class:`ProtocolError` unless ``bias`` has the kind register ``param`` expects."""
    kind = bias_kind(param)
    if not isinstance(bias, kind):
        raise ProtocolError(f"bias register {param} expects {kind.__name__}, got {type(bias).__name__}")
