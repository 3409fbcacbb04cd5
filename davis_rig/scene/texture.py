"""Differentiable texture sampling through precomputed texel lookups; n x n grids sampled without upsampling.

Texture image convention (same as :mod:`davis_rig.scene.masks`): a square ``size x size`` image indexed
``[row, col]``; texel ``(row, col)`` covers ``u in [col/size, (col+1)/size)`` and
``v in [1 - (row+1)/size, 1 - row/size)`` (v up, rows down).

- ``nearest``: texel ``(floor((1-v) size), floor(u size))`` (clamped to the image).
- ``bilinear``: texel centres at integer ``x = u size - 0.5``, ``y = (1-v) size - 0.5``, border clamping
  (as ``grid_sample(align_corners=False, padding_mode="border")``).

The paper's texture is an n x n grid nearest-upsampled to 1024 x 1024 (``F.interpolate(mode="nearest")``
maps texel ``c`` to cell ``floor(c n / size)``). :func:`prepare_lookup` with ``grid_n=n`` resolves each
texel tap of the ``size`` image to its grid cell with the same integer formula, so sampling the n x n grid
gives **bit-identical** values and gradients to sampling the upsampled image, without materialising it
(:func:`upsample_grid` builds the image for comparison and for export). A UV part mask at texture
resolution is applied per tap: ``value = mask * T + (1 - mask) * fill`` (the paper's
``M * U + (1 - M) * 1``), again identical to masking the upsampled image.

The lookup (indices + weights, no gradients) depends only on the rasterized UVs, so it is built once per
clip; :meth:`TexelLookup.sample` is one gather and a weighted sum per optimiser step. The gradient of the
sampled values w.r.t. the texture is the sparse map ``d value_n / d T[k] = sum_taps weight * mask``.
"""

from __future__ import annotations

from dataclasses import dataclass

from davis_rig._lazy import optional_import
from davis_rig.errors import ShapeError

__all__ = ["TexelLookup", "prepare_lookup", "sample_texture", "upsample_grid"]

MODES = ("nearest", "bilinear")


def _torch():
    return optional_import("torch", "texture sampling")


@dataclass
class TexelLookup:
    """Precomputed texture taps of N sample points.

    Attributes:
        index: int64 [N, K], flat index into the sampled texture (``row * cols + col`` of the ``size``
            image, or of the ``grid_n x grid_n`` grid when ``grid_n`` is set); K = 1 (nearest) or 4.
        weight: float [N, K], tap weights (sum to 1 per point).
        painted: float [N, K], 1 where the tap lies inside the part mask (or no mask), else 0.
        texture_hw: (rows, cols) of the texture this lookup samples.
    """

    index: "object"
    weight: "object"
    painted: "object"
    texture_hw: tuple[int, int]

    def sample(self, texture, fill: float = 1.0):
        """Sample a texture (differentiable w.r.t. ``texture``).

        Args:
            texture: float tensor [rows, cols] or [C, rows, cols] with the lookup's ``texture_hw``.
            fill: value outside the part mask (paper: white = 1.0).

        Returns:
            float tensor [N] or [C, N].

        Raises:
            ShapeError: the texture size differs from the lookup's.
        """
        if tuple(texture.shape[-2:]) != tuple(self.texture_hw):
            rows, cols = self.texture_hw
            raise ShapeError(f"texture must be [..., {rows}, {cols}], got {tuple(texture.shape)}")
        flat = texture.reshape(*texture.shape[:-2], -1)
        # index_select, not flat[..., index]: its backward (index_add) sums each texel's taps in a fixed order, so
        # gradients are bit-reproducible on several CPU threads (advanced indexing's accumulate is not)
        taps = flat.index_select(-1, self.index.reshape(-1)).view(*flat.shape[:-1], *self.index.shape)  # [..., N, K]
        weight = self.weight.to(taps.dtype)
        painted = self.painted.to(taps.dtype)
        values = weight * painted * taps
        out = values.sum(-1)
        unpainted = (weight * (1 - painted)).sum(-1)
        return out + fill * unpainted


def prepare_lookup(uv, size: int = 1024, mode: str = "nearest", grid_n: int | None = None, mask=None) -> TexelLookup:
    """Texture taps of UV points for a ``size x size`` texture (optionally an upsampled n x n grid).

    Args:
        uv: float tensor [N, 2], ``(u, v)`` (v up).
        size: texture resolution (texels per side) whose texel grid defines the taps (paper: 1024).
        mode: ``"nearest"`` or ``"bilinear"``.
        grid_n: if set, the texture is an ``grid_n x grid_n`` grid nearest-upsampled to ``size``; the lookup
            then indexes the grid directly.
        mask: optional bool array/tensor [size, size], the paintable texels (taps outside get ``fill``).

    Returns:
        :class:`TexelLookup` on ``uv``'s device.

    Raises:
        ShapeError: uv not [N, 2] or mask not [size, size]. ValueError: unknown mode or bad sizes.
    """
    torch = _torch()
    if uv.ndim != 2 or uv.shape[-1] != 2:
        raise ShapeError(f"uv must be [N, 2], got {tuple(uv.shape)}")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    size = int(size)
    if size < 1 or (grid_n is not None and not 1 <= int(grid_n) <= size):
        raise ValueError(f"need size >= 1 and 1 <= grid_n <= size, got size={size}, grid_n={grid_n}")
    device = uv.device
    u = uv[:, 0].double()
    v = uv[:, 1].double()
    if mode == "nearest":
        col = torch.floor(u * size).long().clamp(0, size - 1)[:, None]
        row = torch.floor((1.0 - v) * size).long().clamp(0, size - 1)[:, None]
        weight = torch.ones((uv.shape[0], 1), dtype=uv.dtype, device=device)
    else:
        x = u * size - 0.5
        y = (1.0 - v) * size - 0.5
        x0 = torch.floor(x)
        y0 = torch.floor(y)
        fx = (x - x0)[:, None]
        fy = (y - y0)[:, None]
        x0 = x0.long()[:, None]
        y0 = y0.long()[:, None]
        dx = torch.tensor([[0, 1, 0, 1]], device=device)
        dy = torch.tensor([[0, 0, 1, 1]], device=device)
        col = (x0 + dx).clamp(0, size - 1)
        row = (y0 + dy).clamp(0, size - 1)
        wx = torch.where(dx == 1, fx, 1 - fx)
        wy = torch.where(dy == 1, fy, 1 - fy)
        weight = (wx * wy).to(uv.dtype)
    if mask is not None:
        mask_t = torch.as_tensor(mask, device=device)
        if tuple(mask_t.shape) != (size, size):
            raise ShapeError(f"mask must be [{size}, {size}], got {tuple(mask_t.shape)}")
        painted = mask_t.bool()[row, col]
    else:
        painted = torch.ones_like(row, dtype=torch.bool)
    if grid_n is None:
        index = row * size + col
        hw = (size, size)
    else:
        n = int(grid_n)
        index = torch.div(row * n, size, rounding_mode="floor") * n + torch.div(col * n, size, rounding_mode="floor")
        hw = (n, n)
    return TexelLookup(index=index, weight=weight, painted=painted, texture_hw=hw)


def sample_texture(texture, uv, mode: str = "nearest", size: int | None = None, mask=None, fill: float = 1.0):
    """Sample a texture at UV points (differentiable w.r.t. ``texture``); one-shot :func:`prepare_lookup`.

    Args:
        texture: float tensor [rows, cols] or [C, rows, cols]; a square grid smaller than ``size`` is
            treated as nearest-upsampled to ``size``.
        uv: float tensor [N, 2] (v up).
        mode: ``"nearest"`` or ``"bilinear"``.
        size: texel resolution of the taps (default the texture's own size).
        mask: optional bool [size, size] paintable texels; fill: value outside the mask.

    Returns:
        float tensor [N] or [C, N].
    """
    rows, cols = texture.shape[-2:]
    if rows != cols:
        raise ShapeError(f"texture must be square, got {tuple(texture.shape)}")
    size = rows if size is None else int(size)
    lookup = prepare_lookup(uv, size=size, mode=mode, grid_n=None if rows == size else rows, mask=mask)
    return lookup.sample(texture, fill=fill)


def upsample_grid(grid, size: int = 1024):
    """Nearest upsampling of an n x n grid to ``size x size`` (cell of texel c = floor(c n / size)).

    Args:
        grid: tensor [..., n, n].
        size: output texels per side.

    Returns:
        tensor [..., size, size] (differentiable; equals ``F.interpolate(mode="nearest")`` for size = 2^k).
    """
    torch = _torch()
    n = grid.shape[-1]
    if grid.shape[-2] != n:
        raise ShapeError(f"grid must be square [..., n, n], got {tuple(grid.shape)}")
    cells = torch.div(torch.arange(size, device=grid.device) * n, size, rounding_mode="floor")
    return grid[..., cells, :][..., :, cells]
