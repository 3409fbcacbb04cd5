"""Triangle rasterizer without autograd: per-sample face id, perspective-correct barycentrics and depth.

Only the texture is optimised, so geometry needs no gradients: the rasterizer runs once per clip under
``torch.no_grad`` and the differentiable part (texture lookup + compositing, :mod:`davis_rig.scene.renderer`)
reuses its output at every optimiser step.

Algorithm (vectorised torch, identical on CPU and CUDA, batched over frames):

1. project vertices (done by the caller) and gather the triangles of every frame, cull back faces,
   faces behind the near plane and faces whose bounding box holds no sample centre;
2. enumerate candidate (face, sample) pairs of every face's bounding box with ``repeat_interleave``;
3. evaluate the barycentrics as affine functions of the sample centre in bbox-local coordinates, keep the
   samples inside (edges inclusive: no cracks between neighbours; the z-buffer resolves the double hits);
4. z-buffer: pack ``float32 depth bits << 32 | face`` into one int64 key (positive float32 bits sort like
   the floats, the face id makes keys unique) and ``scatter_reduce(amin)`` the keys per sample; a pair wins
   iff its key equals the minimum;
5. keep face id, perspective-correct barycentrics (``b_i/z_i`` renormalised) and depth of the winners
   (:func:`rasterize_sparse`; :func:`rasterize` expands them into dense maps).

Supersampling ``s`` rasterizes at ``s x`` the resolution (sample centres at ``(j + (a + 0.5)/s)`` in pixels);
coverage alpha is the fraction of covered samples per pixel.

Why this rasterizer (figures from ``benchmarks/render.py``, 10 walk frames of the 27,420-face body at the
middle scale, 304 x 240, 1 thread on a shared, loaded 2-core CPU, so +-30 %):

- The body at 130-175 px is mostly sub-pixel triangles: the bounding-box pair list is only 3.6 candidates
  per covered sample at s = 1, 2 and 3, so a frame is a handful of large tensor ops with no per-face or
  per-pixel Python loop, batched over frames (which is what a GPU needs). Measured: 4.0 / 7.1-7.6 / 17 ms
  per frame for s = 1 / 2 / 3 (rasterization only; with projection, normals, UVs and shades
  :func:`~davis_rig.scene.renderer.rasterize_mesh` takes 5.9 / 9.3 / 19-27 ms). The optimiser reuses
  the raster of a clip: one texture step (lookup + compositing + backward) costs 0.25-1.1 ms/frame.
  With 2 threads nothing could be measured reliably on this shared box (other jobs took the cores).
- NVIDIA warp (``benchmarks/render.py --warp``: the same algorithm as warp kernels, one thread per
  triangle, atomic-min depth pass + face-id pass, face ids only): 3.7 / 5.2-5.4 / 7.3-12 ms per frame on
  the same CPU (two runs), identical face ids, i.e. 1.1x / 1.4x / 1.4-2.3x faster than torch here, but it
  needs the ``warp-lang`` runtime (not a dependency of this package; anny's), a kernel build per machine
  and warp version (4.5 s on first use) and copies between the two array runtimes. At the default s = 2
  the gain is about 2 ms per frame of a step that runs once per clip, so torch stays the single code path.
- Ray casting needs a BVH of the deforming mesh for every frame (27k triangles), more work than
  rasterizing them; not measured.
- OpenGL via moderngl/EGL needs a GPU driver or a software Mesa (llvmpipe) with EGL in every environment
  (this box and CI have no EGL) and a read-back per frame; results would also differ by driver. Not
  measured (no EGL here).
"""

from __future__ import annotations

from dataclasses import dataclass

from davis_rig._lazy import optional_import
from davis_rig.errors import ShapeError

__all__ = ["Fragments", "SparseFragments", "rasterize", "rasterize_sparse"]


def _torch():
    return optional_import("torch", "the rasterizer")


@dataclass
class Fragments:
    """Rasterizer output at sample resolution ``(H*s, W*s)``.

    Attributes:
        face_id: int64 [T, H*s, W*s], index into the faces, -1 where no face covers the sample.
        bary: float [T, H*s, W*s, 3], perspective-correct barycentric weights (0 where uncovered).
        depth_m: float [T, H*s, W*s], camera depth z of the visible surface (m, ``inf`` where uncovered).
        supersample: samples per pixel side ``s``.
    """

    face_id: "object"
    bary: "object"
    depth_m: "object"
    supersample: int

    @property
    def covered(self):
        """bool [T, H*s, W*s], samples covered by a face."""
        return self.face_id >= 0

    def coverage(self):
        """Fraction of covered samples per pixel, float32 [T, H, W] in [0, 1]."""
        s = self.supersample
        t, hs, ws = self.face_id.shape
        mask = self.covered.to(self.bary.dtype).reshape(t, hs // s, s, ws // s, s)
        return mask.mean(dim=(2, 4))


@dataclass
class SparseFragments:
    """Rasterizer output for the covered samples only (what the renderer consumes).

    Attributes:
        sample: int64 [N], flat sample index ``t*(H s)*(W s) + row*(W s) + col`` (each at most once).
        face: int64 [N], visible face.
        bary: float [N, 3], perspective-correct barycentric weights.
        depth_m: float [N], camera depth of the visible surface (m).
        shape: ``(T, H*s, W*s)``; supersample: ``s``.
    """

    sample: "object"
    face: "object"
    bary: "object"
    depth_m: "object"
    shape: tuple[int, int, int]
    supersample: int

    def to_dense(self) -> Fragments:
        """The same result as dense per-sample maps (:class:`Fragments`)."""
        torch = _torch()
        t, hs, ws = self.shape
        n = t * hs * ws
        device = self.face.device
        face = torch.full((n,), -1, dtype=torch.int64, device=device)
        bary = torch.zeros((n, 3), dtype=self.bary.dtype, device=device)
        depth = torch.full((n,), float("inf"), dtype=self.depth_m.dtype, device=device)
        face[self.sample] = self.face
        bary[self.sample] = self.bary
        depth[self.sample] = self.depth_m
        return Fragments(face.view(t, hs, ws), bary.view(t, hs, ws, 3), depth.view(t, hs, ws), self.supersample)


def rasterize(
    vertices_px,
    faces,
    hw: tuple[int, int],
    supersample: int = 1,
    cull_backfaces: bool = True,
    near_m: float = 1e-3,
    max_pairs: int = 1 << 22,
) -> Fragments:
    """Rasterize triangles of a batch of frames into dense per-sample maps (no autograd).

    Same arguments as :func:`rasterize_sparse`; returns ``rasterize_sparse(...).to_dense()``.

    Returns:
        :class:`Fragments` at ``(H*s, W*s)``.
    """
    return rasterize_sparse(vertices_px, faces, hw, supersample, cull_backfaces, near_m, max_pairs).to_dense()


def _check_inputs(vertices_px, faces, hw: tuple[int, int], supersample: int) -> tuple[int, int, int]:
    """``(s, h, w)`` of valid arguments of :func:`rasterize_sparse`; ShapeError / ValueError otherwise."""
    if vertices_px.ndim != 3 or vertices_px.shape[-1] != 3:
        raise ShapeError(f"vertices_px must be [T, V, 3], got {tuple(vertices_px.shape)}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise ShapeError(f"faces must be [F, 3], got {tuple(faces.shape)}")
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    h, w = int(hw[0]), int(hw[1])
    if h < 1 or w < 1:
        raise ValueError(f"image size must be positive, got {hw}")
    return s, h, w


@dataclass
class _Candidates:
    """The (frame, face) pairs whose bounding box holds sample centres, with their barycentric set-up.

    Attributes:
        live: int64 [L], flat ``frame * F + face`` of each pair; counts: int64 [L], samples in its bounding box.
        ox, oy: float [L], the box origin (sample units); bw, bh: float [L], its width and height (samples).
        table: float [L, 7], ``(db0/dcx, db0/dcy, b0(0), db1/dcx, db1/dcy, b1(0), bw)`` in box-local coordinates.
        z_table: float [L, 3], the corners' depths (m).
    """

    live: "object"
    counts: "object"
    ox: "object"
    oy: "object"
    bw: "object"
    bh: "object"
    table: "object"
    z_table: "object"


def _candidates(comp, faces, n_frames: int, hs: int, ws: int, cull_backfaces: bool, near_m: float):
    """Cull the triangles of every frame and set up the barycentrics of the survivors (:class:`_Candidates`).

    Args:
        comp: float [3 T, V], coordinate-major sample-unit vertices (x rows, then y, then depth).

    Returns:
        :class:`_Candidates`, or ``None`` when no face's bounding box holds a sample centre.
    """
    torch = _torch()
    n_faces = faces.shape[0]
    fl = faces.long()
    c0, c1, c2 = (comp.index_select(1, fl[:, k]).view(3, n_frames, n_faces) for k in range(3))  # each [3, T, F]
    x0_, x1_, x2_ = c0[0], c1[0], c2[0]
    y0_, y1_, y2_ = c0[1], c1[1], c2[1]
    area = (x1_ - x0_) * (y2_ - y0_) - (x2_ - x0_) * (y1_ - y0_)
    keep = (c0[2] > near_m) & (c1[2] > near_m) & (c2[2] > near_m) & (area != 0)
    if cull_backfaces:
        keep &= area < 0  # counter-clockwise as seen = negative signed area in y-down pixel coordinates
    # sample j has its centre at j + 0.5 (sample units): the bbox holds j in [ceil(min-0.5), floor(max-0.5)]
    xmin = torch.ceil(torch.minimum(torch.minimum(x0_, x1_), x2_) - 0.5).clamp(0, ws)
    xmax = torch.floor(torch.maximum(torch.maximum(x0_, x1_), x2_) - 0.5).clamp(-1, ws - 1)
    ymin = torch.ceil(torch.minimum(torch.minimum(y0_, y1_), y2_) - 0.5).clamp(0, hs)
    ymax = torch.floor(torch.maximum(torch.maximum(y0_, y1_), y2_) - 0.5).clamp(-1, hs - 1)
    bw = (xmax - xmin + 1).clamp(min=0)
    bh = (ymax - ymin + 1).clamp(min=0)
    counts = torch.where(keep, bw * bh, torch.zeros_like(bw)).reshape(-1).long()  # [T*F]
    live = torch.nonzero(counts > 0).squeeze(1)
    if live.numel() == 0:
        return None
    pick = lambda a: a.reshape(-1).index_select(0, live)  # noqa: E731
    # Barycentrics as affine functions of the sample centre in bbox-local coordinates (small numbers,
    # no cancellation): b_i(cx, cy) = a_i * cx + c_i * cy + k_i with cx = dx + 0.5, cy = dy + 0.5.
    ox, oy = pick(xmin), pick(ymin)
    lx = [pick(x0_) - ox, pick(x1_) - ox, pick(x2_) - ox]
    ly = [pick(y0_) - oy, pick(y1_) - oy, pick(y2_) - oy]
    inv_area = 1.0 / pick(area)
    coeffs = []
    for i, j, k in ((0, 1, 2), (1, 2, 0)):  # b_i is the edge function of the opposite edge (j, k)
        coeffs += [
            (ly[j] - ly[k]) * inv_area,  # d b_i / d cx
            (lx[k] - lx[j]) * inv_area,  # d b_i / d cy
            (lx[j] * ly[k] - lx[k] * ly[j]) * inv_area,  # b_i at the bbox-local origin
        ]
    table = torch.stack(coeffs + [pick(bw)], dim=1)  # [L, 7]
    z_table = torch.stack([pick(c0[2]), pick(c1[2]), pick(c2[2])], dim=1)  # [L, 3]
    return _Candidates(live, counts.index_select(0, live), ox, oy, pick(bw), pick(bh), table, z_table)


def _chunk_bounds(counts, max_pairs: int) -> list[int]:
    """Boundaries of consecutive candidate chunks with <= ``max_pairs`` (face, sample) pairs each (a single huge
    face forms its own chunk)."""
    torch = _torch()
    cumulative = torch.cumsum(counts, 0)
    bounds = [0]
    total = int(cumulative[-1])
    if total > max_pairs:
        marks = torch.arange(max_pairs, total, max_pairs, device=counts.device)
        cuts = torch.searchsorted(cumulative, marks, right=True).tolist()
        bounds += [c for c in cuts if 0 < c < counts.numel()]
    bounds.append(counts.numel())
    return sorted(set(bounds))


def _inside_samples(cand: _Candidates, lo: int, hi: int, n_faces: int, hs: int, ws: int, box) -> dict | None:
    """The (face, sample) pairs of candidates ``[lo, hi)`` whose sample centre lies inside the triangle.

    Args:
        box: ``(x0, y0, w, h)`` of the z-buffer window (sample units).

    Returns:
        ``{"row": candidate [N], "sample": flat sample [N], "slot": z-buffer slot [N], "b": barycentrics [N, 3]}``,
        or ``None`` when no sample of the chunk is inside.
    """
    torch = _torch()
    device = cand.counts.device
    box_x0, box_y0, box_w, box_h = box
    cnt = cand.counts[lo:hi]
    n = int(cnt.sum())
    rows = torch.repeat_interleave(torch.arange(lo, hi, device=device), cnt, output_size=n)
    starts = torch.cumsum(cnt, 0) - cnt
    local = torch.arange(n, device=device) - torch.repeat_interleave(starts, cnt, output_size=n)
    tab = cand.table.index_select(0, rows)
    width = tab[:, 6].long()
    dy = torch.div(local, width, rounding_mode="floor")
    dx = local - dy * width
    cx = dx.to(tab.dtype) + 0.5
    cy = dy.to(tab.dtype) + 0.5
    b0 = tab[:, 0] * cx + tab[:, 1] * cy + tab[:, 2]
    b1 = tab[:, 3] * cx + tab[:, 4] * cy + tab[:, 5]
    b2 = 1.0 - b0 - b1
    sel = torch.nonzero((b0 >= 0) & (b1 >= 0) & (b2 >= 0)).squeeze(1)
    if sel.numel() == 0:
        return None
    row = rows.index_select(0, sel)
    frame = torch.div(cand.live.index_select(0, row), n_faces, rounding_mode="floor")
    px = cand.ox.index_select(0, row).long() + dx.index_select(0, sel)
    py = cand.oy.index_select(0, row).long() + dy.index_select(0, sel)
    return {"row": row, "sample": frame * (hs * ws) + py * ws + px,
            "slot": frame * (box_h * box_w) + (py - box_y0) * box_w + (px - box_x0),
            "b": torch.stack([b0.index_select(0, sel), b1.index_select(0, sel), b2.index_select(0, sel)], 1)}


def rasterize_sparse(
    vertices_px,
    faces,
    hw: tuple[int, int],
    supersample: int = 1,
    cull_backfaces: bool = True,
    near_m: float = 1e-3,
    max_pairs: int = 1 << 22,
) -> SparseFragments:
    """Rasterize triangles of a batch of frames; covered samples only (no autograd).

    Args:
        vertices_px: float tensor [T, V, 3]: ``(x_px, y_px, depth_m)`` in continuous pixel coordinates of
            the output image (pixel ``(i, j)`` covers ``[j, j+1) x [i, i+1)``; see :mod:`.camera`).
        faces: int tensor [F, 3], vertex indices; counter-clockwise seen from the front (outside).
        hw: output image (height, width) in pixels.
        supersample: samples per pixel side ``s >= 1``.
        cull_backfaces: drop faces seen from behind (clockwise on screen). Closed meshes render the same
            either way; culling halves the work.
        near_m: faces with a vertex at depth <= near_m are dropped (m).
        max_pairs: candidate (face, sample) pairs processed per chunk (bounds the temporary memory).

    Returns:
        :class:`SparseFragments`, samples in increasing frame order.

    Raises:
        ShapeError: vertices not [T, V, 3] or faces not [F, 3].
        ValueError: supersample < 1 or a non-positive image size.
    """
    torch = _torch()
    s, h, w = _check_inputs(vertices_px, faces, hw, supersample)
    device = vertices_px.device
    dtype = vertices_px.dtype
    n_frames = vertices_px.shape[0]
    n_faces = faces.shape[0]
    hs, ws = h * s, w * s
    empty_i = torch.zeros(0, dtype=torch.int64, device=device)
    result = SparseFragments(
        sample=empty_i,
        face=empty_i,
        bary=torch.zeros((0, 3), dtype=dtype, device=device),
        depth_m=torch.zeros(0, dtype=dtype, device=device),
        shape=(n_frames, hs, ws),
        supersample=s,
    )
    if n_faces == 0 or n_frames == 0:
        return result
    with torch.no_grad():
        scale = torch.tensor([s, s, 1.0], dtype=dtype, device=device)
        # coordinate-major [3 T, V] so each corner gather is one index_select along the last dim of a 2-D tensor
        # (3-4x faster than the same gather along dim 2 of [3, T, V] on CPU)
        comp = (vertices_px * scale).permute(2, 0, 1).reshape(3 * n_frames, -1)
        cand = _candidates(comp, faces, n_frames, hs, ws, cull_backfaces, near_m)
        if cand is None:
            return result
        # the z-buffer spans only the union of the live bounding boxes (a slot per sample of that window in every
        # frame): a buffer of all T*H s*W s samples costs more in page faults than the rest of the z-buffer
        box_x0, box_y0 = int(cand.ox.min()), int(cand.oy.min())
        box = (box_x0, box_y0, int((cand.ox + cand.bw).max()) - box_x0, int((cand.oy + cand.bh).max()) - box_y0)
        bounds = _chunk_bounds(cand.counts, max_pairs)
        found = [f for f in (_inside_samples(cand, lo, hi, n_faces, hs, ws, box)
                             for lo, hi in zip(bounds[:-1], bounds[1:])) if f is not None]
        if not found:
            return result
        _resolve_visibility(result, cand, found, n_faces, n_frames * box[2] * box[3])
    return result


def _resolve_visibility(result: SparseFragments, cand: _Candidates, found: list[dict], n_faces: int,
                        z_slots: int) -> None:
    """z-buffer over the candidate samples only: the nearest (face, sample) pair of every sample wins; its face,
    perspective-correct barycentrics and depth go into ``result``.

    Keys pack ``float32 depth bits << 32 | face`` (unique per pair, ordered like the depths); only the ``z_slots``
    slots of candidate samples are written (include_self=False) and read, so the buffer is left uninitialised.
    """
    torch = _torch()
    row = torch.cat([f["row"] for f in found])
    sample = torch.cat([f["sample"] for f in found])
    w_persp = torch.cat([f["b"] for f in found]) / cand.z_table.index_select(0, row)
    depth = 1.0 / w_persp.sum(dim=1)
    face_frame = cand.live.index_select(0, row)
    face = face_frame - torch.div(face_frame, n_faces, rounding_mode="floor") * n_faces
    key = (depth.float().view(torch.int32).long() << 32) | face
    slot = torch.cat([f["slot"] for f in found])
    zbuf = torch.empty((z_slots,), dtype=torch.int64, device=key.device)
    zbuf.scatter_reduce_(0, slot, key, reduce="amin", include_self=False)
    win = torch.nonzero(key == zbuf.index_select(0, slot)).squeeze(1)
    result.sample = sample.index_select(0, win)
    result.face = face.index_select(0, win)
    result.bary = w_persp.index_select(0, win) * depth.index_select(0, win)[:, None]
    result.depth_m = depth.index_select(0, win)
