"""APS frames as assembled from the DAVIS word stream."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from davis_rig.errors import ShapeError

__all__ = ["ApsFrame"]


@dataclass(frozen=True, eq=False)
class ApsFrame:
    """One complete APS (grey-level) frame, libcaer-compatible.

    Attributes:
        pixels: ``uint16`` [rows, cols], the ROI only; libcaer 16-bit values = 10-bit CDS value << 6, row-major,
            origin upper-left (output orientation).
        position_x: output column of the ROI's left edge, px.
        position_y: output row of the ROI's top edge, px.
        t_start_of_frame_us: frame-start event time, µs (64-bit, overflow included).
        t_start_exposure_us: exposure-start time, µs.
        t_end_exposure_us: exposure-end time, µs.
        t_end_of_frame_us: frame-end time, µs.

    Raises:
        ShapeError: ``pixels`` is not a 2-D ``uint16`` array.
    """

    pixels: np.ndarray
    position_x: int = 0
    position_y: int = 0
    t_start_of_frame_us: int = 0
    t_start_exposure_us: int = 0
    t_end_exposure_us: int = 0
    t_end_of_frame_us: int = 0

    def __post_init__(self) -> None:
        pixels = np.asarray(self.pixels)
        if pixels.ndim != 2 or pixels.dtype != np.uint16:
            raise ShapeError(f"pixels: expected uint16 [rows, cols], got {pixels.dtype} {pixels.shape}")
        object.__setattr__(self, "pixels", pixels)
        for name in ("position_x", "position_y", "t_start_of_frame_us", "t_start_exposure_us", "t_end_exposure_us",
                     "t_end_of_frame_us"):
            object.__setattr__(self, name, int(getattr(self, name)))

    @property
    def t_exposure_mid_us(self) -> int:
        """libcaer's frame timestamp: ``SOE + (EOE - SOE) // 2``, µs (exposure midpoint, integer division)."""
        return self.t_start_exposure_us + (self.t_end_exposure_us - self.t_start_exposure_us) // 2

    @property
    def height(self) -> int:
        """ROI height, px."""
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        """ROI width, px."""
        return int(self.pixels.shape[1])

    @property
    def pixels_10bit(self) -> np.ndarray:
        """CDS values ``pixels >> 6``, ``uint16`` [rows, cols], 0..1023 (new array)."""
        return self.pixels >> 6

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ApsFrame):
            return NotImplemented
        return (
            self.position_x == other.position_x
            and self.position_y == other.position_y
            and self.t_start_of_frame_us == other.t_start_of_frame_us
            and self.t_start_exposure_us == other.t_start_exposure_us
            and self.t_end_exposure_us == other.t_end_exposure_us
            and self.t_end_of_frame_us == other.t_end_of_frame_us
            and self.pixels.shape == other.pixels.shape
            and bool(np.array_equal(self.pixels, other.pixels))
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return (
            f"ApsFrame({self.height}x{self.width} at ({self.position_x},{self.position_y}), "
            f"sof={self.t_start_of_frame_us} soe={self.t_start_exposure_us} eoe={self.t_end_exposure_us} "
            f"eof={self.t_end_of_frame_us} µs)"
        )
