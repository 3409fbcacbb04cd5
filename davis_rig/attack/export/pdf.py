"""The tiled vector PDF of the pattern pieces (reportlab): an overview page, then one page per tile.

Page geometry is in PDF points (1 mm = 72 / 25.4 pt); all coordinates are absolute page coordinates. Black cells are
filled rectangles clipped to the piece's outline (even-odd, holes stay white), the outline is stroked in red (cut
line), tiles carry cut marks, registration marks towards their printed neighbours, labels and a 50 mm check bar.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from davis_rig.attack.export.grid import black_rectangles
from davis_rig.attack.export.pattern import PatternPiece
from davis_rig.attack.export.tiles import PAPER_SIZES_MM, Tile, plan_tiles, tile_label
from davis_rig.errors import MissingDependencyError, ShapeError

__all__ = ["CHECK_BAR_MM", "PT_PER_MM", "write_pattern_pdf"]

#: PDF points per millimetre.
PT_PER_MM = 72.0 / 25.4
#: Length of the scale-check bar on every page (mm).
CHECK_BAR_MM = 50.0


def _reportlab():
    try:
        from reportlab.pdfgen import canvas
    except ImportError as exc:
        raise MissingDependencyError("the PDF export needs reportlab: pip install 'davis_rig[export]'") from exc
    return canvas


@dataclass
class _Layout:
    paper: str
    margin_mm: float
    grid: np.ndarray
    pieces: list[PatternPiece]
    tiles: list[Tile] = field(default_factory=list)


def _mm(value):
    return value * PT_PER_MM


def _draw_cut_marks(c, x0, y0, x1, y1, gap=1.5, length=6.0):
    """Crop marks in the margin at the four corners of the rectangle (pt)."""
    c.setLineWidth(0.4)
    c.setStrokeColorRGB(0, 0, 0)
    g, ln = _mm(gap), _mm(length)
    for x, sx in ((x0, -1), (x1, 1)):
        for y, sy in ((y0, -1), (y1, 1)):
            c.line(x + sx * g, y, x + sx * (g + ln), y)
            c.line(x, y + sy * g, x, y + sy * (g + ln))


def _draw_registration(c, x, y, radius_mm=3.0, arm_mm=5.0):
    """Crosshair + circle centred on (x, y) (pt)."""
    c.setLineWidth(0.35)
    c.setStrokeColorRGB(0.0, 0.55, 0.9)
    r, a = _mm(radius_mm), _mm(arm_mm)
    c.circle(x, y, r, stroke=1, fill=0)
    c.line(x - a, y, x + a, y)
    c.line(x, y - a, x, y + a)


def _draw_check_bar(c, x, y, length_mm=CHECK_BAR_MM):
    """A stroked scale bar of ``length_mm`` with 10 mm ticks, left end at (x, y) (pt)."""
    c.setLineWidth(0.5)
    c.setStrokeColorRGB(0, 0, 0)
    c.line(x, y, x + _mm(length_mm), y)
    for k in range(int(length_mm // 10) + 1):
        tick = _mm(2.0 if k % 5 else 3.0)
        c.line(x + _mm(10 * k), y, x + _mm(10 * k), y + tick)
    c.setFont("Helvetica", 6)
    c.drawString(x + _mm(length_mm) + 4, y, f"{length_mm:g} mm: check the print scale")


def _outline_path(c, piece: PatternPiece, to_page):
    path = c.beginPath()
    for loop in piece.loops_uv:
        pts = to_page(piece.to_mm(loop))
        path.moveTo(*pts[0])
        for x, y in pts[1:]:
            path.lineTo(x, y)
        path.close()
    return path


def _cell_rects_mm(piece: PatternPiece, rects: np.ndarray, n: int) -> np.ndarray:
    """Black rectangles in piece mm: float64 [K, 4] (x0, y0, x1, y1)."""
    if len(rects) == 0:
        return np.zeros((0, 4))
    r0, c0, r1, c1 = rects.T
    xa, xb = piece.u_to_mm(c0 / n), piece.u_to_mm(c1 / n)
    ya, yb = piece.v_to_mm(1.0 - r1 / n), piece.v_to_mm(1.0 - r0 / n)
    return np.stack([np.minimum(xa, xb), ya, np.maximum(xa, xb), yb], axis=1)


def _joined_neighbours(tile: Tile, kept: set[tuple[int, int, int]]) -> dict[str, tuple[int, int]]:
    """Edge (``"top"``, ``"bottom"``, ``"left"``, ``"right"``) -> ``(row, col)`` of each neighbouring tile that is
    printed: ``kept`` holds ``(piece, row, col)`` of the printed tiles (:func:`plan_tiles` drops empty ones)."""
    neighbours = {
        "top": (tile.row - 1, tile.col), "bottom": (tile.row + 1, tile.col),
        "left": (tile.row, tile.col - 1), "right": (tile.row, tile.col + 1),
    }  # fmt: skip
    return {edge: rc for edge, rc in neighbours.items() if (tile.piece, *rc) in kept}


def _draw_tile(c, layout: _Layout, tile: Tile, page_no: int, num_pages: int, rects_mm: list[np.ndarray],
               kept: set[tuple[int, int, int]]):
    """One tile page; registration marks and "joins" labels only towards the printed tiles in ``kept``
    (``(piece, row, col)``)."""
    from reportlab.pdfgen.canvas import FILL_EVEN_ODD

    piece = layout.pieces[tile.piece]
    n = layout.grid.shape[0]
    m = _mm(layout.margin_mm)
    page_w, page_h = c._pagesize
    tx0, ty0 = m, m
    tx1, ty1 = m + _mm(tile.width_mm), m + _mm(tile.height_mm)

    def to_page(xy_mm):
        xy_mm = np.asarray(xy_mm, dtype=np.float64)
        return np.stack([m + _mm(xy_mm[..., 0] - tile.x0_mm), m + _mm(xy_mm[..., 1] - tile.y0_mm)], axis=-1)

    # black cells clipped to the tile and the piece outline
    c.saveState()
    clip = c.beginPath()
    clip.rect(tx0, ty0, tx1 - tx0, ty1 - ty0)
    c.clipPath(clip, stroke=0, fill=0)
    c.clipPath(_outline_path(c, piece, to_page), stroke=0, fill=0, fillMode=FILL_EVEN_ODD)
    c.setFillColorRGB(0, 0, 0)
    boxes = rects_mm[tile.piece]
    inside = ((boxes[:, 2] > tile.x0_mm) & (boxes[:, 0] < tile.x0_mm + tile.width_mm)
              & (boxes[:, 3] > tile.y0_mm) & (boxes[:, 1] < tile.y0_mm + tile.height_mm))  # fmt: skip
    for x0, y0, x1, y1 in boxes[inside]:
        (px0, py0), (px1, py1) = to_page([[x0, y0], [x1, y1]])
        c.rect(px0, py0, px1 - px0, py1 - py0, stroke=0, fill=1)
    c.restoreState()
    # cut line (piece outline), clipped to the tile
    c.saveState()
    clip = c.beginPath()
    clip.rect(tx0, ty0, tx1 - tx0, ty1 - ty0)
    c.clipPath(clip, stroke=0, fill=0)
    c.setStrokeColorRGB(0.85, 0.0, 0.0)
    c.setLineWidth(0.6)
    c.drawPath(_outline_path(c, piece, to_page), stroke=1, fill=0)
    c.restoreState()
    # tile frame, cut marks, registration marks
    c.saveState()
    c.setStrokeColorRGB(0.6, 0.6, 0.6)
    c.setLineWidth(0.25)
    c.setDash(2, 2)
    c.rect(tx0, ty0, tx1 - tx0, ty1 - ty0, stroke=1, fill=0)
    c.restoreState()
    _draw_cut_marks(c, tx0, ty0, tx1, ty1)
    c.setFont("Helvetica", 7)
    c.setFillColorRGB(0, 0, 0)
    for edge, (r, col) in _joined_neighbours(tile, kept).items():
        text = f"joins {piece.name} {tile_label(r, col)}"
        if edge in ("top", "bottom"):
            y = ty1 if edge == "top" else ty0
            for f in (0.25, 0.75):
                _draw_registration(c, tx0 + f * (tx1 - tx0), y)
            c.drawCentredString((tx0 + tx1) / 2, y + 4 if edge == "top" else y - 10, text)
        else:
            x = tx0 if edge == "left" else tx1
            for f in (0.25, 0.75):
                _draw_registration(c, x, ty0 + f * (ty1 - ty0))
            c.saveState()
            c.translate(x - 4 if edge == "left" else x + 10, (ty0 + ty1) / 2)
            c.rotate(90)
            c.drawCentredString(0, 0, text)
            c.restoreState()
    # labels
    c.setFillColorRGB(0, 0, 0)
    c.setFont("Helvetica-Bold", 9)
    c.drawString(tx0, page_h - m + _mm(5), f"{piece.name}  tile {tile.label}")
    c.setFont("Helvetica", 7)
    c.drawString(tx0 + _mm(45), page_h - m + _mm(5),
                 f"row {tile.row + 1}/{tile.rows}, column {tile.col + 1}/{tile.cols}  |  "
                 f"{n}x{n} grid, cell {piece.cell_mm(n):.2f} mm{'  |  mirrored' if piece.mirrored else ''}")
    c.drawRightString(tx1, page_h - m + _mm(5), f"page {page_no}/{num_pages}")
    c.drawString(tx0, _mm(3), f"{layout.paper}, print at 100 % (no fit to page). Red: cut line. Blue: registration.")
    _draw_check_bar(c, tx1 - _mm(CHECK_BAR_MM) - _mm(45), _mm(4))


def _draw_overview(c, layout: _Layout, num_pages: int, title: str):
    from reportlab.pdfgen.canvas import FILL_EVEN_ODD

    page_w, page_h = c._pagesize
    m = _mm(layout.margin_mm)
    n = layout.grid.shape[0]
    c.setFont("Helvetica-Bold", 13)
    c.drawString(m, page_h - m, title)
    c.setFont("Helvetica", 8)
    y = page_h - m - 16
    lines = [f"{n}x{n} black/white grid, {len(layout.pieces)} pieces, {num_pages} pages ({layout.paper}); "
             "print every page at 100 % (no fit to page) and check the 50 mm bar.",
             "Cut each tile at the corner marks, butt tiles together matching the blue registration marks and "
             "the 'joins' labels, then cut the piece along the red line."]
    for piece in layout.pieces:
        pages = [t for t in layout.tiles if layout.pieces[t.piece] is piece]
        stretch = piece.stretch_quartiles
        lines.append(f"{piece.name}: {piece.width_mm:.0f} x {piece.height_mm:.0f} mm, cell {piece.cell_mm(n):.2f} mm, "
                     f"scale {piece.mm_per_uv:.1f} mm/UV (body stretch quartiles {stretch[0]:.0f}/{stretch[1]:.0f}/"
                     f"{stretch[2]:.0f}), tiles {', '.join(t.label for t in pages)}")
    import textwrap

    for line in lines:
        for part in textwrap.wrap(line, 135, subsequent_indent="    "):
            c.drawString(m, y, part)
            y -= 11
    # miniature of every piece with its tile grid
    top = y - 10
    area_w = page_w - 2 * m
    area_h = top - m - 30
    extents = []  # per piece: (x_min, x_max, y_min, y_max) of the piece and its tiles, mm
    for index, piece in enumerate(layout.pieces):
        own = [t for t in layout.tiles if t.piece == index]
        extents.append((min([0.0] + [t.x0_mm for t in own]), max([piece.width_mm] + [t.x0_mm + t.width_mm for t in own]),
                        min([0.0] + [t.y0_mm for t in own]), max([piece.height_mm] + [t.y0_mm + t.height_mm for t in own])))
    total_w = sum(e[1] - e[0] for e in extents) + 20 * (len(layout.pieces) - 1)
    max_h = max(e[3] - e[2] for e in extents)
    k = min(area_w / _mm(total_w), area_h / _mm(max_h))  # page pt per piece pt
    x = m
    rects = black_rectangles(layout.grid)
    for index, piece in enumerate(layout.pieces):
        ext = extents[index]

        def to_page(xy_mm, x=x, ext=ext):
            xy_mm = np.asarray(xy_mm, dtype=np.float64)
            return np.stack([x + k * _mm(xy_mm[..., 0] - ext[0]),
                             top - k * _mm(max_h) + k * _mm(xy_mm[..., 1] - ext[2])], axis=-1)

        c.saveState()
        c.clipPath(_outline_path(c, piece, to_page), stroke=0, fill=0, fillMode=FILL_EVEN_ODD)
        c.setFillColorRGB(0.15, 0.15, 0.15)
        for x0, y0, x1, y1 in _cell_rects_mm(piece, rects, n):
            (a, b), (d, e) = to_page([[x0, y0], [x1, y1]])
            c.rect(a, b, d - a, e - b, stroke=0, fill=1)
        c.restoreState()
        c.setStrokeColorRGB(0.85, 0, 0)
        c.setLineWidth(0.5)
        c.drawPath(_outline_path(c, piece, to_page), stroke=1, fill=0)
        c.setStrokeColorRGB(0.0, 0.55, 0.9)
        c.setLineWidth(0.3)
        c.setFont("Helvetica", 5)
        for tile in layout.tiles:
            if tile.piece != index:
                continue
            (a, b), (d, e) = to_page([[tile.x0_mm, tile.y0_mm], [tile.x0_mm + tile.width_mm, tile.y0_mm + tile.height_mm]])
            c.rect(a, b, d - a, e - b, stroke=1, fill=0)
            c.drawCentredString((a + d) / 2, (b + e) / 2, tile.label)
        c.setFont("Helvetica-Bold", 7)
        c.drawString(x, top - k * _mm(max_h) - 22, piece.name)
        x += k * _mm(ext[1] - ext[0] + 20)
    _draw_check_bar(c, m, _mm(6))


def write_pattern_pdf(
    grid: np.ndarray,
    pieces: Sequence[PatternPiece],
    path: str | Path,
    paper: str = "A4",
    margin_mm: float = 12.0,
    title: str = "davis_rig adversarial texture: pattern pieces",
) -> list[Tile]:
    """Write the tiled vector PDF of the pattern pieces (page 1 overview, then one page per tile).

    Args:
        grid: float [n, n], 1 = white, 0 = black (row 0 = top of the texture, high v).
        pieces: from :func:`pattern_pieces`.
        path: output ``.pdf``.
        paper: ``"A4"`` or ``"A3"``.
        margin_mm: page margin (tile area = page - 2 margins).
        title: overview title.

    Returns:
        The tiles, in page order (page ``i + 2`` holds ``tiles[i]``).

    Raises:
        ShapeError: grid not square. ValueError: no pieces, unknown paper. MissingDependencyError: reportlab.
    """
    canvas = _reportlab()
    grid = np.asarray(grid, dtype=np.float64)
    if grid.ndim != 2 or grid.shape[0] != grid.shape[1]:
        raise ShapeError(f"grid must be square [n, n], got {grid.shape}")
    if not pieces:
        raise ValueError("no pattern pieces to write")
    if paper not in PAPER_SIZES_MM:
        raise ValueError(f"paper must be one of {sorted(PAPER_SIZES_MM)}, got {paper!r}")
    layout = _Layout(paper=paper, margin_mm=float(margin_mm), grid=grid, pieces=list(pieces))
    for index, piece in enumerate(layout.pieces):
        layout.tiles += plan_tiles(piece, paper, margin_mm, index)
    n = grid.shape[0]
    rects = black_rectangles(grid)
    rects_mm = [_cell_rects_mm(piece, rects, n) for piece in layout.pieces]
    num_pages = len(layout.tiles) + 1
    portrait = tuple(_mm(v) for v in PAPER_SIZES_MM[paper])
    c = canvas.Canvas(str(path), pagesize=portrait, pageCompression=1)
    c.setTitle(title)
    c.setCreator("davis_rig.attack.export")
    _draw_overview(c, layout, num_pages, title)
    c.showPage()
    kept = {(tile.piece, tile.row, tile.col) for tile in layout.tiles}
    for page_no, tile in enumerate(layout.tiles, start=2):
        c.setPageSize(portrait[::-1] if tile.landscape else portrait)
        _draw_tile(c, layout, tile, page_no, num_pages, rects_mm, kept)
        c.showPage()
    c.save()
    return layout.tiles
