"""The texture grid of the print export: reading a grid or an upsampled map, upsampling, PNGs, black rectangles.

A grid is float [n, n] of 0 (black) / 1 (white), row 0 at the top of the texture (high v); an upsampled map is the
grid nearest-upsampled to S x S texels (cell of texel c: ``floor(c * n / S)``, as the renderer's lookup).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from davis_rig.errors import ConfigError, FormatError, ShapeError

__all__ = ["MAX_GRID_CELLS", "black_rectangles", "grid_from_map", "load_texture_grid", "upsample", "write_png"]

#: Largest grid a square image is taken to be directly (larger images are upsampled maps).
MAX_GRID_CELLS = 256


def _to_unit(image: np.ndarray, where: str) -> np.ndarray:
    if image.ndim == 3:
        if image.shape[2] not in (1, 3, 4):
            raise FormatError(f"{where}: image must be grey, RGB or RGBA, got shape {image.shape}")
        image = image[..., :3].mean(axis=2) if image.shape[2] >= 3 else image[..., 0]
    if image.ndim != 2:
        raise FormatError(f"{where}: texture must be a 2-D grid or image, got shape {image.shape}")
    if image.size == 0:
        raise FormatError(f"{where}: the texture is empty (shape {image.shape})")
    if image.dtype == np.uint8:
        return image.astype(np.float64) / 255.0
    if image.dtype == np.uint16:
        return image.astype(np.float64) / 65535.0
    if np.issubdtype(image.dtype, np.bool_) or np.issubdtype(image.dtype, np.integer) or \
            np.issubdtype(image.dtype, np.floating):
        if np.issubdtype(image.dtype, np.floating) and not np.all(np.isfinite(image)):
            raise FormatError(f"{where}: texture has non-finite values")
        if image.size and (image.min() < 0 or image.max() > 1):  # e.g. 0..255 saved as floats: not 1 = white
            raise FormatError(f"{where}: texture values must lie in [0, 1] (1 = white), got "
                              f"{float(image.min()):g}..{float(image.max()):g}")
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
        except (OSError, ValueError, EOFError) as exc:
            raise FormatError(f"{path}: not a readable .npy array ({exc})") from exc
        if not isinstance(raw, np.ndarray):
            raw.close()
            raise FormatError(f"{path}: an .npz archive, not a .npy array")
        while raw.ndim > 2 and 1 in (raw.shape[0], raw.shape[-1]):  # [1, n, n] or [n, n, 1]; a 1x1 grid stays 2-D
            raw = raw[0] if raw.shape[0] == 1 else raw[..., 0]
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
