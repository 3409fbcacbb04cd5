"""Sensor geometry and orientation as reported by the camera's read-only configuration parameters."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping

from davis_rig.errors import ProtocolError
from davis_rig.types import DAVIS346_HW

__all__ = ["SensorLayout"]

_INVERT_XY_BIT = 0x04
_APS_FLIP_X_BIT = 0x02
_APS_FLIP_Y_BIT = 0x01
_IMU_FLIP_X_BIT = 0x04
_IMU_FLIP_Y_BIT = 0x02
_IMU_FLIP_Z_BIT = 0x01
_MAX_SIZE = 4096  # 12-bit address field


@dataclass(frozen=True)
class SensorLayout:
    """Raw sensor read-outs of a DAVIS camera (PROTOCOL.md §5), the decoder's view of the device.

    Field names follow ``device_info`` in the shared test vectors. Sizes are *raw device* values in pixels
    (used for range checks on the wire); the ``*_width`` / ``*_height`` properties give the user (output) size
    after the invertXY swap.

    Attributes:
        dvs_size_columns: DVS 0 SIZE_COLUMNS, px.
        dvs_size_rows: DVS 1 SIZE_ROWS, px.
        dvs_orientation_info: DVS 2 ORIENTATION_INFO (bit 2 = invertXY).
        aps_size_columns: APS 0 SIZE_COLUMNS, px.
        aps_size_rows: APS 1 SIZE_ROWS, px.
        aps_orientation_info: APS 2 ORIENTATION_INFO (bit 2 invertXY, bit 1 flipX, bit 0 flipY).
        imu_type: IMU 0 TYPE (0 none, 1 InvenSense 6050/6150, 2 InvenSense 9250, 3 Bosch BMI160).
        imu_orientation_info: IMU 1 ORIENTATION_INFO (bit 2 flipX, bit 1 flipY, bit 0 flipZ).
        chip_id: SYSINFO 1 chip identifier (DAVIS346: 4, 5 or 9).
        aps_color_filter: APS 3 COLOR_FILTER (0 = monochrome).
    """

    dvs_size_columns: int
    dvs_size_rows: int
    dvs_orientation_info: int
    aps_size_columns: int
    aps_size_rows: int
    aps_orientation_info: int
    imu_type: int
    imu_orientation_info: int
    chip_id: int
    aps_color_filter: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int):
                try:
                    coerced = int(value)
                except (TypeError, ValueError) as exc:
                    raise ProtocolError(f"{f.name}: expected an int, got {value!r}") from exc
                if coerced != value:
                    raise ProtocolError(f"{f.name}: expected an int, got {value!r}")
                object.__setattr__(self, f.name, coerced)
        for name in ("dvs_size_columns", "dvs_size_rows", "aps_size_columns", "aps_size_rows"):
            value = getattr(self, name)
            if not 1 <= value <= _MAX_SIZE:
                raise ProtocolError(f"{name}: expected 1..{_MAX_SIZE} px, got {value}")
        for name in ("dvs_orientation_info", "aps_orientation_info", "imu_orientation_info", "imu_type", "chip_id",
                     "aps_color_filter"):
            value = getattr(self, name)
            if value < 0:
                raise ProtocolError(f"{name}: expected >= 0, got {value}")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def davis346(cls) -> "SensorLayout":
        """DAVIS346B as assumed by the shared vectors: 346 columns × 260 rows, orientation 0, chip id 5, IMU type 1.

        The one home of the DAVIS346's read-outs (the virtual camera answers them by default).
        """
        rows, columns = DAVIS346_HW
        return cls(
            dvs_size_columns=columns,
            dvs_size_rows=rows,
            dvs_orientation_info=0,
            aps_size_columns=columns,
            aps_size_rows=rows,
            aps_orientation_info=0,
            imu_type=1,
            imu_orientation_info=0,
            chip_id=5,
            aps_color_filter=0,
        )

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> "SensorLayout":
        """Build a layout from a mapping with the field names (e.g. a test vector's ``device_info``).

        Unknown keys are ignored; ``aps_color_filter`` defaults to 0.

        Raises:
            ProtocolError: a required key is missing or a value is invalid.
        """
        names = [f.name for f in fields(cls)]
        missing = [n for n in names if n not in mapping and n != "aps_color_filter"]
        if missing:
            raise ProtocolError(f"device info: missing keys {missing}, got keys {sorted(mapping)}")
        return cls(**{n: mapping[n] for n in names if n in mapping})

    def to_dict(self) -> dict[str, int]:
        """Return the raw fields as a plain ``dict`` (round-trips through :meth:`from_mapping`)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    # ------------------------------------------------------------------ derived orientation
    @property
    def dvs_invert_xy(self) -> bool:
        """True when the device's DVS row address is the output x (ORIENTATION_INFO bit 2)."""
        return bool(self.dvs_orientation_info & _INVERT_XY_BIT)

    @property
    def aps_invert_xy(self) -> bool:
        """True when APS device columns become output rows (ORIENTATION_INFO bit 2)."""
        return bool(self.aps_orientation_info & _INVERT_XY_BIT)

    @property
    def aps_flip_x(self) -> bool:
        """True when the APS column counter runs backwards (ORIENTATION_INFO bit 1)."""
        return bool(self.aps_orientation_info & _APS_FLIP_X_BIT)

    @property
    def aps_flip_y(self) -> bool:
        """True when the APS row counter runs backwards (ORIENTATION_INFO bit 0)."""
        return bool(self.aps_orientation_info & _APS_FLIP_Y_BIT)

    @property
    def imu_flip_x(self) -> bool:
        """True when IMU x axes are negated (IMU ORIENTATION_INFO bit 2)."""
        return bool(self.imu_orientation_info & _IMU_FLIP_X_BIT)

    @property
    def imu_flip_y(self) -> bool:
        """True when IMU y axes are negated (IMU ORIENTATION_INFO bit 1)."""
        return bool(self.imu_orientation_info & _IMU_FLIP_Y_BIT)

    @property
    def imu_flip_z(self) -> bool:
        """True when IMU z axes are negated (IMU ORIENTATION_INFO bit 0)."""
        return bool(self.imu_orientation_info & _IMU_FLIP_Z_BIT)

    @property
    def dvs_width(self) -> int:
        """Output DVS width, px (SIZE_ROWS when invertXY, else SIZE_COLUMNS)."""
        return self.dvs_size_rows if self.dvs_invert_xy else self.dvs_size_columns

    @property
    def dvs_height(self) -> int:
        """Output DVS height, px."""
        return self.dvs_size_columns if self.dvs_invert_xy else self.dvs_size_rows

    @property
    def aps_width(self) -> int:
        """Output APS width, px (SIZE_ROWS when invertXY, else SIZE_COLUMNS)."""
        return self.aps_size_rows if self.aps_invert_xy else self.aps_size_columns

    @property
    def aps_height(self) -> int:
        """Output APS height, px."""
        return self.aps_size_columns if self.aps_invert_xy else self.aps_size_rows

    @property
    def dvs_hw(self) -> tuple[int, int]:
        """Output DVS size as ``(height, width)``, px."""
        return (self.dvs_height, self.dvs_width)

    @property
    def aps_hw(self) -> tuple[int, int]:
        """Output APS size as ``(height, width)``, px."""
        return (self.aps_height, self.aps_width)
