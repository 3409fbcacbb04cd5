"""Texture-space renderer: rasterize once (no autograd), then composite differentiably w.r.t. the texture.

For every frame, pixel ``p`` with ``s x s`` samples:

``I(p) = B(p) (1 - alpha(p)) + (1 / s^2) * sum_{covered samples q of p} shade(q) T(uv(q))``

with ``alpha(p)`` the covered fraction of the samples (so ``I = B (1 - alpha) + alpha * mean(shade * T)``),
``shade`` the Lambert shade (:mod:`.shading`) and ``T(uv)`` the texture (:mod:`.texture`). Geometry, UVs,
shades and coverage come from :func:`rasterize_mesh` (no gradients); :meth:`RasterizedMesh.compose` is a
gather + ``index_add``, so gradients flow only to the texture, and
``dI(p)/dT[k] = (1/s^2) sum_q shade(q) * weight_k(q) * mask_k(q)`` (the analytic sparse map).

Ground-truth boxes per frame: the tight box of the pixels with coverage > 0 (``x0, y0, x1, y1`` in pixel
edges, i.e. ``x1 = last column + 1``; always inside the frame), and the box of the projected vertices
clipped to the frame (includes occluded parts). NaN rows for frames without a visible person.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import ShapeError
from davis_rig.scene.camera import PinholeCamera
from davis_rig.scene.rasterize import rasterize_sparse
from davis_rig.scene.shading import Light, lambert, vertex_normals
from davis_rig.scene.texture import TexelLookup, prepare_lookup

__all__ = ["EMPTY_PART", "RasterizedMesh", "boxes_from_coverage", "boxes_from_points", "rasterize_mesh"]

#: Part label of background pixels in part-label images.
EMPTY_PART = 255


def _torch():
    return optional_import("torch", "the renderer")


@dataclass
class RasterizedMesh:
    """Everything needed to composite a textured mesh over a background, per covered sample.

    Attributes:
        hw: image (height, width), px; supersample: samples per pixel side ``s``; num_frames: T.
        sample_pixel: int64 [N], flat index ``t*H*W + row*W + col`` of each covered sample's pixel.
        face: int64 [N], visible face of each covered sample.
        uv: float [N, 2], texture coordinates (v up) at each sample.
        shade: float [N], Lambert shade at each sample.
        coverage: float [T, H, W], covered fraction alpha per pixel.
        vertex_boxes: float32 [T, 4], box of all projected vertices clipped to the frame (NaN: none).
        sample_index: int64 [N], flat index ``t*(H s)*(W s) + row_s*(W s) + col_s`` of each covered sample.
    """

    hw: tuple[int, int]
    supersample: int
    num_frames: int
    sample_pixel: "object"
    face: "object"
    uv: "object"
    shade: "object"
    coverage: "object"
    vertex_boxes: np.ndarray
    sample_index: "object"

    def lookup(self, size: int = 1024, mode: str = "nearest", grid_n: int | None = None, mask=None) -> TexelLookup:
        """Texel taps of the covered samples (see :func:`davis_rig.scene.texture.prepare_lookup`)."""
        return prepare_lookup(self.uv, size=size, mode=mode, grid_n=grid_n, mask=mask)

    def compose(self, values, background):
        """Composite per-sample texture values over a background (differentiable in both).

        Equals ``backdrop(background, dtype) + person(values)`` (a clip re-rendered with many textures keeps
        its :meth:`backdrop`).

        Args:
            values: float tensor [N] (texture value per covered sample, e.g. ``lookup.sample(T)``), or
                ``None`` for an all-white texture.
            background: float tensor/array [H, W] or [T, H, W] (linear intensity).

        Returns:
            float tensor [T, H, W], the rendered intensity.

        Raises:
            ShapeError: sizes do not match.
        """
        person = self.person(values)
        return self.backdrop(background, person.dtype) + person

    def backdrop(self, background, dtype=None):
        """The visible part of the background, ``B (1 - alpha)`` (texture-independent; differentiable in ``B``).

        Args:
            background: float tensor/array [H, W] or [T, H, W] (linear intensity).
            dtype: result dtype (default: the coverage's).

        Returns:
            float tensor [T, H, W].

        Raises:
            ShapeError: the background's size does not match.
        """
        torch = _torch()
        h, w = self.hw
        t = self.num_frames
        dtype = dtype or self.coverage.dtype
        bg = torch.as_tensor(background, device=self.coverage.device)
        if not torch.is_floating_point(bg):
            bg = bg.to(self.coverage.dtype)
        if tuple(bg.shape) not in ((h, w), (t, h, w)):
            raise ShapeError(f"background must be [{h}, {w}] or [{t}, {h}, {w}], got {tuple(bg.shape)}")
        return bg.to(dtype) * (1 - self.coverage.to(dtype))

    def person(self, values, *, pixels=None, hw=None):
        """The textured body's share of every pixel, ``alpha * mean(shade * T)`` (differentiable in ``values``).

        Args:
            values: float tensor [N] (texture value per covered sample), or ``None`` for an all-white texture.
            pixels, hw: render into a smaller frame of ``hw = (h, w)`` pixels instead, with ``pixels`` (int64 [N])
                each sample's flat index ``t*h*w + row*w + col`` there (a crop holding every covered sample);
                default :attr:`sample_pixel` in the full :attr:`hw`.

        Returns:
            float tensor [T, H, W] (or [T, h, w]) in the dtype of ``shade * values``.

        Raises:
            ShapeError: ``values`` is not one value per covered sample.
        """
        torch = _torch()
        h, w = self.hw if hw is None else hw
        if values is not None and tuple(values.shape) != tuple(self.shade.shape):
            raise ShapeError(f"values must be [{self.shade.shape[0]}], got {tuple(values.shape)}")
        lit = self.shade if values is None else self.shade.to(values.dtype) * values
        person = torch.zeros(self.num_frames * h * w, dtype=lit.dtype, device=lit.device)
        person.index_add_(0, self.sample_pixel if pixels is None else pixels, lit)
        return person.view(self.num_frames, h, w) / float(self.supersample**2)

    def render(self, texture=None, background=0.5, mode: str = "nearest", mask=None, size: int = 1024, fill=1.0):
        """One-shot texture lookup + :meth:`compose` (build the lookup once yourself when iterating).

        Args:
            texture: float tensor [n, n] (a grid upsampled to ``size``) or [size, size]; ``None`` = white.
            background: float [H, W] / [T, H, W] or a scalar intensity.
            mode, mask, size, fill: see :func:`davis_rig.scene.texture.prepare_lookup`.

        Returns:
            float tensor [T, H, W].
        """
        torch = _torch()
        if np.isscalar(background):
            background = torch.full(self.hw, float(background), dtype=self.coverage.dtype, device=self.coverage.device)
        if texture is None:
            return self.compose(None, background)
        n = texture.shape[-1]
        lookup = self.lookup(size=size, mode=mode, grid_n=None if n == size else n, mask=mask)
        return self.compose(lookup.sample(texture, fill=fill), background)

    def part_labels(self, face_parts) -> np.ndarray:
        """Part label per pixel (of the sample nearest the pixel centre), uint8 [T, H, W]; 255 = background.

        Args:
            face_parts: int array [F], part code per face.
        """
        torch = _torch()
        s = self.supersample
        h, w = self.hw
        ws = w * s
        rest = self.sample_index % (h * s * ws)
        centre = ((rest // ws) % s == s // 2) & ((rest % ws) % s == s // 2)
        parts = torch.as_tensor(np.asarray(face_parts, dtype=np.int64), device=self.face.device)
        labels = torch.full((self.num_frames * h * w,), EMPTY_PART, dtype=torch.int64, device=self.face.device)
        labels[self.sample_pixel[centre]] = parts[self.face[centre]]
        return labels.view(self.num_frames, h, w).to(torch.uint8).cpu().numpy()

    def boxes(self) -> np.ndarray:
        """Tight boxes of the covered pixels per frame, float32 [T, 4] ``(x0, y0, x1, y1)``; NaN if none."""
        return boxes_from_coverage(self.coverage)


def boxes_from_coverage(coverage, threshold: float = 0.0) -> np.ndarray:
    """Tight boxes of the pixels with coverage > threshold.

    Args:
        coverage: float tensor/array [T, H, W].
        threshold: pixels with alpha > threshold count as person.

    Returns:
        float32 [T, 4], ``(x0, y0, x1, y1)`` in pixel edges (``x1 = last column + 1``); NaN rows if empty.
    """
    cov = np.asarray(coverage.detach().cpu() if hasattr(coverage, "detach") else coverage)
    if cov.ndim != 3:
        raise ShapeError(f"coverage must be [T, H, W], got {cov.shape}")
    mask = cov > threshold
    cols = mask.any(axis=1)  # [T, W]
    rows = mask.any(axis=2)  # [T, H]
    out = np.full((cov.shape[0], 4), np.nan, dtype=np.float32)
    has = cols.any(axis=1)
    w, h = cov.shape[2], cov.shape[1]
    out[has, 0] = cols[has].argmax(axis=1)
    out[has, 2] = w - cols[has, ::-1].argmax(axis=1)
    out[has, 1] = rows[has].argmax(axis=1)
    out[has, 3] = h - rows[has, ::-1].argmax(axis=1)
    return out


def boxes_from_points(points_px, hw: tuple[int, int]) -> np.ndarray:
    """Boxes of projected points clipped to the frame.

    Args:
        points_px: float tensor [T, N, 3] ``(x_px, y_px, depth)``.
        hw: frame (height, width).

    Returns:
        float32 [T, 4] ``(x0, y0, x1, y1)``; NaN rows where a point is behind the camera or the box
        misses the frame.
    """
    h, w = hw
    if hasattr(points_px, "detach") and points_px.is_floating_point():
        # reduce in the tensor's own dtype, then widen: the same float64 extremes (the widening is exact and
        # monotonic) without a float64 copy of every point and a strided numpy reduction (~20 ms per clip)
        q = points_px.detach()
        lo = q[..., :2].amin(dim=1).cpu().double().numpy()
        hi = q[..., :2].amax(dim=1).cpu().double().numpy()
        behind = (q[..., 2] <= 0).any(dim=1).cpu().numpy()
    else:
        p = np.asarray(points_px.detach().cpu() if hasattr(points_px, "detach") else points_px, dtype=np.float64)
        lo = p[..., :2].min(axis=1)
        hi = p[..., :2].max(axis=1)
        behind = (p[..., 2] <= 0).any(axis=1)
    out = np.stack(
        [np.clip(lo[:, 0], 0, w), np.clip(lo[:, 1], 0, h), np.clip(hi[:, 0], 0, w), np.clip(hi[:, 1], 0, h)], axis=1
    ).astype(np.float32)
    bad = behind | (out[:, 2] <= out[:, 0]) | (out[:, 3] <= out[:, 1])
    out[bad] = np.nan
    return out


def _blend_corners(corners, bary):
    """``(corners * bary[..., None]).sum(dim=1)`` for [N, 3, D] corners, bit for bit, ~3x faster on CPU."""
    b = bary[..., None]
    return corners[:, 0] * b[:, 0] + corners[:, 1] * b[:, 1] + corners[:, 2] * b[:, 2]


def _rasterize_in_groups(projected, faces, hw: tuple[int, int], s: int, cull_backfaces: bool, group: int):
    """Rasterize the frames ``group`` at a time (bounded dense z-buffers): covered samples ``(sample, face, bary)``,
    ``sample`` flat over all frames (``t*(H s)*(W s) + row_s*(W s) + col_s``)."""
    torch = _torch()
    per_frame = hw[0] * s * hw[1] * s
    parts = {"sample": [], "face": [], "bary": []}
    for first in range(0, projected.shape[0], group):  # a few groups of frames at most
        frags = rasterize_sparse(projected[first : first + group], faces, hw, supersample=s,
                                 cull_backfaces=cull_backfaces)
        parts["sample"].append(frags.sample + first * per_frame)
        parts["face"].append(frags.face)
        parts["bary"].append(frags.bary)
    return torch.cat(parts["sample"]), torch.cat(parts["face"]), torch.cat(parts["bary"])


def _sample_pixels(sample, hw: tuple[int, int], s: int):
    """Frame int64 [N] and flat pixel ``t*H*W + row*W + col`` int64 [N] of flat sample indices [N]."""
    torch = _torch()
    h, w = hw
    per_frame = h * s * w * s
    frame = torch.div(sample, per_frame, rounding_mode="floor")
    rest = sample - frame * per_frame
    row = torch.div(rest, w * s, rounding_mode="floor")
    col = rest - row * (w * s)
    pixel = frame * (h * w) + torch.div(row, s, rounding_mode="floor") * w + torch.div(col, s, rounding_mode="floor")
    return frame, pixel


def _corner_normals(vertices_m, faces, face, frame):
    """Vertex normals of the three corners of each sample's face in its frame, [N, 3 corners, 3]."""
    normals = vertex_normals(vertices_m, faces)  # [T, V, 3]
    n_verts = normals.shape[1]
    corner = (faces.long().index_select(0, face) + (frame * n_verts)[:, None]).reshape(-1)
    return normals.reshape(-1, 3).index_select(0, corner).view(-1, 3, 3)


def rasterize_mesh(
    vertices_m,
    faces,
    face_uvs,
    camera: PinholeCamera,
    rotation_w2c,
    translation_w2c,
    supersample: int = 2,
    light: Light | None = None,
    cull_backfaces: bool = True,
    max_samples: int = 1 << 23,
) -> RasterizedMesh:
    """Rasterize a mesh sequence and prepare per-sample UVs and shades (no autograd).

    Args:
        vertices_m: float tensor [T, V, 3], world vertices (m).
        faces: int tensor [F, 3] (counter-clockwise from outside).
        face_uvs: float tensor [F, 3, 2], per-corner UVs (v up).
        camera: intrinsics (output size ``camera.hw``).
        rotation_w2c: [3, 3] or [T, 3, 3]; translation_w2c: [3] or [T, 3] (world -> camera, m).
        supersample: samples per pixel side.
        light: Lambert light (default :class:`Light`).
        cull_backfaces: see :func:`davis_rig.scene.rasterize.rasterize`.
        max_samples: frames are rasterized in groups of at most this many samples (``T_group * H s * W s``),
            which bounds the memory of the z-buffer (8 bytes per sample); only covered samples are kept.

    Returns:
        :class:`RasterizedMesh`.

    Raises:
        ShapeError: shapes do not match.
    """
    torch = _torch()
    light = Light() if light is None else light
    if vertices_m.ndim != 3 or vertices_m.shape[-1] != 3:
        raise ShapeError(f"vertices_m must be [T, V, 3], got {tuple(vertices_m.shape)}")
    if tuple(face_uvs.shape) != (faces.shape[0], 3, 2):
        raise ShapeError(f"face_uvs must be [{faces.shape[0]}, 3, 2], got {tuple(face_uvs.shape)}")
    with torch.no_grad():
        vertices_m = vertices_m.detach()
        projected = camera.project(vertices_m, rotation_w2c, translation_w2c)
        h, w = camera.hw
        s = int(supersample)
        t = vertices_m.shape[0]
        group = max(1, int(max_samples) // (h * s * w * s))
        sample, face, bary = _rasterize_in_groups(projected, faces, camera.hw, s, cull_backfaces, group)
        frame, pixel = _sample_pixels(sample, camera.hw, s)
        uv = _blend_corners(torch.as_tensor(face_uvs, device=vertices_m.device).to(vertices_m.dtype)
                            .index_select(0, face), bary)
        shade = lambert(_blend_corners(_corner_normals(vertices_m, faces, face, frame), bary), light)
        counts = torch.bincount(pixel, minlength=t * h * w)  # cheaper than pooling the dense sample map
        coverage = (counts.to(vertices_m.dtype) / float(s * s)).view(t, h, w)
    return RasterizedMesh(
        hw=(h, w),
        supersample=s,
        num_frames=t,
        sample_pixel=pixel,
        face=face,
        uv=uv,
        shade=shade,
        coverage=coverage,
        vertex_boxes=boxes_from_points(projected, (h, w)),
        sample_index=sample,
    )
