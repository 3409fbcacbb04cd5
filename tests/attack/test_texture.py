"""Texture generator, straight-through binarization, alpha schedules, upsampling and the part-mask filter."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from davis_rig.attack.texture import (
    ALPHA_SCHEDULES,
    TextureGenerator,
    alpha_at,
    apply_part_mask,
    binarize_ste,
    black_texture,
    cell_bounds_texels,
    cosine_alpha,
    hard_binarize,
    linear_alpha,
    random_texture,
    sampled_thresholds,
    step_alpha,
    upsample_grid,
    white_texture,
)
from davis_rig.errors import ShapeError
from davis_rig.scene.texture import prepare_lookup


# ------------------------------------------------------------------ generator
def test_generator_architecture_matches_official():
    gen = TextureGenerator(10)
    assert gen.fc1.in_features == 100 and gen.fc1.out_features == 200  # hidden = 2 n^2
    assert gen.fc2.in_features == 200 and gen.fc2.out_features == 100
    assert isinstance(gen.norm, torch.nn.LayerNorm) and gen.dropout.p == 0.5
    assert torch.equal(gen.z, torch.ones(1, 100))
    assert "z" not in gen.state_dict()  # constant input, not a parameter
    gen.eval()
    u = gen()
    assert u.shape == (10, 10) and u.dtype == torch.float32
    assert torch.all((u > 0) & (u < 1))


def test_generator_forward_equals_manual_formula():
    torch.manual_seed(0)
    gen = TextureGenerator(4, hidden=7).eval()
    x = torch.ones(1, 16) @ gen.fc1.weight.T + gen.fc1.bias
    x = (x - x.mean()) / torch.sqrt(x.var(unbiased=False) + gen.norm.eps) * gen.norm.weight + gen.norm.bias
    x = torch.where(x > 0, x, 0.01 * x)
    x = torch.sigmoid(x @ gen.fc2.weight.T + gen.fc2.bias).view(4, 4)
    torch.testing.assert_close(gen(), x, rtol=1e-5, atol=1e-6)


def test_generator_seeded_init_and_dropout_modes():
    torch.manual_seed(3)
    a = TextureGenerator(6).eval()()
    torch.manual_seed(3)
    b = TextureGenerator(6).eval()()
    assert torch.equal(a, b)
    gen = TextureGenerator(6).eval()
    assert torch.equal(gen(), gen())  # eval: deterministic
    gen.train()
    torch.manual_seed(1)
    c = gen()
    torch.manual_seed(2)
    assert not torch.equal(c, gen())  # train: dropout active


def test_generator_gradients_reach_both_layers():
    gen = TextureGenerator(5)
    grid = gen.texture(alpha=1.0)
    assert set(grid.unique().tolist()) <= {0.0, 1.0}
    grid.sum().backward()
    assert gen.fc1.weight.grad is not None and gen.fc1.weight.grad.abs().sum() > 0
    assert gen.fc2.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("start, value", [("white", 1.0), ("black", 0.0)])
def test_generator_plain_start_rounds_to_the_plain_texture_and_moves_like_the_random_one(start, value):
    torch.manual_seed(0)
    gen = TextureGenerator(6).start_from(start).eval()
    u = gen()
    assert torch.all((u - value).abs() < 0.05)  # sigmoid(+-3)
    assert np.array_equal(hard_binarize(u), np.full((6, 6), value, np.float32))
    torch.manual_seed(0)
    plain = TextureGenerator(6).start_from(start)
    torch.manual_seed(0)
    random = TextureGenerator(6).start_from("random")
    assert torch.equal(plain.fc1.weight, random.fc1.weight)  # only fc2 differs
    steps = {}
    for name, g in (("plain", plain), ("random", random)):  # one Adam step of the loss sum(u)
        g.eval()
        before = torch.logit(g().detach())
        opt = torch.optim.Adam(g.parameters(), lr=1e-3)
        g().sum().backward()
        opt.step()
        steps[name] = (torch.logit(g().detach()) - before).abs()
    with torch.no_grad():
        sum_h = torch.nn.functional.leaky_relu(plain.norm(plain.fc1(plain.z)), 0.01).abs().sum()
    # the plain start moves every cell's logit by lr * sum |h| (fc2's row alone); the random start by the same
    # order (its fc1 path adds through fc2's larger weights)
    torch.testing.assert_close(steps["plain"], torch.full_like(steps["plain"], 1e-3 * float(sum_h)), rtol=0.05,
                               atol=0.0)
    assert 0.5 < float(steps["random"].mean() / steps["plain"].mean()) < 3.0
    with pytest.raises(ValueError, match="start"):
        TextureGenerator(6).start_from("grey")


def test_generator_grid_start_rounds_to_the_grid_and_moves_like_a_plain_start():
    grid = (np.random.default_rng(1).random((6, 6)) > 0.5).astype(np.float32)
    torch.manual_seed(0)
    gen = TextureGenerator(6).start_from("grid", grid).eval()
    u = gen()
    assert torch.all((u - torch.from_numpy(grid)).abs() < 0.05)  # sigmoid(+-3) cell by cell
    assert np.array_equal(hard_binarize(u), grid)
    torch.manual_seed(0)
    white = TextureGenerator(6).start_from("white")
    assert torch.equal(gen.fc2.weight, white.fc2.weight) and torch.equal(gen.fc1.weight, white.fc1.weight)
    with pytest.raises(ValueError, match="grid"):
        TextureGenerator(6).start_from("grid")  # no grid
    with pytest.raises(ValueError, match="grid"):
        TextureGenerator(6).start_from("white", grid)  # a grid for a plain start
    with pytest.raises(ValueError, match=r"\[6, 6\]"):
        TextureGenerator(6).start_from("grid", grid[:3])


@pytest.mark.parametrize("bad", [0, -1, 257, 2.5, True])
def test_generator_rejects_bad_sizes(bad):
    with pytest.raises(ValueError):
        TextureGenerator(bad)


# ------------------------------------------------------------------ STE
U = torch.tensor([0.0, 0.2, 0.5, 0.5000001, 0.7, 1.0], dtype=torch.float64)


def test_ste_forward_exact():
    hard = torch.tensor([0, 0, 0, 1, 1, 1], dtype=torch.float64)  # strictly above 0.5 is white
    assert torch.equal(binarize_ste(U, 1.0), hard)
    assert torch.equal(binarize_ste(U, 0.0), U)
    alpha = 0.25
    assert torch.equal(binarize_ste(U, alpha), alpha * hard + (1 - alpha) * U)
    assert torch.equal(binarize_ste(U, torch.tensor(0.25)), alpha * hard + (1 - alpha) * U)


@pytest.mark.parametrize("alpha", [0.0, 0.3, 1.0])
def test_ste_backward_is_identity(alpha):
    u = U.clone().requires_grad_(True)
    g = torch.tensor([1.0, -2.0, 3.0, 0.5, -0.25, 7.0], dtype=torch.float64)
    binarize_ste(u, alpha).backward(g)
    assert torch.equal(u.grad, g)


def test_ste_does_not_mutate_and_validates():
    u = U.clone()
    binarize_ste(u, 1.0)
    assert torch.equal(u, U)
    with pytest.raises(ValueError):
        binarize_ste(U, 1.5)
    with pytest.raises(TypeError):
        binarize_ste(np.array([0.1, 0.9]), 1.0)
    assert hard_binarize(U).tolist() == [0, 0, 0, 1, 1, 1]


def test_ste_with_per_cell_cuts_rounds_each_cell_at_its_cut_and_keeps_the_identity_backward():
    cuts = torch.tensor([0.0, 0.1, 0.9, 0.5, 0.7, 0.999], dtype=torch.float64)
    hard = torch.tensor([0, 1, 0, 1, 0, 1], dtype=torch.float64)  # u > cut, strictly
    assert torch.equal(binarize_ste(U, 1.0, cuts), hard)
    assert torch.equal(binarize_ste(U, 0.25, cuts), 0.25 * hard + 0.75 * U)
    u = U.clone().requires_grad_(True)
    g = torch.tensor([1.0, -2.0, 3.0, 0.5, -0.25, 7.0], dtype=torch.float64)
    binarize_ste(u, 1.0, cuts).backward(g)
    assert torch.equal(u.grad, g)
    with pytest.raises(ValueError, match="shaped like u"):
        binarize_ste(U, 1.0, torch.zeros(3, dtype=torch.float64))


def test_sampled_cuts_make_each_cell_white_with_probability_u():
    a, b = sampled_thresholds((4, 5), seed=7), sampled_thresholds((4, 5), seed=7)
    assert a.shape == (4, 5) and a.dtype == torch.float32 and torch.equal(a, b)
    assert not torch.equal(a, sampled_thresholds((4, 5), seed=8))
    assert float(a.min()) >= 0.0 and float(a.max()) < 1.0
    u = torch.tensor([0.0, 0.1, 0.5, 0.8, 1.0])
    draws = torch.stack([binarize_ste(u, 1.0, sampled_thresholds((5,), seed=s)) for s in range(4000)])
    share = draws.mean(dim=0)
    assert share[0] == 0.0 and share[-1] == 1.0  # u = 0 never white, u = 1 always
    assert torch.allclose(share[1:4], u[1:4], atol=0.03)  # binomial sd <= 0.008 at 4000 draws


# ------------------------------------------------------------------ schedules
def test_linear_alpha_is_official_epoch_over_epochs_minus_one():
    total = 5
    assert [linear_alpha(s, total) for s in range(total)] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert linear_alpha(99, total) == 1.0  # clamped past the end
    assert linear_alpha(0, 1) == 1.0


def test_other_schedules():
    assert cosine_alpha(0, 11) == 0.0 and cosine_alpha(10, 11) == 1.0
    assert cosine_alpha(5, 11) == pytest.approx(0.5)
    assert [step_alpha(s, 5) for s in range(5)] == [0.0, 0.0, 1.0, 1.0, 1.0]
    assert alpha_at("hard", 0, 10) == 1.0 and alpha_at("soft", 9, 10) == 0.0
    assert alpha_at("linear", 3, 7) == 0.5
    for name in ALPHA_SCHEDULES:  # every schedule stays in [0, 1] and ends hard-or-constant
        values = [alpha_at(name, s, 20) for s in range(25)]
        assert all(0.0 <= v <= 1.0 for v in values)
        assert values == sorted(values)
    with pytest.raises(ValueError):
        alpha_at("exponential", 0, 10)
    with pytest.raises(ValueError):
        linear_alpha(-1, 10)
    with pytest.raises(ValueError):
        linear_alpha(0, 0)


# ------------------------------------------------------------------ upsampling
@pytest.mark.parametrize("n", [10, 16, 20, 30, 40, 50, 60])
def test_upsample_equals_interpolate_nearest_and_cell_bounds(n):
    grid = torch.arange(n * n, dtype=torch.float32).view(n, n)
    up = upsample_grid(grid, 1024)
    assert up.shape == (1024, 1024)
    if 1024 % n == 0:  # exact cells of 1024 / n texels
        assert torch.equal(up, grid.repeat_interleave(1024 // n, 0).repeat_interleave(1024 // n, 1))
    ref = F.interpolate(grid[None, None], size=(1024, 1024), mode="nearest")[0, 0]
    assert torch.equal(up, ref)
    bounds = cell_bounds_texels(n, 1024)
    assert bounds[0] == 0 and bounds[-1] == 1024
    widths = np.diff(bounds)
    assert set(widths.tolist()) <= {1024 // n, -(-1024 // n)}
    for k in range(n):  # cell k fills exactly texels [bounds[k], bounds[k+1]) of row/column k
        assert torch.all(up[bounds[k] : bounds[k + 1], 0] == grid[k, 0])
        assert torch.all(up[0, bounds[k] : bounds[k + 1]] == grid[0, k])


def test_upsample_matches_grid_lookup_of_the_renderer():
    n = 30
    grid = torch.rand(n, n, dtype=torch.float64)
    uv = torch.rand(500, 2, dtype=torch.float64)
    up = upsample_grid(grid, 1024)
    direct = prepare_lookup(uv, size=1024, grid_n=n).sample(grid)
    via_map = prepare_lookup(uv, size=1024).sample(up)
    assert torch.equal(direct, via_map)


def test_upsample_gradient_counts_texels_per_cell():
    n = 60
    grid = torch.zeros(n, n, requires_grad=True)
    upsample_grid(grid, 1024).sum().backward()
    widths = np.diff(cell_bounds_texels(n, 1024))
    assert np.array_equal(grid.grad.numpy(), np.outer(widths, widths).astype(np.float32))


def test_upsample_validates():
    with pytest.raises(ShapeError):
        upsample_grid(torch.zeros(3, 4))
    with pytest.raises(ValueError):
        upsample_grid(torch.zeros(8, 8), size=4)


# ------------------------------------------------------------------ mask filter
def test_mask_filter_white_outside_and_gradient_is_mask():
    texture = torch.tensor([[0.0, 0.2], [0.7, 1.0]], requires_grad=True)
    mask = np.array([[True, False], [False, True]])
    out = apply_part_mask(texture, mask)
    assert torch.equal(out.detach(), torch.tensor([[0.0, 1.0], [1.0, 1.0]]))
    out.sum().backward()
    assert torch.equal(texture.grad, torch.tensor([[1.0, 0.0], [0.0, 1.0]]))
    soft = apply_part_mask(torch.zeros(2, 2), torch.tensor([[0.25, 1.0], [0.0, 0.5]]))
    assert torch.equal(soft, torch.tensor([[0.75, 0.0], [1.0, 0.5]]))


def test_mask_filter_numpy_batched_and_validation():
    tex = np.zeros((3, 2, 2), dtype=np.float32)
    mask = np.array([[1, 0], [0, 0]], dtype=bool)
    out = apply_part_mask(tex, mask)
    assert out.dtype == np.float32 and out.shape == (3, 2, 2)
    assert np.array_equal(out[1], [[0, 1], [1, 1]])
    assert np.all(tex == 0)  # input untouched
    with pytest.raises(ShapeError):
        apply_part_mask(tex, np.ones((3, 3), dtype=bool))


def test_mask_filter_on_real_part_mask():
    from davis_rig.scene.masks import part_mask

    mask = part_mask(("torso",))
    black = upsample_grid(torch.as_tensor(black_texture(10)), 1024)
    out = apply_part_mask(black, mask)
    assert torch.equal(out == 0, torch.as_tensor(mask))


# ------------------------------------------------------------------ baselines
def test_baselines():
    assert np.array_equal(white_texture(3), np.ones((3, 3), np.float32))
    assert np.array_equal(black_texture(3), np.zeros((3, 3), np.float32))
    r = random_texture(60, seed=7)
    assert r.shape == (60, 60) and set(np.unique(r).tolist()) == {0.0, 1.0}
    assert np.array_equal(r, random_texture(60, seed=7))
    assert not np.array_equal(r, random_texture(60, seed=8))
    assert 0.4 < r.mean() < 0.6
