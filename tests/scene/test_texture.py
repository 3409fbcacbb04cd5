"""Texture lookups: nearest/bilinear taps, grid == upsampled 1024^2 map (values and gradients), masks."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from davis_rig.errors import ShapeError
from davis_rig.scene.texture import prepare_lookup, sample_texture, upsample_grid


def _centre_uv(row, col, size):
    """UV of a texel centre (v up)."""
    return [(col + 0.5) / size, 1.0 - (row + 0.5) / size]


def test_nearest_picks_texels_top_down():
    texture = torch.arange(16, dtype=torch.float64).reshape(4, 4)
    uv = torch.tensor([_centre_uv(0, 0, 4), _centre_uv(3, 1, 4), [0.999, 0.999], [0.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    values = sample_texture(texture, uv, mode="nearest")
    # v = 1 is the top row (row 0); u = 1, v = 0 clamp to the last column / row
    assert values.tolist() == [0.0, 13.0, 3.0, 12.0, 3.0]


def test_bilinear_matches_grid_sample():
    rng = np.random.default_rng(0)
    texture = torch.as_tensor(rng.random((8, 8)))
    uv = torch.as_tensor(rng.uniform(-0.05, 1.05, size=(200, 2)))
    ours = sample_texture(texture, uv, mode="bilinear")
    grid = torch.stack([2 * uv[:, 0] - 1, 1 - 2 * uv[:, 1]], -1)[None, None]  # y down in grid_sample
    ref = F.grid_sample(texture[None, None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    np.testing.assert_allclose(ours.numpy(), ref[0, 0, 0].numpy(), atol=1e-12)
    centre = sample_texture(texture, torch.tensor([_centre_uv(2, 5, 8)], dtype=torch.float64), mode="bilinear")
    assert centre.item() == pytest.approx(texture[2, 5].item())


def test_upsample_grid_equals_interpolate_nearest():
    grid = torch.rand(3, 10, 10)
    for n in (10, 20, 30, 60):
        g = torch.rand(n, n)
        assert torch.equal(upsample_grid(g, 1024), F.interpolate(g[None, None], size=(1024, 1024), mode="nearest")[0, 0])
    assert upsample_grid(grid, 64).shape == (3, 64, 64)


@pytest.mark.parametrize("mode", ["nearest", "bilinear"])
@pytest.mark.parametrize("n", [10, 30, 60])
def test_grid_and_upsampled_map_render_identically(mode, n):
    rng = np.random.default_rng(n)
    uv = torch.as_tensor(rng.random((5000, 2)), dtype=torch.float32)
    mask = rng.random((1024, 1024)) < 0.7
    grid = torch.as_tensor((rng.random((n, n)) > 0.5).astype(np.float32) * 0.8 + 0.1, dtype=torch.float32)
    grid_a = grid.clone().requires_grad_()
    grid_b = grid.clone().requires_grad_()
    direct = prepare_lookup(uv, 1024, mode, grid_n=n, mask=mask)
    assert direct.texture_hw == (n, n)
    values_direct = direct.sample(grid_a)
    full = prepare_lookup(uv, 1024, mode, mask=mask)
    values_full = full.sample(upsample_grid(grid_b, 1024))
    assert torch.equal(values_direct, values_full)  # bit-identical
    weights = torch.as_tensor(rng.random(5000), dtype=torch.float32)
    (values_direct * weights).sum().backward()
    (values_full * weights).sum().backward()
    np.testing.assert_allclose(grid_a.grad.numpy(), grid_b.grad.numpy(), rtol=1e-5, atol=1e-6)


def test_mask_fills_white_and_blocks_gradients():
    texture = torch.zeros(4, 4, requires_grad=True)
    mask = np.zeros((4, 4), dtype=bool)
    mask[:, :2] = True  # left half paintable
    uv = torch.tensor([_centre_uv(1, 0, 4), _centre_uv(1, 3, 4)])
    values = sample_texture(texture, uv, mode="nearest", mask=mask, fill=1.0)
    assert values.tolist() == [0.0, 1.0]
    values.sum().backward()
    expected = torch.zeros(4, 4)
    expected[1, 0] = 1.0
    assert torch.equal(texture.grad, expected)


def test_gradient_is_the_analytic_sparse_map():
    rng = np.random.default_rng(3)
    uv = torch.as_tensor(rng.random((7, 2)), dtype=torch.float64)
    texture = torch.as_tensor(rng.random((6, 6)), dtype=torch.float64)
    jac = torch.autograd.functional.jacobian(lambda t: sample_texture(t, uv, mode="bilinear"), texture)  # [7, 6, 6]
    x = uv[:, 0].numpy() * 6 - 0.5
    y = (1 - uv[:, 1].numpy()) * 6 - 0.5
    expected = np.zeros((7, 6, 6))
    for i in range(7):  # hand-written bilinear weights (clamped borders accumulate)
        x0, y0 = int(np.floor(x[i])), int(np.floor(y[i]))
        fx, fy = x[i] - x0, y[i] - y0
        for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            expected[i, min(max(y0 + dy, 0), 5), min(max(x0 + dx, 0), 5)] += wgt
    np.testing.assert_allclose(jac.numpy(), expected, atol=1e-12)


def test_channels_and_errors():
    texture = torch.rand(3, 8, 8)
    uv = torch.rand(10, 2)
    assert sample_texture(texture, uv).shape == (3, 10)
    lookup = prepare_lookup(uv, 8)
    with pytest.raises(ShapeError):
        lookup.sample(torch.rand(4, 4))
    with pytest.raises(ShapeError):
        prepare_lookup(torch.rand(10, 3), 8)
    with pytest.raises(ValueError):
        prepare_lookup(uv, 8, mode="cubic")
    with pytest.raises(ShapeError):
        prepare_lookup(uv, 8, mask=np.ones((4, 4), bool))


def test_gradient_bit_reproducible_on_two_threads():
    """Many samples on few cells: the grid gradient sums the same taps in the same order on every call (the
    attack's runs repeat bit for bit on several CPU threads)."""
    rng = np.random.default_rng(3)
    lookup = prepare_lookup(torch.as_tensor(rng.random((300_000, 2)), dtype=torch.float32), grid_n=10)
    upstream = torch.as_tensor(rng.standard_normal(300_000), dtype=torch.float32)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        grads = []
        for _ in range(5):
            grid = torch.full((10, 10), 0.5, requires_grad=True)
            (lookup.sample(grid) * upstream).sum().backward()
            grads.append(grid.grad)
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(grads[0], g) for g in grads[1:])
    expected = torch.zeros(100, dtype=torch.float64).index_add_(0, lookup.index[:, 0], upstream.double())
    np.testing.assert_allclose(grads[0].flatten().double().numpy(), expected.numpy(), rtol=1e-4, atol=1e-3)
