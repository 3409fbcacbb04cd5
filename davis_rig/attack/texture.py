"""The paper's black/white texture: generator network, straight-through binarization, upsampling, part mask.

Pipeline (paper, "Texture Map Generation Network"; official ``UV_Generator``)::

    z = 1 (n*n)  ->  fc(n*n -> hidden) -> LayerNorm -> LeakyReLU -> Dropout(0.5) -> fc(hidden -> n*n) -> sigmoid
      -> u in (0, 1)^{n x n}                                 (:class:`TextureGenerator`)
      -> u_b = alpha * [u > t] + (1 - alpha) * u             (:func:`binarize_ste`, backward = identity;
                                                             t = 0.5 as the paper, or t ~ U[0, 1) per cell)
      -> U_hat = nearest upsampling of u_b to 1024 x 1024    (:func:`upsample_grid`)
      -> U_tilde = M * U_hat + (1 - M) * 1                   (:func:`apply_part_mask`, white outside the parts)

Texture values are intensities: 1 = white, 0 = black. Grid cell ``(i, j)`` is row ``i`` (top = high v) and
column ``j`` (left = low u) of the texture image, the image convention of :mod:`davis_rig.scene.masks`.

The differentiable renderer can sample the n x n grid directly (:func:`davis_rig.scene.texture.prepare_lookup`
with ``grid_n=n``); :func:`upsample_grid` is the same integer map (texel ``c`` -> cell ``floor(c * n / size)``),
so both give bit-identical textures. Training-time ``alpha`` follows a schedule (:func:`alpha_at`): the
official code anneals it linearly from 0 (soft) to 1 (hard) over training (:func:`linear_alpha`).

Baseline textures of the paper (white, black, a seeded random pattern) are numpy arrays (no torch needed).
"""

from __future__ import annotations

import math

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.errors import ShapeError

with optional_dependency("the texture generator"):
    import torch
    from torch import nn

__all__ = [
    "ALPHA_SCHEDULES",
    "BINARIZERS",
    "TEXTURE_STARTS",
    "MAX_CELLS",
    "TextureGenerator",
    "alpha_at",
    "apply_part_mask",
    "binarize_ste",
    "black_texture",
    "cell_bounds_texels",
    "constant_alpha",
    "cosine_alpha",
    "hard_binarize",
    "linear_alpha",
    "random_texture",
    "sampled_thresholds",
    "step_alpha",
    "upsample_grid",
    "white_texture",
]

#: Largest grid accepted (the paper uses 10 ... 60 cells per side).
MAX_CELLS = 256
#: Starting textures of :meth:`TextureGenerator.start_from`: ``"random"`` (torch's default initialisation, as the
#: official code: a random-looking grid), a plain texture, or a given black/white ``"grid"``.
TEXTURE_STARTS = ("random", "white", "black", "grid")
#: |logit| of a plain start: u = sigmoid(±3) = 0.953 / 0.047.
PLAIN_START_LOGIT = 3.0


def _check_cells(n_cells: int) -> int:
    if isinstance(n_cells, bool) or int(n_cells) != n_cells or not 1 <= int(n_cells) <= MAX_CELLS:
        raise ValueError(f"n_cells must be an integer in [1, {MAX_CELLS}], got {n_cells!r}")
    return int(n_cells)


# ---------------------------------------------------------------------------------------------- generator
class TextureGenerator(nn.Module):
    """Generation block of the paper: a constant all-ones input through a two-layer MLP to an n x n sigmoid map.

    ``fc1 (n^2 -> hidden) -> LayerNorm(hidden) -> LeakyReLU -> Dropout(p) -> fc2 (hidden -> n^2) -> sigmoid``;
    the input ``z`` is a fixed buffer of ones (the paper's white n x n image), so the only trainable
    parameters are the layers'. Dropout is active in ``train()`` mode (as in the official code) and off in
    ``eval()``; use ``eval()`` to read the final texture. Initialisation follows torch's defaults: call
    ``torch.manual_seed`` first for a reproducible start.

    Args:
        n_cells: grid cells per side n (1 ... :data:`MAX_CELLS`).
        hidden: hidden width (default ``2 * n^2``, as the official code).
        dropout: dropout probability after the activation (paper: 0.5).
        negative_slope: LeakyReLU slope (torch default 0.01, as the official ``F.leaky_relu``).

    Example:
        >>> gen = TextureGenerator(10).eval()
        >>> u = gen()                       # float32 [10, 10] in (0, 1)
        >>> grid = binarize_ste(u, 1.0)     # {0, 1}, gradients pass straight through
    """

    def __init__(self, n_cells: int, hidden: int | None = None, dropout: float = 0.5, negative_slope: float = 0.01):
        super().__init__()
        n = _check_cells(n_cells)
        hidden = 2 * n * n if hidden is None else int(hidden)
        if hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {hidden}")
        if not 0.0 <= float(dropout) < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        self.n_cells = n
        self.hidden = hidden
        self.negative_slope = float(negative_slope)
        self.register_buffer("z", torch.ones(1, n * n), persistent=False)
        self.fc1 = nn.Linear(n * n, hidden)
        self.norm = nn.LayerNorm(hidden)
        self.dropout = nn.Dropout(float(dropout))
        self.fc2 = nn.Linear(hidden, n * n)

    def forward(self) -> "torch.Tensor":
        """The soft grid u.

        Returns:
            float tensor [n, n], values in (0, 1) (1 = white), on the module's device and dtype.
        """
        x = self.fc1(self.z.to(self.fc1.weight.dtype))
        x = nn.functional.leaky_relu(self.norm(x), self.negative_slope)
        x = torch.sigmoid(self.fc2(self.dropout(x)))
        return x.view(self.n_cells, self.n_cells)

    def start_from(self, start: str, grid=None) -> "TextureGenerator":
        """Set the starting texture: ``"random"`` leaves the initialisation as it is; ``"white"`` / ``"black"``
        shrink fc2's weights 1000-fold and set its bias to ``±PLAIN_START_LOGIT``, so every cell starts at
        u = 0.953 / 0.047 (rounded: plain white / black); ``"grid"`` does the same cell by cell, white where
        ``grid`` > 0.5. An Adam step then moves each cell's logit by ``lr * sum |h|`` (fc2's row; ``sum |h|`` is
        about 0.4 per hidden unit), the random start's by about as much again through fc1 and fc2's larger
        weights: the starts take steps of the same order.

        Args:
            start: one of :data:`TEXTURE_STARTS`.
            grid: float [n, n] (1 = white), for ``"grid"`` only.

        Returns:
            self.

        Raises:
            ValueError: unknown start, a grid without ``"grid"`` or the reverse, or a grid not [n, n].
        """
        if start not in TEXTURE_STARTS:
            raise ValueError(f"start must be one of {TEXTURE_STARTS}, got {start!r}")
        if (start == "grid") != (grid is not None):
            raise ValueError("a 'grid' start needs grid=[n, n], and only it takes one")
        if start == "grid":
            grid = np.asarray(grid, dtype=np.float32)
            if grid.shape != (self.n_cells, self.n_cells):
                raise ValueError(f"start grid must be [{self.n_cells}, {self.n_cells}], got {list(grid.shape)}")
        if start != "random":
            with torch.no_grad():
                self.fc2.weight.mul_(1e-3)
                white = np.ones(self.n_cells ** 2, bool) if start == "white" else \
                    np.zeros(self.n_cells ** 2, bool) if start == "black" else grid.reshape(-1) > 0.5
                self.fc2.bias.copy_(torch.from_numpy(np.where(white, PLAIN_START_LOGIT, -PLAIN_START_LOGIT)))
        return self

    def texture(self, alpha: float = 1.0) -> "torch.Tensor":
        """The binarized grid ``binarize_ste(self(), alpha)``, float tensor [n, n]."""
        return binarize_ste(self(), alpha)

    def extra_repr(self) -> str:
        return f"n_cells={self.n_cells}, hidden={self.hidden}"


# ---------------------------------------------------------------------------------------------- STE
class _SoftToHardSTE(torch.autograd.Function):
    """forward ``alpha * [u > t] + (1 - alpha) * u``; backward: the identity for ``u``, nothing for alpha or t."""

    @staticmethod
    def forward(ctx, u, alpha, threshold):
        hard = (u > threshold).to(u.dtype)
        return alpha * hard + (1 - alpha) * u

    @staticmethod
    def backward(ctx, grad_output):
        return grad_output, None, None


#: Hard parts of :func:`binarize_ste`: ``"threshold"`` (the paper: white where u > 0.5) or ``"sample"``
#: (stochastic binarization: each cell white with probability u, a fresh draw every step; :func:`sampled_thresholds`).
BINARIZERS = ("threshold", "sample")


def binarize_ste(u: "torch.Tensor", alpha: "float | torch.Tensor" = 1.0,
                 threshold: "float | torch.Tensor" = 0.5) -> "torch.Tensor":
    """Straight-through soft-to-hard binarization (paper, Eq. for ``u_b``; official ``STEFunction``).

    Forward: ``alpha * [u > threshold] + (1 - alpha) * u`` (``alpha = 1``: exactly 0/1; ``alpha = 0``: ``u``).
    Backward: ``d out / d u = 1`` (identity, whatever ``alpha`` and ``threshold``); no gradient w.r.t. either.

    Args:
        u: float tensor, any shape, values in [0, 1].
        alpha: hardness in [0, 1], a float or a 0-dim tensor.
        threshold: the cut of the hard part: 0.5 (the paper's) or a tensor like ``u`` of per-cell cuts; uniform
            draws in [0, 1) (:func:`sampled_thresholds`) make the hard part a Bernoulli(u) sample.

    Returns:
        float tensor like ``u``.

    Raises:
        ValueError: alpha outside [0, 1], or a threshold tensor not shaped like ``u``;
        TypeError: u is not a floating-point tensor.
    """
    if not isinstance(u, torch.Tensor) or not torch.is_floating_point(u):
        raise TypeError(f"u must be a floating-point torch tensor, got {type(u).__name__}")
    a = float(alpha)
    if not 0.0 <= a <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {a}")
    if isinstance(threshold, torch.Tensor) and threshold.dim() > 0 and threshold.shape != u.shape:
        raise ValueError(f"threshold must be a number or shaped like u {list(u.shape)}, got {list(threshold.shape)}")
    alpha_t = torch.as_tensor(a, dtype=u.dtype, device=u.device)
    threshold_t = torch.as_tensor(threshold, dtype=u.dtype, device=u.device)
    return _SoftToHardSTE.apply(u, alpha_t, threshold_t)


def sampled_thresholds(shape: tuple[int, ...], seed: int, device="cpu") -> "torch.Tensor":
    """Per-cell cuts of stochastic binarization: uniform draws in [0, 1), reproducible from ``seed`` alone.

    With them, :func:`binarize_ste`'s hard part is white with probability ``u`` per cell (``P[u > t] = u``), so
    its straight-through gradient is taken at grids sampled around ``u`` rather than at ``u``'s rounding.

    Args:
        shape: tensor shape, e.g. ``(n, n)``.
        seed: integer seed (the caller derives it from the run's seed and the step).
        device: where the tensor goes (drawn on the CPU, so every device and rank gets the same cuts).

    Returns:
        float32 tensor of ``shape``.
    """
    generator = torch.Generator(device="cpu").manual_seed(int(seed))
    return torch.rand(tuple(shape), generator=generator).to(device)


def hard_binarize(u) -> np.ndarray:
    """Final black/white grid for export and evaluation: ``1.0 where u > 0.5`` else ``0.0``.

    Args:
        u: array-like or tensor [..., n, n] in [0, 1].

    Returns:
        float32 numpy array of 0/1, same shape.
    """
    if isinstance(u, torch.Tensor):
        u = u.detach().cpu().numpy()
    return (np.asarray(u) > 0.5).astype(np.float32)


# ---------------------------------------------------------------------------------------------- schedules
def _progress(step: int, total_steps: int) -> float:
    if int(total_steps) < 1:
        raise ValueError(f"total_steps must be >= 1, got {total_steps}")
    if int(step) < 0:
        raise ValueError(f"step must be >= 0, got {step}")
    if total_steps == 1:
        return 1.0
    return min(1.0, int(step) / (int(total_steps) - 1))


def linear_alpha(step: int, total_steps: int) -> float:
    """Official schedule: ``alpha = step / (total_steps - 1)``, 0 at the first step, 1 at the last (clamped).

    Args:
        step: 0-based step (the official code steps it once per epoch).
        total_steps: number of steps; 1 gives alpha = 1.

    Returns:
        alpha in [0, 1].
    """
    return _progress(step, total_steps)


def cosine_alpha(step: int, total_steps: int) -> float:
    """Smooth ramp ``(1 - cos(pi * p)) / 2`` with ``p = step / (total_steps - 1)``: slow start and end."""
    return 0.5 * (1.0 - math.cos(math.pi * _progress(step, total_steps)))


def step_alpha(step: int, total_steps: int, switch_fraction: float = 0.5) -> float:
    """Soft (0) until ``switch_fraction`` of training, then hard (1)."""
    if not 0.0 <= switch_fraction <= 1.0:
        raise ValueError(f"switch_fraction must be in [0, 1], got {switch_fraction}")
    return 1.0 if _progress(step, total_steps) >= switch_fraction else 0.0


def constant_alpha(step: int, total_steps: int, value: float = 1.0) -> float:
    """The same alpha at every step (``value = 1``: pure STE, hard forward from the start)."""
    _progress(step, total_steps)
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"value must be in [0, 1], got {value}")
    return float(value)


#: Schedules by name, each ``f(step, total_steps) -> alpha``.
ALPHA_SCHEDULES = {
    "linear": linear_alpha,
    "cosine": cosine_alpha,
    "step": step_alpha,
    "hard": lambda step, total_steps: constant_alpha(step, total_steps, 1.0),
    "soft": lambda step, total_steps: constant_alpha(step, total_steps, 0.0),
}


def alpha_at(schedule: str, step: int, total_steps: int) -> float:
    """Alpha of a named schedule (:data:`ALPHA_SCHEDULES`: linear = official, cosine, step, hard, soft).

    Raises:
        ValueError: unknown schedule name, step < 0 or total_steps < 1.
    """
    if schedule not in ALPHA_SCHEDULES:
        raise ValueError(f"unknown alpha schedule {schedule!r}; expected one of {sorted(ALPHA_SCHEDULES)}")
    return float(ALPHA_SCHEDULES[schedule](step, total_steps))


# ---------------------------------------------------------------------------------------------- upsampling, mask
def cell_bounds_texels(n_cells: int, size: int = 1024) -> np.ndarray:
    """Texel boundaries of the grid cells after nearest upsampling to ``size``.

    Cell ``k`` covers texels ``[bounds[k], bounds[k + 1])`` with ``bounds[k] = ceil(k * size / n)`` (the
    inverse of texel ``c`` -> cell ``floor(c * n / size)``). When ``n`` divides ``size`` every cell is
    ``size / n`` texels; otherwise cells are ``floor(size / n)`` or ``ceil(size / n)`` texels (e.g. 60 cells
    on 1024 texels: 17 or 18), which is what ``F.interpolate(mode="nearest", size=size)`` produces too.

    Returns:
        int64 [n + 1], from 0 to ``size``.
    """
    n = _check_cells(n_cells)
    k = np.arange(n + 1, dtype=np.int64)
    return -((-k * int(size)) // n)  # ceil division


def upsample_grid(grid: "torch.Tensor", size: int = 1024) -> "torch.Tensor":
    """Nearest upsampling of an n x n grid to the ``size x size`` texture map (differentiable).

    Texel ``(r, c)`` takes cell ``(floor(r n / size), floor(c n / size))`` (see :func:`cell_bounds_texels`),
    identical to :func:`davis_rig.scene.texture.upsample_grid` and to sampling the grid with
    ``prepare_lookup(grid_n=n)``; equal to ``F.interpolate(mode="nearest")``.

    Args:
        grid: float tensor [..., n, n].
        size: output texels per side (>= n; paper: 1024).

    Returns:
        tensor [..., size, size]; the gradient of a texel flows to its cell.

    Raises:
        ShapeError: grid not square; ValueError: size < n.
    """
    from davis_rig.scene.texture import upsample_grid as _scene_upsample

    if grid.ndim < 2 or grid.shape[-1] != grid.shape[-2]:
        raise ShapeError(f"grid must be square [..., n, n], got {tuple(grid.shape)}")
    if int(size) < grid.shape[-1]:
        raise ValueError(f"size must be >= n = {grid.shape[-1]}, got {size}")
    return _scene_upsample(grid, int(size))


def apply_part_mask(texture, mask):
    """The paper's mask filter ``U_tilde = M * U + (1 - M) * 1``: white outside the chosen parts.

    Args:
        texture: float tensor or numpy array [..., H, W] (1 = white).
        mask: bool or float [H, W] (1 = paintable), e.g. :func:`davis_rig.scene.masks.part_mask`; a tensor or
            numpy array (converted to the texture's type, device and dtype).

    Returns:
        same type as ``texture``, [..., H, W]; differentiable w.r.t. ``texture`` (gradient ``M``). Inputs are
        not modified.

    Raises:
        ShapeError: mask is not [H, W] of the texture.
    """
    hw = tuple(texture.shape[-2:])
    if tuple(mask.shape) != hw:
        raise ShapeError(f"mask must be {list(hw)} like the texture {list(texture.shape)}, got {list(mask.shape)}")
    if isinstance(texture, torch.Tensor):
        m = torch.as_tensor(mask, device=texture.device)
        m = m.to(texture.dtype)
        return m * texture + (1 - m)
    texture = np.asarray(texture)
    m = np.asarray(mask, dtype=texture.dtype if np.issubdtype(texture.dtype, np.floating) else np.float32)
    return m * texture + (1 - m)


# ---------------------------------------------------------------------------------------------- baselines
def white_texture(n_cells: int = 1) -> np.ndarray:
    """All-white baseline grid, float32 [n, n] of ones."""
    n = _check_cells(n_cells)
    return np.ones((n, n), dtype=np.float32)


def black_texture(n_cells: int = 1) -> np.ndarray:
    """All-black baseline grid, float32 [n, n] of zeros (black inside the mask, white elsewhere after masking)."""
    n = _check_cells(n_cells)
    return np.zeros((n, n), dtype=np.float32)


def random_texture(n_cells: int = 60, seed: int = 0, p_white: float = 0.5) -> np.ndarray:
    """Seeded random black/white baseline grid (paper: a random 60 x 60 pattern).

    Args:
        n_cells: cells per side.
        seed: seed of ``numpy.random.default_rng`` (same seed -> same pattern on every platform).
        p_white: probability of a white cell.

    Returns:
        float32 [n, n] of 0/1.
    """
    n = _check_cells(n_cells)
    if not 0.0 <= p_white <= 1.0:
        raise ValueError(f"p_white must be in [0, 1], got {p_white}")
    rng = np.random.default_rng(seed)
    return (rng.random((n, n)) < p_white).astype(np.float32)
