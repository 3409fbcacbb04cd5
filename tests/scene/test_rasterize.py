"""Rasterizer: known pixels, z-buffer, perspective-correct barycentrics, culling, chunking, brute-force reference."""

import numpy as np
import pytest
import torch

from davis_rig.errors import ShapeError
from davis_rig.scene.rasterize import rasterize


def _quad(x0, y0, x1, y1, z=1.0, dtype=torch.float64):
    """Screen-space quad, front-facing (counter-clockwise as seen on the y-down screen)."""
    v = torch.tensor([[x0, y0, z], [x0, y1, z], [x1, y1, z], [x1, y0, z]], dtype=dtype)
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return v, f


def test_quad_covers_known_pixels():
    v, f = _quad(2.0, 1.0, 6.0, 4.0)
    frags = rasterize(v[None], f, (6, 8))
    expected = np.zeros((6, 8), dtype=bool)
    expected[1:4, 2:6] = True  # pixel centres (j + 0.5, i + 0.5) inside [2, 6] x [1, 4]
    assert np.array_equal(frags.covered[0].numpy(), expected)
    assert np.array_equal(frags.coverage()[0].numpy(), expected.astype(np.float64))
    assert torch.all(frags.depth_m[0][frags.covered[0]] == 1.0)
    assert torch.isinf(frags.depth_m[0][~frags.covered[0]]).all()
    np.testing.assert_allclose(frags.bary[0][frags.covered[0]].sum(-1).numpy(), 1.0, atol=1e-12)


def test_supersampled_coverage_of_half_pixels():
    v, f = _quad(2.5, 1.0, 6.0, 3.5)
    cov = rasterize(v[None], f, (5, 8), supersample=2).coverage()[0].numpy()
    expected = np.zeros((5, 8))
    expected[1:3, 3:6] = 1.0
    expected[1:3, 2] = 0.5
    expected[3, 3:6] = 0.5
    expected[3, 2] = 0.25
    np.testing.assert_allclose(cov, expected)


def test_backface_culling_and_winding():
    v, f = _quad(2.0, 1.0, 6.0, 4.0)
    back = f[:, [0, 2, 1]]
    assert not rasterize(v[None], back, (6, 8)).covered.any()
    both = rasterize(v[None], back, (6, 8), cull_backfaces=False)
    assert torch.equal(both.covered, rasterize(v[None], f, (6, 8)).covered)


def test_zbuffer_nearest_wins_in_any_order():
    near_v, near_f = _quad(0.0, 0.0, 4.0, 4.0, z=1.0)
    far_v, far_f = _quad(2.0, 2.0, 6.0, 6.0, z=2.0)
    vertices = torch.cat([near_v, far_v])[None]
    for faces in (torch.cat([near_f, far_f + 4]), torch.cat([far_f + 4, near_f])):
        frags = rasterize(vertices, faces, (6, 6))
        depth = frags.depth_m[0].numpy()
        assert np.all(depth[:4, :4] == 1.0)
        assert np.all(depth[4:, 2:] == 2.0) and np.all(depth[2:, 4:] == 2.0)
        assert np.isinf(depth[:2, 4:]).all() and np.isinf(depth[4:, :2]).all()


def test_perspective_correct_barycentrics_reproject_to_sample_centres():
    f_px, c = 20.0, 10.0
    cam_pts = torch.tensor([[-0.4, -0.3, 1.0], [-0.3, 0.4, 3.0], [0.5, 0.1, 2.0]], dtype=torch.float64)
    screen = torch.stack([f_px * cam_pts[:, 0] / cam_pts[:, 2] + c, f_px * cam_pts[:, 1] / cam_pts[:, 2] + c, cam_pts[:, 2]], 1)
    faces = torch.tensor([[0, 1, 2]])
    frags = rasterize(screen[None], faces, (20, 20), supersample=2, cull_backfaces=False)
    covered = frags.covered[0]
    assert covered.sum() > 50
    rows, cols = torch.nonzero(covered, as_tuple=True)
    point = frags.bary[0][rows, cols] @ cam_pts  # 3-D point from the barycentrics
    x = f_px * point[:, 0] / point[:, 2] + c
    y = f_px * point[:, 1] / point[:, 2] + c
    np.testing.assert_allclose(x.numpy(), (cols.double() + 0.5).numpy() / 2, atol=1e-9)
    np.testing.assert_allclose(y.numpy(), (rows.double() + 0.5).numpy() / 2, atol=1e-9)
    np.testing.assert_allclose(frags.depth_m[0][rows, cols].numpy(), point[:, 2].numpy(), atol=1e-9)


def test_near_plane_drops_faces_behind_camera():
    v, f = _quad(0.0, 0.0, 4.0, 4.0, z=1.0)
    v[1, 2] = -1.0  # vertex 1 behind the camera: face 0 (0, 1, 2) is dropped, face 1 (0, 2, 3) stays
    frags = rasterize(v[None], f, (4, 4))
    assert set(torch.unique(frags.face_id).tolist()) == {-1, 1}
    assert frags.covered.any()


def _brute_force(vertices, faces, hw):
    """Reference z-buffer: every face against every pixel centre (numpy broadcasting)."""
    h, w = hw
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    tri = vertices[faces]  # [F, 3, 3]
    x, y, z = tri[..., 0], tri[..., 1], tri[..., 2]
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    e = lambda a, b: (x[:, a, None, None] - xx) * (y[:, b, None, None] - yy) - (x[:, b, None, None] - xx) * (y[:, a, None, None] - yy)  # noqa: E731
    b0 = e(1, 2) / area[:, None, None]
    b1 = e(2, 0) / area[:, None, None]
    b2 = 1 - b0 - b1
    inside = (b0 >= 0) & (b1 >= 0) & (b2 >= 0) & (area < 0)[:, None, None]
    inv_z = b0 / z[:, 0, None, None] + b1 / z[:, 1, None, None] + b2 / z[:, 2, None, None]
    depth = np.where(inside, 1 / inv_z, np.inf)
    return depth.min(axis=0), np.where(np.isfinite(depth.min(axis=0)), depth.argmin(axis=0), -1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_triangles_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = 40
    centres = rng.uniform(-2, 26, size=(n, 1, 2))
    corners = centres + rng.normal(scale=4.0, size=(n, 3, 2))
    depth = rng.uniform(1.0, 5.0, size=(n, 3, 1))
    vertices = np.concatenate([corners, depth], axis=-1).reshape(-1, 3)
    faces = np.arange(3 * n).reshape(n, 3)
    ref_depth, ref_face = _brute_force(vertices, faces, (20, 24))
    for max_pairs in (1 << 20, 64):  # single chunk and many chunks give the same result
        frags = rasterize(torch.as_tensor(vertices)[None], torch.as_tensor(faces), (20, 24), max_pairs=max_pairs)
        np.testing.assert_allclose(frags.depth_m[0].numpy(), ref_depth, rtol=1e-9)
        finite = np.isfinite(ref_depth)
        assert np.array_equal(frags.face_id[0].numpy()[finite] >= 0, np.ones(finite.sum(), bool))
        # face ids agree wherever the nearest surface is unique
        agree = frags.face_id[0].numpy() == ref_face
        assert agree.mean() > 0.99


def test_frames_are_independent_in_a_batch():
    rng = np.random.default_rng(5)
    vertices = torch.as_tensor(np.concatenate([rng.uniform(0, 16, (3, 30, 2)), rng.uniform(1, 3, (3, 30, 1))], -1))
    faces = torch.as_tensor(rng.integers(0, 30, (25, 3)))
    batch = rasterize(vertices, faces, (12, 16), supersample=2, cull_backfaces=False)
    for t in range(3):
        one = rasterize(vertices[t : t + 1], faces, (12, 16), supersample=2, cull_backfaces=False)
        assert torch.equal(batch.face_id[t], one.face_id[0])
        assert torch.equal(batch.bary[t], one.bary[0])


def test_closed_fan_has_no_cracks():
    # a hexagon fan around a centre vertex: every pixel centre inside is covered exactly once
    angles = np.linspace(0, 2 * np.pi, 7)[:-1]
    ring = np.stack([8 + 7 * np.cos(angles), 8 + 7 * np.sin(angles), np.ones(6)], 1)
    vertices = torch.as_tensor(np.vstack([[8.0, 8.0, 1.0], ring]))[None]
    faces = torch.tensor([[0, 1 + (k + 1) % 6, 1 + k] for k in range(6)])
    frags = rasterize(vertices, faces, (16, 16), supersample=3)
    covered = frags.covered[0].numpy()
    yy, xx = (np.mgrid[0:48, 0:48] + 0.5) / 3
    inside_strict = np.hypot(xx - 8, yy - 8) < 7 * np.cos(np.pi / 6) - 1e-6
    assert covered[inside_strict].all()


def test_bad_shapes():
    with pytest.raises(ShapeError):
        rasterize(torch.zeros(4, 3), torch.zeros(1, 3, dtype=torch.long), (4, 4))
    with pytest.raises(ShapeError):
        rasterize(torch.zeros(1, 4, 3), torch.zeros(3, dtype=torch.long), (4, 4))
    with pytest.raises(ValueError):
        rasterize(torch.zeros(1, 4, 3), torch.zeros(1, 3, dtype=torch.long), (4, 4), supersample=0)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (torch.cuda.is_available() is False)")
def test_cuda_matches_cpu():
    rng = np.random.default_rng(7)
    n = 300
    centres = rng.uniform(-2, 66, size=(n, 1, 2))
    corners = centres + rng.normal(scale=5.0, size=(n, 3, 2))
    vertices = torch.as_tensor(np.concatenate([corners, rng.uniform(1.0, 5.0, size=(n, 3, 1))], -1).reshape(1, -1, 3))
    faces = torch.arange(3 * n).reshape(n, 3)
    cpu = rasterize(vertices, faces, (48, 64), supersample=2)
    gpu = rasterize(vertices.cuda(), faces.cuda(), (48, 64), supersample=2)
    assert torch.equal(cpu.face_id, gpu.face_id.cpu())
    np.testing.assert_allclose(cpu.bary.numpy(), gpu.bary.cpu().numpy(), atol=1e-9)
