"""Export a black/white texture for the physical attack: print-ready vector PDF pattern pieces, PNGs, preview.

The paper prints the optimized texture on paper, cuts it into pieces per body part and assembles clothing
(appendix, fabrication). This module lays the texture out as **pattern pieces**, one per UV island of each
chosen body part (connected components of the part's UV triangles; the outline is the boundary of the
island's triangles), at physical scale, and tiles every piece onto A4 or A3 pages:

- **Scale** (mm per UV unit ``S``; a grid cell is ``S / n`` mm): by default from the body itself, per island,
  the median over its triangles of ``sqrt(3D area / UV area)`` of the rest-pose mesh of one body shape
  (``stretch="median"``; ``"area"`` uses the total-area ratio), times ``ease``. Or one user scale for all
  pieces: ``texture_mm`` (side of the whole UV square, the official code's 500/1000 mm) or ``cell_mm``.
- **Vector content**: black cells are filled rectangles (runs of cells merged), clipped to the piece's
  outline (even-odd, so holes stay white); white is the paper. The outline is stroked in red (cut line).
  The cell grid is uniform in UV (cell ``(i, j)`` spans ``u in [j/n, (j+1)/n]``, ``v in [1-(i+1)/n, 1-i/n]``);
  the 1024 x 1024 digital map rounds cell borders to whole texels (:func:`~davis_rig.attack.texture.cell_bounds_texels`),
  a difference below one texel.
- **Pages**: page 1 is an overview (pieces, sizes, cell sizes, tile grids, a 50 mm check bar). Every other
  page is one tile of one piece, exact physical scale (print at 100 %), with cut marks at the tile corners,
  registration marks (crosshair + circle centred on every edge shared with a neighbour tile, at 1/4 and
  3/4 of the edge), the tile label (rows A, B, ... from the top, columns 1, 2, ...), the labels of the
  neighbouring tiles, page number and a 50 mm scale bar. Tiles that hold no part of the piece are skipped.
  Page geometry is in PDF points (1 mm = 72 / 25.4 pt); all coordinates are absolute page coordinates.
- **Orientation**: the UV triangles of the bundled body wind counter-clockwise (v up) like the 3D faces seen
  from outside, so the printed side is the outside; an island with clockwise UVs is mirrored (``mirrored``).

:func:`export_texture` writes everything: ``pattern_<paper>.pdf``, ``texture_grid.png`` (n x n),
``texture_1024.png`` (nearest-upsampled and masked: white outside the parts, what the renderer sees),
``preview.png`` (front and back of the textured rest-pose body, rendered by :mod:`davis_rig.scene.renderer`)
and ``pattern.json`` (scales, sizes, pages). The PDF needs ``reportlab`` (extra ``export``); the preview needs
torch (skipped with a note in ``pattern.json`` when torch is missing).

Modules: :mod:`~davis_rig.attack.export.grid` (texture io, black rectangles), :mod:`~davis_rig.attack.export.pattern`
(pattern pieces), :mod:`~davis_rig.attack.export.tiles` (pages), :mod:`~davis_rig.attack.export.pdf` (the PDF),
:mod:`~davis_rig.attack.export.preview` (the render); their public names are importable from this package.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable

import numpy as np

from davis_rig.attack.export.grid import (
    MAX_GRID_CELLS,
    black_rectangles,
    grid_from_map,
    load_texture_grid,
    upsample,
    write_png,
)
from davis_rig.attack.export.pattern import DEFAULT_PARTS, PatternPiece, pattern_pieces
from davis_rig.attack.export.pdf import CHECK_BAR_MM, PT_PER_MM, write_pattern_pdf
from davis_rig.attack.export.preview import render_preview
from davis_rig.attack.export.tiles import PAPER_SIZES_MM, Tile, plan_tiles
from davis_rig.errors import MissingDependencyError, ShapeError

__all__ = [
    "CHECK_BAR_MM",
    "DEFAULT_PARTS",
    "MAX_GRID_CELLS",
    "PAPER_SIZES_MM",
    "PT_PER_MM",
    "PatternPiece",
    "Tile",
    "black_rectangles",
    "export_texture",
    "grid_from_map",
    "load_texture_grid",
    "pattern_pieces",
    "plan_tiles",
    "render_preview",
    "upsample",
    "write_pattern_pdf",
    "write_png",
]


def export_texture(
    grid: np.ndarray,
    out_dir: str | Path,
    parts: Iterable[str] = DEFAULT_PARTS,
    paper: str = "A4",
    texture_mm: float | None = None,
    cell_mm: float | None = None,
    shape_index: int = 0,
    stretch: str = "median",
    ease: float = 1.0,
    margin_mm: float = 12.0,
    preview: bool = True,
    map_size: int = 1024,
) -> dict[str, Path]:
    """Write the print PDF, the PNG textures, a preview render and ``pattern.json`` for a grid.

    Args:
        grid: float [n, n] (values > 0.5 are white; binarized here).
        out_dir: output directory (created if missing).
        parts: painted body parts (one or more pattern pieces each).
        paper: ``"A4"`` or ``"A3"``.
        texture_mm, cell_mm: optional user scale (see :func:`pattern_pieces`); default: the body's size.
        shape_index, stretch, ease: body scale options (see :func:`pattern_pieces`).
        margin_mm: page margin.
        preview: also render ``preview.png`` (needs torch; skipped with a note when torch is missing).
        map_size: side of the upsampled PNG map (paper: 1024).

    Returns:
        dict name -> path of the written files (``pdf``, ``grid_png``, ``map_png``, ``preview_png``, ``json``).
        Files of an earlier export into ``out_dir`` that this one does not rewrite (another paper's PDF, a map of
        another size, a preview) are removed.

    Raises:
        ShapeError: grid not square. ValueError: bad options. MissingDependencyError: reportlab missing.
    """
    grid = np.asarray(grid, dtype=np.float64)
    if grid.ndim != 2 or grid.shape[0] != grid.shape[1]:
        raise ShapeError(f"grid must be square [n, n], got {grid.shape}")
    grid = (grid > 0.5).astype(np.float32)
    n = grid.shape[0]
    parts = tuple(parts)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pieces = pattern_pieces(parts, shape_index=shape_index, stretch=stretch, ease=ease, texture_mm=texture_mm,
                            cell_mm=cell_mm, n_cells=n)
    written = {"pdf": out / f"pattern_{paper}.pdf"}
    tiles = write_pattern_pdf(grid, pieces, written["pdf"], paper=paper, margin_mm=margin_mm)
    from davis_rig.scene.masks import part_mask

    written["grid_png"] = write_png(out / "texture_grid.png", grid)
    mask = part_mask(parts, size=map_size)
    written["map_png"] = write_png(out / f"texture_{map_size}.png", np.where(mask, upsample(grid, map_size), 1.0))
    notes = []
    if preview:
        try:
            written["preview_png"] = write_png(out / "preview.png", render_preview(grid, parts, shape_index))
        except MissingDependencyError as exc:
            notes.append(f"preview skipped: {exc}")
    scale = "texture_mm" if texture_mm is not None else "cell_mm" if cell_mm is not None else f"body:{stretch}"
    info = {"grid_cells": n, "parts": list(parts), "paper": paper, "paper_mm": list(PAPER_SIZES_MM[paper]),
            "margin_mm": margin_mm, "scale": scale, "shape_index": shape_index, "ease": ease, "pages": len(tiles) + 1,
            "pieces": _pieces_info(pieces, tiles, n), "notes": notes}
    written["json"] = out / "pattern.json"
    written["json"].write_text(json.dumps(info, indent=2) + "\n")
    _remove_stale(out, set(written.values()))
    return written


def _remove_stale(out: Path, kept: set[Path]) -> None:
    """Remove this export's own files from an earlier export into ``out`` that this one did not rewrite (the other
    paper's PDF, a map of another size, a preview now skipped), so the folder never mixes two prints."""
    names = [*(f"pattern_{paper}.pdf" for paper in PAPER_SIZES_MM), "preview.png"]
    stale = [out / name for name in names] + [p for p in out.glob("texture_*.png") if p.stem[8:].isdigit()]
    for path in stale:
        if path not in kept and path.is_file():
            path.unlink()


def _pieces_info(pieces: list[PatternPiece], tiles: list[Tile], n_cells: int) -> list[dict]:
    """``pattern.json``'s record of every piece: size, scale, stretch and its tiles with their pages."""
    return [
        {
            "name": p.name, "part": p.part, "faces": int(len(p.face_ids)), "mm_per_uv": p.mm_per_uv,
            "cell_mm": p.cell_mm(n_cells), "width_mm": p.width_mm, "height_mm": p.height_mm, "mirrored": p.mirrored,
            "stretch_quartiles_mm_per_uv": list(p.stretch_quartiles),
            "tiles": [{"label": t.label, "page": i + 2, "landscape": t.landscape}
                      for i, t in enumerate(tiles) if t.piece == k],
        }
        for k, p in enumerate(pieces)
    ]  # fmt: skip
