"""Tiling a pattern piece onto pages: the orientation with fewer non-empty tiles, the piece centred on the grid.

Tiles are labelled by row letter (A, B, ... from the top) and column number (``B3``); tiles that hold no part of the
piece are dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from davis_rig.attack.export.pattern import PatternPiece

__all__ = ["PAPER_SIZES_MM", "Tile", "plan_tiles", "tile_label"]

#: Paper sizes (width, height) in mm, portrait.
PAPER_SIZES_MM: dict[str, tuple[float, float]] = {"A4": (210.0, 297.0), "A3": (297.0, 420.0)}
_ROW_LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"


@dataclass(frozen=True)
class Tile:
    """One page of one piece.

    Attributes:
        piece: index into the piece list.
        row, col: tile position (row 0 = top, col 0 = left); ``label`` = row letter + column number (``B3``).
        rows, cols: the piece's tile grid.
        x0_mm, y0_mm: bottom-left corner of the tile in piece coordinates (mm, x right, y up).
        width_mm, height_mm: the tile (printable area of the page).
        landscape: page orientation.
    """

    piece: int
    row: int
    col: int
    rows: int
    cols: int
    x0_mm: float
    y0_mm: float
    width_mm: float
    height_mm: float
    landscape: bool

    @property
    def label(self) -> str:
        """Row letter(s) + column number, e.g. ``B3`` (:func:`tile_label`)."""
        return tile_label(self.row, self.col)


def tile_label(row: int, col: int) -> str:
    """The label of tile ``(row, col)`` (0-based): row letters A ... Z, AA, AB, ... then the 1-based column (``B3``)."""
    letters = ""
    r = row
    while True:
        letters = _ROW_LETTERS[r % 26] + letters
        r = r // 26 - 1
        if r < 0:
            break
    return f"{letters}{col + 1}"


def _piece_raster(piece: PatternPiece, px_mm: float = 1.0, grow_px: int = 2) -> tuple[np.ndarray, float]:
    """Boolean occupancy image of a piece (rows from the top), grown by ``grow_px``; and its pixel size (mm)."""
    import cv2

    w = int(math.ceil(piece.width_mm / px_mm)) + 1
    h = int(math.ceil(piece.height_mm / px_mm)) + 1
    image = np.zeros((h, w), dtype=np.uint8)
    tri = piece.to_mm(piece.triangles_uv) / px_mm
    tri[..., 1] = piece.height_mm / px_mm - tri[..., 1]
    cv2.fillPoly(image, list(np.round(tri * 16).astype(np.int32)), 1, lineType=cv2.LINE_8, shift=4)
    if grow_px:
        image = cv2.dilate(image, np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8))
    return image.astype(bool), px_mm


def plan_tiles(piece: PatternPiece, paper: str = "A4", margin_mm: float = 12.0, index: int = 0) -> list[Tile]:
    """Tile a piece onto pages: the orientation with fewer non-empty tiles (portrait on ties), piece centred.

    Args:
        piece: the piece.
        paper: ``"A4"`` or ``"A3"``.
        margin_mm: page margin around the tile (labels and marks live there).
        index: the piece's index (stored in the tiles).

    Returns:
        The non-empty tiles, row-major.

    Raises:
        ValueError: unknown paper or a margin leaving no printable area.
    """
    if paper not in PAPER_SIZES_MM:
        raise ValueError(f"paper must be one of {sorted(PAPER_SIZES_MM)}, got {paper!r}")
    occupancy, px_mm = _piece_raster(piece)
    best = None
    for landscape in (False, True):
        pw, ph = PAPER_SIZES_MM[paper][::-1] if landscape else PAPER_SIZES_MM[paper]
        tw, th = pw - 2 * margin_mm, ph - 2 * margin_mm
        if tw <= 10 or th <= 10:
            raise ValueError(f"margin_mm={margin_mm} leaves no printable area on {paper}")
        cols = max(1, math.ceil(piece.width_mm / tw - 1e-9))
        rows = max(1, math.ceil(piece.height_mm / th - 1e-9))
        x_off = (cols * tw - piece.width_mm) / 2
        y_top = piece.height_mm + (rows * th - piece.height_mm) / 2
        tiles = []
        for r in range(rows):
            for c in range(cols):
                x0, y0 = c * tw - x_off, y_top - (r + 1) * th
                # occupancy rows count from the piece's top edge
                c0, c1 = max(0, int(math.floor(x0 / px_mm))), int(math.ceil((x0 + tw) / px_mm))
                r0 = max(0, int(math.floor((piece.height_mm - (y0 + th)) / px_mm)))
                r1 = int(math.ceil((piece.height_mm - y0) / px_mm))
                if occupancy[r0:r1, c0:c1].any():
                    tiles.append(Tile(index, r, c, rows, cols, x0, y0, tw, th, landscape))
        if best is None or len(tiles) < len(best):
            best = tiles
    return best
