"""A preview of a texture on the body: front and back of the textured rest-pose body (torch, the toolkit's renderer)."""

from __future__ import annotations

from typing import Iterable

import numpy as np

from davis_rig.attack.export.pattern import DEFAULT_PARTS
from davis_rig.errors import MissingDependencyError
from davis_rig.scene.body import BodyAsset

__all__ = ["render_preview"]

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
