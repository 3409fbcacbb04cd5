"""Renderer: a textured quad renders to known pixels, d(image)/d(texture) is the analytic sparse map,
part masks land on the intended body parts, boxes contain the person."""

import math

import numpy as np
import pytest
import torch

from davis_rig.errors import ShapeError
from davis_rig.scene.camera import PinholeCamera, distance_for_height, look_at
from davis_rig.scene.masks import PAINTABLE_PARTS, part_mask
from davis_rig.scene.renderer import EMPTY_PART, boxes_from_coverage, rasterize_mesh
from davis_rig.scene.shading import Light

CAMERA = PinholeCamera(width_px=16, height_px=12, fx_px=10.0, fy_px=10.0, cx_px=8.0, cy_px=6.0)
FLAT = Light(direction=(0.0, 0.0, -1.0), ambient=1.0, diffuse=0.0)


def _quad_scene(tilt_rad=0.0, dtype=torch.float64):
    """A quad at z = 1 in camera axes spanning pixels x in [4, 12), y in [3, 9); u right, v up."""
    corners = np.array([[-0.4, -0.3, 0.0], [-0.4, 0.3, 0.0], [0.4, 0.3, 0.0], [0.4, -0.3, 0.0]])  # TL BL BR TR
    c, s = math.cos(tilt_rad), math.sin(tilt_rad)
    corners = corners @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T + [0.0, 0.0, 1.0]
    vertices = torch.as_tensor(corners, dtype=dtype)[None]
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uv_corner = torch.tensor([[0.0, 1.0], [0.0, 0.0], [1.0, 0.0], [1.0, 1.0]], dtype=dtype)
    return vertices, faces, uv_corner[faces]


def _render_quad(texture, supersample=2, tilt_rad=0.0, light=FLAT, mode="nearest"):
    vertices, faces, face_uvs = _quad_scene(tilt_rad)
    raster = rasterize_mesh(vertices, faces, face_uvs, CAMERA, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), supersample=supersample, light=light)
    return raster, raster.render(texture, background=0.25, mode=mode, size=texture.shape[-1])


def test_textured_quad_renders_known_pixels():
    texture = torch.tensor([[0.9, 0.1], [0.6, 0.3]], dtype=torch.float64)
    raster, image = _render_quad(texture)
    expected = np.full((12, 16), 0.25)
    expected[3:6, 4:8] = 0.9
    expected[3:6, 8:12] = 0.1
    expected[6:9, 4:8] = 0.6
    expected[6:9, 8:12] = 0.3
    np.testing.assert_allclose(image[0].numpy(), expected, atol=1e-12)
    assert raster.boxes().tolist() == [[4.0, 3.0, 12.0, 9.0]]
    np.testing.assert_allclose(raster.vertex_boxes, [[4.0, 3.0, 12.0, 9.0]], atol=1e-5)


def test_lambert_shade_scales_the_texture():
    texture = torch.ones(2, 2, dtype=torch.float64)
    light = Light(direction=(0.0, -1.0, -1.0), ambient=0.2, diffuse=0.8)  # 45 deg to the quad normal (0, 0, -1)
    _, image = _render_quad(texture, light=light)
    assert image[0, 5, 6].item() == pytest.approx(0.2 + 0.8 * math.cos(math.pi / 4))


def test_official_light_lights_the_image_left_side_and_leaves_the_front_at_ambient():
    from davis_rig.scene.shading import lambert

    normals = torch.tensor([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    np.testing.assert_allclose(lambert(normals, Light.official()).numpy(), [0.5, 0.8, 0.5])  # front, left, right


def test_image_gradient_is_the_sparse_cell_map():
    texture = torch.rand(2, 2, dtype=torch.float64)
    jac = torch.autograd.functional.jacobian(lambda t: _render_quad(t)[1], texture)  # [1, 12, 16, 2, 2]
    expected = np.zeros((1, 12, 16, 2, 2))
    expected[0, 3:6, 4:8, 0, 0] = 1.0
    expected[0, 3:6, 8:12, 0, 1] = 1.0
    expected[0, 6:9, 4:8, 1, 0] = 1.0
    expected[0, 6:9, 8:12, 1, 1] = 1.0
    np.testing.assert_allclose(jac.numpy(), expected, atol=1e-12)


def test_image_gradient_is_the_analytic_map_with_shading_and_bilinear():
    rng = np.random.default_rng(0)
    texture = torch.as_tensor(rng.random((8, 8)))
    light = Light(direction=(0.3, -0.5, -1.0), ambient=0.3, diffuse=0.7)
    raster, _ = _render_quad(texture, supersample=3, tilt_rad=0.5, light=light, mode="bilinear")
    jac = torch.autograd.functional.jacobian(lambda t: _render_quad(t, 3, 0.5, light, "bilinear")[1], texture)
    # analytic: dI(p)/dT[k] = (1/s^2) * sum over samples q of p of shade(q) * bilinear weight_k(uv(q))
    expected = np.zeros((12 * 16, 64))
    x = raster.uv[:, 0].numpy() * 8 - 0.5
    y = (1 - raster.uv[:, 1].numpy()) * 8 - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dx, dy, weight in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        k = np.clip(y0 + dy, 0, 7) * 8 + np.clip(x0 + dx, 0, 7)
        np.add.at(expected, (raster.sample_pixel.numpy(), k), raster.shade.numpy() * weight / 9.0)
    np.testing.assert_allclose(jac.reshape(12 * 16, 64).numpy(), expected, atol=1e-12)
    assert (jac.reshape(12 * 16, 64).abs().sum(1) > 0).sum() > 40  # non-trivial: many pixels depend on it


def test_compose_checks_shapes():
    raster, _ = _render_quad(torch.ones(2, 2, dtype=torch.float64))
    with pytest.raises(ShapeError):
        raster.compose(None, torch.zeros(5, 5))
    with pytest.raises(ShapeError):
        raster.compose(torch.zeros(3, dtype=torch.float64), torch.zeros(12, 16))


@pytest.fixture(scope="module")
def body_raster(model):
    """Two frames of the walk (side and front view), large scale, one sample per pixel."""
    verts = model.walk_vertices(0, [0.0, 0.3], advance=False)
    heading = [math.pi / 2, 0.0]
    out = []
    for t, angle in enumerate(heading):
        c, s = math.cos(angle), math.sin(angle)
        rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.append(verts[t] @ rz.T)
    verts = torch.stack(out)
    cam = PinholeCamera.rvt_crop()
    d = distance_for_height("large")
    rotation, translation = look_at([0.0, -d, 0.875], [0.0, 0.0, 0.875])
    return rasterize_mesh(
        verts, model.faces, model.face_uvs, cam, torch.as_tensor(rotation, dtype=torch.float32),
        torch.as_tensor(translation, dtype=torch.float32), supersample=1, light=FLAT,
    )  # fmt: skip


@pytest.mark.parametrize("parts", [(p,) for p in PAINTABLE_PARTS] + [PAINTABLE_PARTS])
def test_masks_cover_the_intended_parts(body_raster, asset, parts):
    """Black texture inside the UV mask, white outside: the black pixels are the pixels of those parts."""
    mask = part_mask(parts)
    image = body_raster.render(torch.zeros(1024, 1024), background=1.0, mask=mask, fill=1.0)
    labels = body_raster.part_labels(asset.face_parts)
    codes = [asset.part_names.index(p) for p in parts]
    person = labels != EMPTY_PART
    painted = image.numpy() < 0.5
    in_part = np.isin(labels, codes)
    assert in_part.sum() > 200
    agreement = (painted == in_part)[person].mean()
    assert agreement > 0.995, f"{parts}: {agreement:.4f}"
    assert not painted[~person].any()


def test_boxes_contain_the_person(body_raster):
    cov = body_raster.coverage.numpy()
    boxes = body_raster.boxes()
    for t in range(cov.shape[0]):
        rows, cols = np.nonzero(cov[t] > 0)
        x0, y0, x1, y1 = boxes[t]
        assert (x0, y0, x1, y1) == (cols.min(), rows.min(), cols.max() + 1, rows.max() + 1)
        vx0, vy0, vx1, vy1 = body_raster.vertex_boxes[t]
        assert np.floor(vx0) <= x0 and np.floor(vy0) <= y0 and x1 <= np.ceil(vx1) and y1 <= np.ceil(vy1)
        height = y1 - y0
        assert 150 < height < 200  # large scale: 175 px for 1.75 m


def test_boxes_from_coverage_empty_and_clipped():
    cov = np.zeros((2, 4, 5))
    cov[1, 0, 4] = 0.5
    boxes = boxes_from_coverage(cov)
    assert np.isnan(boxes[0]).all()
    assert boxes[1].tolist() == [4.0, 0.0, 5.0, 1.0]


def test_frame_groups_give_the_same_raster(model):
    verts = model.walk_vertices(1, [0.0, 0.1, 0.2])
    cam = PinholeCamera.rvt_crop()
    rotation, translation = look_at([0.0, -6.0, 0.875], [0.0, 0.0, 0.875])
    args = (verts, model.faces, model.face_uvs, cam, torch.as_tensor(rotation, dtype=torch.float32), torch.as_tensor(translation, dtype=torch.float32))
    whole = rasterize_mesh(*args, supersample=2)
    grouped = rasterize_mesh(*args, supersample=2, max_samples=240 * 304 * 4)  # one frame per group
    assert torch.equal(whole.sample_index, grouped.sample_index)
    assert torch.equal(whole.face, grouped.face) and torch.equal(whole.uv, grouped.uv)
    assert torch.equal(whole.coverage, grouped.coverage)
    labels = whole.part_labels(model.asset.face_parts)
    assert labels.shape == (3, 240, 304) and set(np.unique(labels)) <= set(range(6)) | {EMPTY_PART}
