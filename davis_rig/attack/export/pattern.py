"""Pattern pieces: the UV islands of the body parts at physical scale (mm per UV unit), with their outlines.

An island is a connected component of a part's UV triangles (sharing a UV vertex); its outline is the boundary of
its triangles (outer loop first). The scale comes from the body (per island, the median or area ratio of
``sqrt(3D area / UV area)`` of the rest-pose mesh of one shape, times ``ease``) or from the user (``texture_mm`` or
``cell_mm``). An island whose UVs wind clockwise is printed mirrored, so that the printed side faces outwards.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from davis_rig.errors import ConfigError
from davis_rig.scene.body import PART_NAMES, BodyAsset

__all__ = ["DEFAULT_PARTS", "PatternPiece", "pattern_pieces"]

#: Default paintable parts (the paper's full-body texture: upper body, arms, legs).
DEFAULT_PARTS: tuple[str, ...] = ("torso", "arms", "legs")


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
        ConfigError (a ValueError): an unknown part, a non-positive size or ease, a texture wider than
            :data:`MAX_TEXTURE_MM` or an ease over :data:`MAX_EASE`, a shape outside the asset.
        ValueError: unknown stretch mode, conflicting sizes, no faces.
    """
    parts = tuple(dict.fromkeys(parts))
    unknown = [p for p in parts if p not in PART_NAMES]
    if unknown or not parts:
        raise ConfigError("parts", f"expected a non-empty list of {PART_NAMES}, got {list(parts)}")
    if stretch not in ("median", "area"):
        raise ValueError(f"stretch must be 'median' or 'area', got {stretch!r}")
    user_scale = _user_scale(texture_mm, cell_mm, n_cells)
    if not 0 < ease <= MAX_EASE:
        raise ConfigError("ease", f"expected a number in (0, {MAX_EASE:g}], got {ease}")
    asset = BodyAsset.load() if asset is None else asset
    if not 0 <= int(shape_index) < asset.num_shapes:
        raise ConfigError("shape_index", f"expected a shape in [0, {asset.num_shapes}), got {shape_index}")
    faces = _FaceAreas.of(asset, int(shape_index))
    scale = _Scale(stretch, float(ease), user_scale)
    pieces = []
    for part in parts:
        part_faces = np.flatnonzero(asset.face_part_mask([part]))
        islands = _islands(asset.face_uv_index[part_faces])
        for k, local in enumerate(islands):
            name = part if len(islands) == 1 else f"{part}-{k + 1}"
            pieces.append(_island_piece(asset, faces, part_faces[local], name, part, scale))
    return pieces


#: Largest printed side of the whole UV square, mm (10 m: a person's texture is 0.5-2 m; a typo beyond it would
#: rasterize pages of gigabytes).
MAX_TEXTURE_MM = 10_000.0
#: Largest ``ease`` on the body's own scale.
MAX_EASE = 10.0


def _user_scale(texture_mm: float | None, cell_mm: float | None, n_cells: int | None) -> float | None:
    """The user's scale (mm per UV unit) of ``texture_mm`` or ``cell_mm`` x ``n_cells``; ``None``: the body's."""
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
    if user_scale is not None and user_scale > MAX_TEXTURE_MM:
        name, value = ("texture_mm", texture_mm) if texture_mm is not None else ("cell_mm", cell_mm)
        raise ConfigError(name, f"the whole texture would print {user_scale:g} mm wide, over the "
                                f"{MAX_TEXTURE_MM:g} mm this export lays out; got {value:g}")
    return user_scale


@dataclass(frozen=True)
class _FaceAreas:
    """Per face of the mesh: UVs float64 [F, 3, 2], rest-pose 3D area float64 [F] (mm²), signed UV area [F]."""

    uv: np.ndarray
    area_3d_mm2: np.ndarray
    signed_uv: np.ndarray

    @classmethod
    def of(cls, asset: BodyAsset, shape_index: int) -> "_FaceAreas":
        """The measures of ``asset``'s faces on the rest pose of ``shape_index``."""
        uv = asset.face_uvs.astype(np.float64)
        verts = asset.rest_vertices_m[shape_index].astype(np.float64)[asset.faces]
        area_3d = 0.5 * np.linalg.norm(np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0]), axis=1) * 1e6
        e1 = uv[:, 1] - uv[:, 0]
        e2 = uv[:, 2] - uv[:, 0]
        return cls(uv=uv, area_3d_mm2=area_3d, signed_uv=0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]))


@dataclass(frozen=True)
class _Scale:
    """How a piece is scaled: the body's ``stretch`` rule times ``ease``, or the user's scale (mm per UV unit)."""

    stretch: str
    ease: float
    user_mm_per_uv: float | None


def _island_piece(asset: BodyAsset, faces: _FaceAreas, ids: np.ndarray, name: str, part: str,
                  scale: _Scale) -> PatternPiece:
    """The :class:`PatternPiece` of one island (faces ``ids``): outline loops (outer first), stretch, scale."""
    corners = asset.face_uv_index[ids]
    loops = [asset.uv_table[loop].astype(np.float64) for loop in _boundary_loops(corners)]
    loops.sort(key=lambda p: -abs(_polygon_area(p)))
    uv_area = np.abs(faces.signed_uv[ids])
    ok = uv_area > 1e-12
    ratio = np.sqrt(faces.area_3d_mm2[ids][ok] / uv_area[ok])
    quartiles = tuple(float(q) for q in np.percentile(ratio, [25, 50, 75])) if ok.any() else (math.nan,) * 3
    if scale.user_mm_per_uv is not None:
        mm_per_uv = scale.user_mm_per_uv
    elif scale.stretch == "median":
        mm_per_uv = float(np.median(ratio)) * scale.ease
    else:
        mm_per_uv = math.sqrt(faces.area_3d_mm2[ids][ok].sum() / uv_area[ok].sum()) * scale.ease
    return PatternPiece(name=name, part=part, face_ids=ids.astype(np.int64), triangles_uv=faces.uv[ids],
                        loops_uv=tuple(loops), mm_per_uv=mm_per_uv, mirrored=bool(faces.signed_uv[ids].sum() < 0),
                        stretch_quartiles=quartiles)
