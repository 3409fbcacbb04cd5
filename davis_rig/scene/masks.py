"""UV-space body-part masks (torso, arms, legs, head, hands, feet) of the bundled body asset.

The masks live in the texture image of the body (default 1024 x 1024 texels). Image convention
(same as anny's segmentation image and a texture read top-down): array index ``[row, col]``, texel
``(row, col)`` covers ``u in [col / W, (col + 1) / W)`` and ``v in [1 - (row + 1) / H, 1 - row / H)``,
i.e. ``row = (1 - v) * H``, ``col = u * W``. A texture sampler using the body's UVs (v up) must flip v
accordingly (``grid_sample`` with ``y = 1 - 2 v`` for ``align_corners=False``).

Each triangle labels the texels whose centres lie inside it (plus the texel of its centroid, so even
sub-texel triangles are represented); texels claimed by triangles of two parts keep the later part in
:data:`~davis_rig.scene.body.PART_NAMES` order.
Then every part's islands are padded a few texels into the empty UV space (seam padding), so bilinear
texture sampling at island borders stays inside the part. The parts never overlap.

The paper's paintable parts are torso (upper body), arms and legs; head, hands and feet are excluded.
:data:`PAINTABLE_COMBINATIONS` lists the 7 non-empty combinations of the paintable parts.
"""

from __future__ import annotations

import functools
import itertools
from typing import Iterable

import numpy as np

from davis_rig.scene.body import PART_NAMES, BodyAsset

__all__ = [
    "DEFAULT_PADDING_PX",
    "EMPTY_LABEL",
    "MASK_SIZE_PX",
    "PAINTABLE_COMBINATIONS",
    "PAINTABLE_PARTS",
    "combination_masks",
    "part_label_map",
    "part_mask",
    "uv_to_texel",
]

#: Default texture size (texels per side).
MASK_SIZE_PX = 1024
#: Default seam padding (texels grown into empty UV space around every island).
DEFAULT_PADDING_PX = 4
#: Label of texels outside every padded island in :func:`part_label_map`.
EMPTY_LABEL = 255
#: Parts the adversarial texture may cover.
PAINTABLE_PARTS: tuple[str, ...] = ("torso", "arms", "legs")
#: All 7 non-empty combinations of :data:`PAINTABLE_PARTS`, singles first.
PAINTABLE_COMBINATIONS: tuple[tuple[str, ...], ...] = tuple(
    combo for r in (1, 2, 3) for combo in itertools.combinations(PAINTABLE_PARTS, r)
)
_SUBPIXEL_BITS = 4


def uv_to_texel(uv: np.ndarray, size: int = MASK_SIZE_PX) -> np.ndarray:
    """Continuous texel coordinates ``(x = col, y = row)`` of UVs; texel centres are at integers.

    Args:
        uv: float array [..., 2], (u right, v up) in [0, 1].
        size: texture size (texels per side).

    Returns:
        float64 array [..., 2]: ``x = u * size - 0.5``, ``y = (1 - v) * size - 0.5``.
    """
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([uv[..., 0] * size - 0.5, (1.0 - uv[..., 1]) * size - 0.5], axis=-1)


def _check_size(size: int, padding_px: int) -> None:
    if int(size) < 16:
        raise ValueError(f"mask size must be >= 16 texels, got {size}")
    if int(padding_px) < 0:
        raise ValueError(f"padding_px must be >= 0, got {padding_px}")


def _triangle_texels(corners: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texels whose centres lie inside (or on) each triangle, plus the texel of each centroid.

    Vectorised: triangles are processed in chunks of similar bounding-box size; each chunk tests a
    [n, h, w] grid of texel centres against the three edge functions.

    Args:
        corners: float64 [F, 3, 2] texel coordinates (x = col, y = row; centres at integers).
        size: texture size.

    Returns:
        (face index, row, col), int64 arrays [N].
    """
    lo = np.clip(np.floor(corners.min(axis=1)).astype(np.int64), 0, size - 1)  # [F, 2]
    hi = np.clip(np.ceil(corners.max(axis=1)).astype(np.int64), 0, size - 1)
    extent = np.maximum(hi - lo + 1, 1)  # [F, 2] (w, h)
    # signed area -> orientation-independent inside test
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    orientation = np.where(area < 0, -1.0, 1.0)
    faces_out, rows_out, cols_out = [], [], []
    sides = extent.max(axis=1)
    chunks = []
    for side in np.unique(sides):  # triangles with the same bounding-box side, in chunks of <= 4 M texels
        same = np.flatnonzero(sides == side)
        step = max(1, (1 << 22) // int(side) ** 2)
        chunks += [(int(side), same[i : i + step]) for i in range(0, len(same), step)]
    for side, ids in chunks:
        offsets = np.arange(side)
        xs = lo[ids, 0, None, None] + offsets[None, None, :]  # [n, 1, side]
        ys = lo[ids, 1, None, None] + offsets[None, :, None]  # [n, side, 1]
        inside = (xs <= hi[ids, 0, None, None]) & (ys <= hi[ids, 1, None, None])
        c = corners[ids]
        for k in range(3):
            a, b = c[:, k], c[:, (k + 1) % 3]
            edge = (b[:, 0] - a[:, 0])[:, None, None] * (ys - a[:, 1, None, None]) - (b[:, 1] - a[:, 1])[
                :, None, None
            ] * (xs - a[:, 0, None, None])
            inside &= edge * orientation[ids, None, None] >= -1e-9
        n_idx, r_idx, c_idx = np.nonzero(inside)
        faces_out.append(ids[n_idx])
        rows_out.append(lo[ids[n_idx], 1] + r_idx)
        cols_out.append(lo[ids[n_idx], 0] + c_idx)
    centroid = np.clip(np.round(corners.mean(axis=1)).astype(np.int64), 0, size - 1)
    faces_out.append(np.arange(len(corners)))
    rows_out.append(centroid[:, 1])
    cols_out.append(centroid[:, 0])
    return np.concatenate(faces_out), np.concatenate(rows_out), np.concatenate(cols_out)


def _rasterize(asset: BodyAsset, size: int, padding_px: int) -> np.ndarray:
    import cv2

    faces, rows, cols = _triangle_texels(uv_to_texel(asset.face_uvs, size), size)
    codes = asset.face_parts[faces]
    best = np.full((size, size), -1, dtype=np.int16)
    np.maximum.at(best, (rows, cols), codes.astype(np.int16))  # later parts win shared texels
    labels = np.where(best < 0, EMPTY_LABEL, best).astype(np.uint8)
    if padding_px:
        kernel = np.ones((3, 3), dtype=np.uint8)
        for _ in range(int(padding_px)):
            empty = labels == EMPTY_LABEL
            if not empty.any():
                break
            grown = labels.copy()
            for code in range(len(PART_NAMES)):
                reach = cv2.dilate((labels == code).astype(np.uint8), kernel).astype(bool) & empty
                grown[reach & (grown == EMPTY_LABEL)] = code
            labels = grown
    return labels


@functools.lru_cache(maxsize=8)
def _default_label_map(size: int, padding_px: int) -> np.ndarray:
    labels = _rasterize(BodyAsset.load(), size, padding_px)
    labels.setflags(write=False)
    return labels


def part_label_map(
    size: int = MASK_SIZE_PX, padding_px: int = DEFAULT_PADDING_PX, asset: BodyAsset | None = None
) -> np.ndarray:
    """Texel-wise part label of the body texture.

    Args:
        size: texture size H = W (texels).
        padding_px: seam padding grown around the islands (texels).
        asset: body asset (``None`` = bundled asset; that result is cached and read-only).

    Returns:
        uint8 [H, W]: index into :data:`~davis_rig.scene.body.PART_NAMES`, or :data:`EMPTY_LABEL`.

    Raises:
        ValueError: size < 16 or padding_px < 0.
    """
    _check_size(size, padding_px)
    if asset is None:
        return _default_label_map(int(size), int(padding_px))
    return _rasterize(asset, int(size), int(padding_px))


def part_mask(
    parts: Iterable[str],
    size: int = MASK_SIZE_PX,
    padding_px: int = DEFAULT_PADDING_PX,
    asset: BodyAsset | None = None,
) -> np.ndarray:
    """Boolean UV mask of the union of body parts.

    Args:
        parts: part names from :data:`~davis_rig.scene.body.PART_NAMES` (e.g. ``("torso", "arms")``).
        size: texture size H = W (texels).
        padding_px: seam padding (texels).
        asset: body asset (``None`` = bundled asset).

    Returns:
        bool [H, W] (a new array).

    Raises:
        ValueError: an unknown part name, size < 16 or padding_px < 0.
    """
    parts = tuple(parts)
    unknown = [p for p in parts if p not in PART_NAMES]
    if unknown:
        raise ValueError(f"unknown body parts {unknown}; expected names from {PART_NAMES}")
    labels = part_label_map(size, padding_px, asset)
    return np.isin(labels, np.array([PART_NAMES.index(p) for p in parts], dtype=np.uint8))


def combination_masks(
    size: int = MASK_SIZE_PX, padding_px: int = DEFAULT_PADDING_PX, asset: BodyAsset | None = None
) -> dict[str, np.ndarray]:
    """Masks of the 7 :data:`PAINTABLE_COMBINATIONS`, keyed ``"torso"``, ..., ``"torso+arms+legs"``.

    Returns:
        dict name -> bool [H, W].
    """
    return {"+".join(combo): part_mask(combo, size, padding_px, asset) for combo in PAINTABLE_COMBINATIONS}
