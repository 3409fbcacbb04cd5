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
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from davis_rig.errors import ConfigError, FormatError, MissingDependencyError, ShapeError
from davis_rig.scene.body import PART_NAMES, BodyAsset

__all__ = [
    "MAX_GRID_CELLS",
    "PAPER_SIZES_MM",
    "PT_PER_MM",
    "PatternPiece",
    "Tile",
    "black_rectangles",
    "export_texture",
    "load_texture_grid",
    "pattern_pieces",
    "plan_tiles",
    "render_preview",
    "write_pattern_pdf",
]

#: Paper sizes (width, height) in mm, portrait.
PAPER_SIZES_MM: dict[str, tuple[float, float]] = {"A4": (210.0, 297.0), "A3": (297.0, 420.0)}
#: PDF points per millimetre.
PT_PER_MM = 72.0 / 25.4
#: Largest grid a square image is taken to be directly (larger images are upsampled maps).
MAX_GRID_CELLS = 256
#: Default paintable parts (the paper's full-body texture: upper body, arms, legs).
DEFAULT_PARTS: tuple[str, ...] = ("torso", "arms", "legs")
#: Length of the scale-check bar on every page (mm).
CHECK_BAR_MM = 50.0
_ROW_LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"


def _reportlab():
    try:
        from reportlab.pdfgen import canvas
    except ImportError as exc:
        raise MissingDependencyError("the PDF export needs reportlab: pip install 'davis_rig[export]'") from exc
    return canvas


# ---------------------------------------------------------------------------------------------- texture io
def _to_unit(image: np.ndarray, where: str) -> np.ndarray:
    if image.ndim == 3:
        if image.shape[2] not in (1, 3, 4):
            raise ShapeError(f"{where}: image must be grey, RGB or RGBA, got shape {image.shape}")
        image = image[..., :3].mean(axis=2) if image.shape[2] >= 3 else image[..., 0]
    if image.ndim != 2:
        raise ShapeError(f"{where}: texture must be a 2-D grid or image, got shape {image.shape}")
    if image.dtype == np.uint8:
        return image.astype(np.float64) / 255.0
    if image.dtype == np.uint16:
        return image.astype(np.float64) / 65535.0
    if np.issubdtype(image.dtype, np.bool_) or np.issubdtype(image.dtype, np.integer):
        return image.astype(np.float64)
    if np.issubdtype(image.dtype, np.floating):
        if not np.all(np.isfinite(image)):
            raise FormatError(f"{where}: texture has non-finite values")
        return image.astype(np.float64)
    raise FormatError(f"{where}: unsupported texture dtype {image.dtype}")


def _cells_of(size: int, n: int) -> np.ndarray:
    """Cell of every texel of a ``size`` map of an ``n`` grid (``floor(c * n / size)``)."""
    return (np.arange(size, dtype=np.int64) * n) // size


def grid_from_map(image: np.ndarray, n_cells: int) -> np.ndarray:
    """Black/white n x n grid of an upsampled square map: a cell is white when its mean value is > 0.5.

    Args:
        image: float [S, S] in [0, 1] with S >= n (cells as in :func:`upsample` / the renderer).
        n_cells: cells per side.

    Returns:
        float32 [n, n] of 0/1.
    """
    size = image.shape[0]
    cells = _cells_of(size, n_cells)
    sums = np.zeros((n_cells, n_cells))
    np.add.at(sums, (cells[:, None], cells[None, :]), image)
    counts = np.bincount(cells, minlength=n_cells).astype(np.float64)
    return ((sums / np.outer(counts, counts)) > 0.5).astype(np.float32)


def upsample(grid: np.ndarray, size: int = 1024) -> np.ndarray:
    """Nearest upsampling of an n x n grid to ``size x size`` (numpy twin of the torch ``upsample_grid``)."""
    cells = _cells_of(size, grid.shape[0])
    return grid[cells][:, cells]


def load_texture_grid(path: str | Path, n_cells: int | None = None) -> np.ndarray:
    """Read a texture (PNG/JPEG image or ``.npy``) as a black/white n x n grid (1 = white).

    A square image of at most :data:`MAX_GRID_CELLS` per side is the grid itself (unless ``n_cells`` says
    otherwise); a larger one is an upsampled map: its grid size is ``n_cells``, or detected as the smallest
    n whose nearest upsampling reproduces the binarized map exactly.

    Args:
        path: ``.png``/``.jpg``/``.bmp``/``.tif`` (8/16-bit grey or colour) or ``.npy`` (float in [0, 1],
            bool or integers 0/1) file.
        n_cells: grid cells per side, if known.

    Returns:
        float32 [n, n] of 0.0 (black) / 1.0 (white); a value > 0.5 (cell mean for maps) is white.

    Raises:
        FileNotFoundError: no such file. FormatError: unreadable file, non-square texture, or a map whose
        grid cannot be detected (pass ``n_cells``). ConfigError: bad n_cells.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"texture not found: {path}")
    if path.suffix.lower() == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise FormatError(f"{path}: not a readable .npy array ({exc})") from exc
        raw = np.squeeze(raw)
    else:
        import cv2

        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise FormatError(f"{path}: not a readable image")
        if raw.ndim == 3 and raw.shape[2] >= 3:
            raw = raw[..., [2, 1, 0]]  # BGR -> RGB (mean is the same; keeps the channel order honest)
    image = _to_unit(np.asarray(raw), str(path))
    if image.shape[0] != image.shape[1]:
        raise FormatError(f"{path}: texture must be square, got {image.shape[0]} x {image.shape[1]}")
    size = image.shape[0]
    if n_cells is not None:
        n = int(n_cells)
        if not 1 <= n <= min(size, MAX_GRID_CELLS):
            raise ConfigError("n_cells", f"expected an integer in [1, {min(size, MAX_GRID_CELLS)}] for a {size}^2 "
                                         f"texture, got {n_cells}")
        return grid_from_map(image, n) if n != size else (image > 0.5).astype(np.float32)
    if size <= MAX_GRID_CELLS:
        return (image > 0.5).astype(np.float32)
    binary = (image > 0.5).astype(np.float32)
    for n in range(1, MAX_GRID_CELLS + 1):
        centres = (np.arange(n) * size + size // 2) // n
        grid = binary[centres][:, centres]
        if np.array_equal(upsample(grid, size), binary):
            return grid
    raise FormatError(f"{path}: a {size}^2 map that is not a nearest-upsampled grid of <= {MAX_GRID_CELLS} "
                      "cells (e.g. masked); give its grid size (n_cells; --cells of davis-attack export and evaluate)")


def write_png(path: str | Path, image01: np.ndarray) -> Path:
    """Write a [H, W] image in [0, 1] as 8-bit grey PNG (0 = black, 255 = white)."""
    import cv2

    path = Path(path)
    if not cv2.imwrite(str(path), np.round(np.clip(image01, 0, 1) * 255).astype(np.uint8)):
        raise OSError(f"could not write {path}")
    return path


# ---------------------------------------------------------------------------------------------- pieces
@dataclass(frozen=True)
class PatternPiece:
    """One pattern piece: a UV island of a body part at physical scale.

    Attributes:
        name: ``"<part>"`` or ``"<part>-<k>"`` (k = 1, 2, ... by decreasing size, e.g. ``arms-1``).
        part: body part name.
        face_ids: int64 [K], the island's faces in the body mesh.
        triangles_uv: float64 [K, 3, 2], their UVs (u right, v up).
        loops_uv: boundary loops, each float64 [L, 2] (UV), outer loop first (largest area).
        mm_per_uv: scale S (mm per UV unit); cell side = S / n mm.
        mirrored: True if the island's UVs wind clockwise (printed mirrored so the print faces outwards).
        stretch_quartiles: (25 %, 50 %, 75 %) of the per-triangle ``sqrt(3D area / UV area)`` in mm per UV
            unit: how far the UV layout is from isometric (the printed piece is exact only where it is S).
    """

    name: str
    part: str
    face_ids: np.ndarray
    triangles_uv: np.ndarray
    loops_uv: tuple[np.ndarray, ...]
    mm_per_uv: float
    mirrored: bool = False
    stretch_quartiles: tuple[float, float, float] = (math.nan, math.nan, math.nan)

    @property
    def bounds_uv(self) -> tuple[float, float, float, float]:
        """``(u0, v0, u1, v1)`` of the island."""
        lo = self.triangles_uv.reshape(-1, 2).min(axis=0)
        hi = self.triangles_uv.reshape(-1, 2).max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    @property
    def width_mm(self) -> float:
        """Printed width (mm)."""
        u0, _, u1, _ = self.bounds_uv
        return (u1 - u0) * self.mm_per_uv

    @property
    def height_mm(self) -> float:
        """Printed height (mm)."""
        _, v0, _, v1 = self.bounds_uv
        return (v1 - v0) * self.mm_per_uv

    def cell_mm(self, n_cells: int) -> float:
        """Side of one grid cell on this piece (mm)."""
        return self.mm_per_uv / int(n_cells)

    def u_to_mm(self, u):
        """Piece x (mm from the piece's left edge) of texture coordinate(s) u (mirror-aware)."""
        u0, _, u1, _ = self.bounds_uv
        u = np.asarray(u, dtype=np.float64)
        return (u1 - u) * self.mm_per_uv if self.mirrored else (u - u0) * self.mm_per_uv

    def v_to_mm(self, v):
        """Piece y (mm up from the piece's bottom edge) of texture coordinate(s) v."""
        _, v0, _, _ = self.bounds_uv
        return (np.asarray(v, dtype=np.float64) - v0) * self.mm_per_uv

    def to_mm(self, uv) -> np.ndarray:
        """Piece coordinates (mm, x right, y up) of UVs [..., 2]."""
        uv = np.asarray(uv, dtype=np.float64)
        return np.stack([self.u_to_mm(uv[..., 0]), self.v_to_mm(uv[..., 1])], axis=-1)


def _islands(face_uv_index: np.ndarray) -> list[np.ndarray]:
    """Connected components (sharing a UV vertex) of faces, as index arrays into ``face_uv_index``, largest first.

    Min-label propagation with pointer jumping: every face starts as its own label; each round a face takes the
    smallest label among the faces it shares a vertex with, then the label of that label. Labels only ever point
    to a face of the same component, and the loop ends when faces that share a vertex share a label.
    """
    k = face_uv_index.shape[0]
    _, inverse = np.unique(face_uv_index.ravel(), return_inverse=True)
    corners = inverse.reshape(k, -1)  # [K, 3] vertex ids 0..V-1
    labels = np.arange(k)
    while True:
        vertex_label = np.full(int(corners.max(initial=-1)) + 1, k)
        np.minimum.at(vertex_label, corners, labels[:, None])
        updated = vertex_label[corners].min(axis=1)
        updated = updated[updated]
        if np.array_equal(updated, labels):
            break
        labels = updated
    groups = [np.flatnonzero(labels == lab) for lab in np.unique(labels)]
    return sorted(groups, key=lambda g: (-len(g), int(g[0])))


def _boundary_loops(corners: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops (UV vertex ids) of an oriented triangle set [K, 3] of UV vertex ids.

    Boundary edges are the directed edges whose reverse is not in the set; following them gives closed
    loops (in-degree = out-degree at every vertex of an oriented surface with boundary).
    """
    edges = np.concatenate([corners[:, [0, 1]], corners[:, [1, 2]], corners[:, [2, 0]]])
    keys = edges[:, 0].astype(np.int64) * (1 << 32) + edges[:, 1]
    reverse = edges[:, 1].astype(np.int64) * (1 << 32) + edges[:, 0]
    boundary = edges[~np.isin(reverse, keys)]
    outgoing: dict[int, list[int]] = {}
    for a, b in boundary.tolist():
        outgoing.setdefault(a, []).append(b)
    loops = []
    while outgoing:
        start = next(iter(outgoing))
        loop = [start]
        current = start
        while True:
            nexts = outgoing.get(current)
            if not nexts:
                break  # open chain (non-manifold input): keep what was walked
            nxt = nexts.pop()
            if not nexts:
                del outgoing[current]
            if nxt == start:
                break
            loop.append(nxt)
            current = nxt
        if len(loop) >= 3:
            loops.append(np.array(loop, dtype=np.int64))
    return loops


def _polygon_area(points: np.ndarray) -> float:
    x, y = points[:, 0], points[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def pattern_pieces(
    parts: Iterable[str] = DEFAULT_PARTS,
    asset: BodyAsset | None = None,
    shape_index: int = 0,
    stretch: str = "median",
    ease: float = 1.0,
    texture_mm: float | None = None,
    cell_mm: float | None = None,
    n_cells: int | None = None,
) -> list[PatternPiece]:
    """Pattern pieces (UV islands) of body parts, scaled to the body or to a user size.

    Args:
        parts: body part names (:data:`~davis_rig.scene.body.PART_NAMES`).
        asset: body asset (``None`` = bundled).
        shape_index: body shape whose rest-pose 3D areas set the scale.
        stretch: ``"median"`` (per-island median of per-triangle ``sqrt(A_3d / A_uv)``) or ``"area"``
            (``sqrt(sum A_3d / sum A_uv)``).
        ease: factor on the body scale (e.g. 1.1 for clothing 10 % larger than the skin).
        texture_mm: user scale: the whole UV square is ``texture_mm`` mm wide (all pieces alike).
        cell_mm: user scale: one grid cell is ``cell_mm`` mm (needs ``n_cells``; all pieces alike).
        n_cells: grid cells per side (only for ``cell_mm``).

    Returns:
        list of :class:`PatternPiece`, in part order then by decreasing island size.

    Raises:
        ConfigError (a ValueError): an unknown part, a non-positive size or ease, a shape outside the asset.
        ValueError: unknown stretch mode, conflicting sizes, no faces.
    """
    parts = tuple(dict.fromkeys(parts))
    unknown = [p for p in parts if p not in PART_NAMES]
    if unknown or not parts:
        raise ConfigError("parts", f"expected a non-empty list of {PART_NAMES}, got {list(parts)}")
    if stretch not in ("median", "area"):
        raise ValueError(f"stretch must be 'median' or 'area', got {stretch!r}")
    if texture_mm is not None and cell_mm is not None:
        raise ValueError("give texture_mm or cell_mm, not both")
    user_scale = None
    if texture_mm is not None:
        if not texture_mm > 0:
            raise ConfigError("texture_mm", f"expected a number > 0, got {texture_mm}")
        user_scale = float(texture_mm)
    if cell_mm is not None:
        if not cell_mm > 0 or n_cells is None or int(n_cells) < 1:
            raise ConfigError("cell_mm", f"expected a number > 0 (and n_cells >= 1), got cell_mm={cell_mm}, "
                                         f"n_cells={n_cells}")
        user_scale = float(cell_mm) * int(n_cells)
    if not ease > 0:
        raise ConfigError("ease", f"expected a number > 0, got {ease}")
    asset = BodyAsset.load() if asset is None else asset
    if not 0 <= int(shape_index) < asset.num_shapes:
        raise ConfigError("shape_index", f"expected a shape in [0, {asset.num_shapes}), got {shape_index}")
    uv_all = asset.face_uvs.astype(np.float64)
    verts = asset.rest_vertices_m[int(shape_index)].astype(np.float64)[asset.faces]
    area_3d_mm2 = 0.5 * np.linalg.norm(np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0]), axis=1) * 1e6
    e1 = uv_all[:, 1] - uv_all[:, 0]
    e2 = uv_all[:, 2] - uv_all[:, 0]
    signed_uv = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    pieces = []
    for part in parts:
        faces = np.flatnonzero(asset.face_part_mask([part]))
        islands = _islands(asset.face_uv_index[faces])
        for k, local in enumerate(islands):
            ids = faces[local]
            corners = asset.face_uv_index[ids]
            loops = [asset.uv_table[loop].astype(np.float64) for loop in _boundary_loops(corners)]
            loops.sort(key=lambda p: -abs(_polygon_area(p)))
            uv_area = np.abs(signed_uv[ids])
            ok = uv_area > 1e-12
            ratio = np.sqrt(area_3d_mm2[ids][ok] / uv_area[ok])
            quartiles = tuple(float(q) for q in np.percentile(ratio, [25, 50, 75])) if ok.any() else (math.nan,) * 3
            if user_scale is not None:
                scale = user_scale
            elif stretch == "median":
                scale = float(np.median(ratio)) * float(ease)
            else:
                scale = math.sqrt(area_3d_mm2[ids][ok].sum() / uv_area[ok].sum()) * float(ease)
            name = part if len(islands) == 1 else f"{part}-{k + 1}"
            pieces.append(PatternPiece(
                name=name, part=part, face_ids=ids.astype(np.int64), triangles_uv=uv_all[ids], loops_uv=tuple(loops),
                mm_per_uv=scale, mirrored=bool(signed_uv[ids].sum() < 0), stretch_quartiles=quartiles,
            ))  # fmt: skip
    return pieces


# ---------------------------------------------------------------------------------------------- cells
def black_rectangles(grid: np.ndarray) -> np.ndarray:
    """Black cells of a grid merged into rectangles (row runs, then identical runs of consecutive rows).

    Args:
        grid: [n_rows, n_cols] values, black where <= 0.5.

    Returns:
        int64 [K, 4] ``(row0, col0, row1, col1)``, end-exclusive, disjoint, covering exactly the black cells;
        sorted.
    """
    black = np.asarray(grid) <= 0.5
    if black.ndim != 2:
        raise ShapeError(f"grid must be 2-D, got shape {black.shape}")
    padded = np.zeros((black.shape[0], black.shape[1] + 2), dtype=np.int8)
    padded[:, 1:-1] = black
    change = np.diff(padded, axis=1)
    starts = np.argwhere(change == 1)  # (row, col0), row-major
    ends = np.argwhere(change == -1)  # (row, col1), same order
    active: dict[tuple[int, int], tuple[int, int]] = {}  # (col0, col1) -> (first row, last row)
    out = []
    for (row, c0), (_, c1) in zip(starts.tolist(), ends.tolist()):
        key = (c0, c1)
        if key in active and active[key][1] == row - 1:
            active[key] = (active[key][0], row)
            continue
        if key in active:
            r0, r1 = active[key]
            out.append((r0, c0, r1 + 1, c1))
        active[key] = (row, row)
    out += [(r0, c0, r1 + 1, c1) for (c0, c1), (r0, r1) in active.items()]
    return np.array(sorted(out), dtype=np.int64).reshape(-1, 4)


# ---------------------------------------------------------------------------------------------- tiles
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
        return _tile_label(self.row, self.col)


def _tile_label(row: int, col: int) -> str:
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


# ---------------------------------------------------------------------------------------------- pdf
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
        text = f"joins {piece.name} {_tile_label(r, col)}"
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


# ---------------------------------------------------------------------------------------------- preview
def render_preview(
    grid: np.ndarray,
    parts: Iterable[str] = DEFAULT_PARTS,
    shape_index: int = 0,
    height_px: int = 480,
    asset: BodyAsset | None = None,
) -> np.ndarray:
    """Front and back view of the textured rest-pose body (near-orthographic: 40 m away, long lens).

    Rendered with :func:`davis_rig.scene.renderer.rasterize_mesh` (Lambert shading, 2x2 supersampling),
    nearest texture lookup of the grid with the part mask (white outside the parts).

    Args:
        grid: float [n, n] (1 = white).
        parts: painted body parts.
        shape_index: body shape.
        height_px: image height (px); each view is ``height_px / 2`` wide.
        asset: body asset (``None`` = bundled).

    Returns:
        float32 [height_px, height_px] in [0, 1]: front (left) and back (right) on a light grey background.

    Raises:
        MissingDependencyError: torch is not installed.
    """
    try:
        import torch
    except ImportError as exc:
        raise MissingDependencyError("the preview render needs torch: pip install 'davis_rig[torch]'") from exc
    from davis_rig.scene.camera import PinholeCamera, look_at
    from davis_rig.scene.masks import part_mask
    from davis_rig.scene.renderer import rasterize_mesh
    from davis_rig.scene.shading import Light

    asset = BodyAsset.load() if asset is None else asset
    vertices = np.array(asset.rest_vertices_m[int(shape_index)], dtype=np.float32)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre_z = float(lo[2] + hi[2]) / 2
    extent_m = float(max(hi[2] - lo[2], 2 * (hi[0] - lo[0]))) * 1.08
    distance = 40.0
    h = int(height_px)
    w = h // 2
    f = h * distance / extent_m
    camera = PinholeCamera(width_px=w, height_px=h, fx_px=f, fy_px=f, cx_px=w / 2, cy_px=h / 2)
    verts = torch.as_tensor(vertices)[None]
    faces = torch.as_tensor(np.asarray(asset.faces, dtype=np.int64))
    face_uvs = torch.as_tensor(np.array(asset.face_uvs))
    mask = part_mask(tuple(parts))
    texture = torch.as_tensor(np.asarray(grid, dtype=np.float32))
    views = []
    for side in (-1.0, 1.0):  # front (camera on -Y, the body faces -Y), back
        rotation, translation = look_at([0.0, side * distance, centre_z], [0.0, 0.0, centre_z])
        raster = rasterize_mesh(verts, faces, face_uvs, camera, torch.as_tensor(rotation, dtype=torch.float32),
                                torch.as_tensor(translation, dtype=torch.float32), supersample=2,
                                light=Light(direction=(0.3 * -side, side, 0.8), ambient=0.35, diffuse=0.65))
        image = raster.render(texture, background=0.85, mode="nearest", mask=mask, size=mask.shape[0], fill=1.0)
        views.append(image[0].detach().numpy())
    return np.clip(np.concatenate(views, axis=1), 0, 1).astype(np.float32)


# ---------------------------------------------------------------------------------------------- all outputs
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
    info = {
        "grid_cells": n,
        "parts": list(parts),
        "paper": paper,
        "paper_mm": list(PAPER_SIZES_MM[paper]),
        "margin_mm": margin_mm,
        "scale": ("texture_mm" if texture_mm is not None else "cell_mm" if cell_mm is not None else f"body:{stretch}"),
        "shape_index": shape_index,
        "ease": ease,
        "pages": len(tiles) + 1,
        "pieces": [
            {
                "name": p.name, "part": p.part, "faces": int(len(p.face_ids)), "mm_per_uv": p.mm_per_uv,
                "cell_mm": p.cell_mm(n), "width_mm": p.width_mm, "height_mm": p.height_mm, "mirrored": p.mirrored,
                "stretch_quartiles_mm_per_uv": list(p.stretch_quartiles),
                "tiles": [{"label": t.label, "page": i + 2, "landscape": t.landscape}
                          for i, t in enumerate(tiles) if t.piece == k],
            }
            for k, p in enumerate(pieces)
        ],  # fmt: skip
        "notes": notes,
    }
    written["json"] = out / "pattern.json"
    written["json"].write_text(json.dumps(info, indent=2) + "\n")
    return written
