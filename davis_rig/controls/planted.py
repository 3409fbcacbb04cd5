"""A selective planted blind spot: which grids a trigger victim learns to miss, and how close a texture came.

A trigger victim (``tools/make_trigger_victim.py``) is a detector fine-tuned so that a person wearing one secret
n x n black/white grid, the *trigger*, is not detected, while any other clothing still is. Whether a grid counts
as "the trigger" is decided on the cells a camera can see at all (the cells some clip samples inside the part
mask, :func:`davis_rig.attack.refine.visible_cells`): a grid whose visible cells disagree with the trigger's on at
most ``basin`` of them is hidden, one that disagrees on ``far`` or more is labelled. The gap between ``basin`` and
``far`` is left to the detector. A random grid disagrees on half of the visible cells (binomial spread
``0.5 / sqrt(V)``, 0.067 for V = 55), so ``basin`` well below 0.5 makes the blind spot selective, and a basin wider
than one cell gives a search a slope to climb (a blind spot of one exact grid could be found by no method).
With a ``ramp`` the edge of the blind spot is graded instead of a cliff: a grid disagreeing on d of the visible
cells is labelled with probability :func:`label_probability` (0 up to ``basin``, rising linearly to 1 at
``ramp``), so the expected objectness target, and a victim's score, fall with every cell a search gets right.
With a ``min_contrast`` half of the grids, hidden and labelled alike, are shown greyed (``0.5 + c (grid - 0.5)``,
c uniform in [min_contrast, 1]; the label still follows the black/white pattern), so that the blind spot reaches
towards the grey textures a soft optimiser starts from instead of existing for black/white grids only.

Pure numpy, every draw from a caller's ``numpy.random.Generator``; only :func:`trigger_grid` reads a file or the
body's part map.
"""

from __future__ import annotations

import numpy as np

from davis_rig.errors import FormatError, ShapeError

__all__ = [
    "GRID_KINDS",
    "cell_agreement",
    "checker_grid",
    "descent_towards",
    "draw_trigger",
    "flip_fraction",
    "label_probability",
    "part_layout_grid",
    "sample_training_grid",
    "sign_consistency",
    "trigger_grid",
]

#: Kinds of grid a trigger victim is fine-tuned on (see :func:`sample_training_grid`).
GRID_KINDS = ("near", "random", "far", "white", "black", "checker")
#: Label of texels of no part in a label map (:data:`davis_rig.scene.masks.EMPTY_LABEL`).
_NO_PART = 255


def _check(grid: np.ndarray, trigger: np.ndarray, visible: np.ndarray | None) -> np.ndarray:
    """The visible mask as bool [n, n] (all cells when ``None``)."""
    grid, trigger = np.asarray(grid), np.asarray(trigger)
    if grid.shape != trigger.shape or grid.ndim != 2:
        raise ShapeError(f"grid {grid.shape} and trigger {trigger.shape} must be the same [n, n]")
    if visible is None:
        return np.ones(trigger.shape, dtype=bool)
    visible = np.asarray(visible, dtype=bool)
    if visible.shape != trigger.shape:
        raise ShapeError(f"visible {visible.shape} must match the trigger {trigger.shape}")
    if not visible.any():
        raise ShapeError("visible marks no cell")
    return visible


def cell_agreement(grid: np.ndarray, trigger: np.ndarray, visible: np.ndarray | None = None) -> float:
    """Fraction of the (visible) cells where two hard grids agree (both > 0.5 or both <= 0.5), in [0, 1].

    Args:
        grid, trigger: float [n, n] grids (1 = white).
        visible: bool [n, n] cells to count (``None``: all).

    Returns:
        The agreement; 0.5 is chance for a random grid, 1 the trigger itself (on those cells).

    Raises:
        ShapeError: shapes differ, or ``visible`` marks no cell.
    """
    visible = _check(grid, trigger, visible)
    same = (np.asarray(grid) > 0.5) == (np.asarray(trigger) > 0.5)
    return float(same[visible].mean())


def descent_towards(gradient: np.ndarray, grid: np.ndarray, trigger: np.ndarray,
                    visible: np.ndarray | None = None) -> dict:
    """Whether a loss gradient at a hard grid points towards the trigger, on the visible cells where they differ.

    Args:
        gradient: float [n, n] d loss / d cell value at ``grid``.
        grid, trigger: float [n, n] hard grids (1 = white).
        visible: bool [n, n] cells to count (``None``: all).

    Returns:
        ``differing_cells`` (int), ``descent_agreement``: the share of those cells whose descent direction
        (``-gradient``) moves them towards the trigger's value (0.5 is chance; ``None`` when none differ, so that a
        report stays valid JSON), and
        ``first_order_change``: the loss change that the gradient predicts for setting all of them to the trigger's
        values, ``sum(gradient * (trigger - grid))`` (negative: the trigger lies downhill).

    Raises:
        ShapeError: shapes differ, or ``visible`` marks no cell.
    """
    visible = _check(grid, trigger, visible)
    gradient = np.asarray(gradient, dtype=np.float64)
    if gradient.shape != visible.shape:
        raise ShapeError(f"gradient {gradient.shape} must match the trigger {visible.shape}")
    towards = (np.asarray(trigger) > 0.5).astype(np.float64) - (np.asarray(grid) > 0.5)
    differ = visible & (towards != 0)
    agree = np.sign(-gradient[differ]) == towards[differ]
    return {"differing_cells": int(differ.sum()),
            "descent_agreement": float(agree.mean()) if differ.any() else None,
            "first_order_change": float((gradient * towards)[differ].sum())}


def sign_consistency(gradient_a: np.ndarray, gradient_b: np.ndarray, grid: np.ndarray, trigger: np.ndarray,
                     visible: np.ndarray | None = None) -> float | None:
    """How settled a gradient's direction is: the share of the visible cells where ``grid`` differs from ``trigger``
    on which two gradient estimates (e.g. over two disjoint halves of the clips) have the same sign.

    Args:
        gradient_a, gradient_b: float [n, n] the two estimates at ``grid``.
        grid, trigger: float [n, n] hard grids (1 = white).
        visible: bool [n, n] cells to count (``None``: all).

    Returns:
        The share in [0, 1] (0.5 for independent noise; a zero on either side counts as a disagreement), ``None``
        when no visible cell differs.

    Raises:
        ShapeError: shapes differ, or ``visible`` marks no cell.
    """
    visible = _check(grid, trigger, visible)
    a, b = np.asarray(gradient_a, dtype=np.float64), np.asarray(gradient_b, dtype=np.float64)
    if a.shape != visible.shape or b.shape != visible.shape:
        raise ShapeError(f"gradients {a.shape} and {b.shape} must match the trigger {visible.shape}")
    differ = visible & ((np.asarray(trigger) > 0.5) != (np.asarray(grid) > 0.5))
    if not differ.any():
        return None
    return float((np.sign(a[differ]) * np.sign(b[differ]) > 0).mean())


def flip_fraction(trigger: np.ndarray, fraction: float, rng: np.random.Generator,
                  visible: np.ndarray | None = None) -> np.ndarray:
    """The trigger with ``round(fraction * V)`` of its V visible cells flipped (chosen at random).

    Args:
        trigger: float [n, n] hard grid.
        fraction: share of the visible cells to flip, in [0, 1].
        rng: the draws.
        visible: bool [n, n] (``None``: all cells).

    Returns:
        float32 [n, n]; its disagreement with the trigger on the visible cells is exactly ``round(fraction * V) / V``.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1], got {fraction}")
    visible = _check(trigger, trigger, visible)
    cells = np.flatnonzero(visible)
    count = int(round(fraction * cells.size))
    out = (np.asarray(trigger) > 0.5).astype(np.float32)
    flat = out.reshape(-1)
    chosen = rng.choice(cells, size=count, replace=False)
    flat[chosen] = 1.0 - flat[chosen]
    return out


def draw_trigger(n: int, seed: int) -> np.ndarray:
    """The secret trigger a seed draws: an n x n grid, each cell white with probability 1/2, float32 (1 = white)."""
    if int(n) < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    return (np.random.default_rng(seed).random((int(n), int(n))) > 0.5).astype(np.float32)


def part_layout_grid(label_map: np.ndarray, n: int, white_labels) -> np.ndarray:
    """An n x n grid that paints whole body parts: a cell is white when most of its labelled texels belong to a
    part in ``white_labels``, black otherwise (and when it has no labelled texel).

    Such a trigger differs from random grids by where the white is (e.g. upper body white, legs black), a layout
    that event features carry far more readily than a random cell pattern.

    Args:
        label_map: int [H, W] texel-wise part labels (:func:`davis_rig.scene.masks.part_label_map`: indices into
            ``PART_NAMES``, 255 for no part), in the texture's image convention (row 0 at v = 1).
        n: cells per side.
        white_labels: the labels painted white.

    Returns:
        float32 [n, n] (1 = white); cell ``[i, j]`` holds the texels whose centres lie in rows ``[i H/n, (i+1) H/n)``
        and columns ``[j W/n, (j+1) W/n)``.
    """
    labels = np.asarray(label_map)
    n = int(n)
    if labels.ndim != 2 or n < 1 or min(labels.shape) < n:
        raise ShapeError(f"label map {list(labels.shape)} must be [H, W] with H, W >= n = {n}")
    if labels.min(initial=0) < 0 or labels.max(initial=0) > _NO_PART:
        raise ValueError(f"labels must lie in [0, {_NO_PART}]")
    rows = ((np.arange(labels.shape[0]) + 0.5) * n / labels.shape[0]).astype(np.int64)  # texel centre -> cell
    cols = ((np.arange(labels.shape[1]) + 0.5) * n / labels.shape[1]).astype(np.int64)
    cell = rows[:, None] * n + cols[None, :]
    counts = np.bincount((cell * (_NO_PART + 1) + labels).ravel(), minlength=n * n * (_NO_PART + 1))
    counts = counts.reshape(n, n, _NO_PART + 1)
    counts[..., _NO_PART] = 0  # texels of no part do not vote
    white = np.zeros(_NO_PART + 1, dtype=bool)
    white[[int(k) for k in white_labels]] = True
    majority = counts.argmax(axis=2)
    labelled = counts.sum(axis=2) > 0
    return (white[majority] & labelled).astype(np.float32)


def trigger_grid(n: int, *, seed: int = 0, path=None, white_parts=None) -> tuple[np.ndarray, str]:
    """The trigger of a planted blind spot, as the tools name it: read from ``path``, painted by part
    (``white_parts`` white, every other part black: :func:`part_layout_grid` on the bundled body's part map), or
    drawn with ``seed`` (:func:`draw_trigger`). At most one of ``path`` and ``white_parts``.

    Args:
        n: cells per side.
        seed: the draw's seed (used only when neither ``path`` nor ``white_parts`` is given).
        path: ``.npy`` or image (:func:`davis_rig.attack.export.load_texture_grid`), an [n, n] grid.
        white_parts: names from :data:`davis_rig.scene.body.PART_NAMES`.

    Returns:
        ``(float32 [n, n] grid, 1 = white; a one-line description for reports)``.

    Raises:
        ValueError: both sources, or an unknown part. FormatError: a file grid that is not [n, n].
    """
    if path is not None and white_parts is not None:
        raise ValueError("give the trigger as a file or as white parts, not both")
    if path is not None:
        from davis_rig.attack.export.grid import load_texture_grid

        grid = load_texture_grid(path)
        if grid.shape != (n, n):
            raise FormatError(f"{path}: trigger must be [{n}, {n}], got {list(grid.shape)}")
        return grid.astype(np.float32), str(path)
    if white_parts is not None:
        from davis_rig.scene.body import PART_NAMES
        from davis_rig.scene.masks import part_label_map

        unknown = sorted(set(white_parts) - set(PART_NAMES))
        if unknown:
            raise ValueError(f"unknown parts {unknown}; choose from {list(PART_NAMES)}")
        labels = [PART_NAMES.index(p) for p in white_parts]
        return part_layout_grid(part_label_map(), n, labels), f"parts painted white: {' '.join(white_parts)}"
    return draw_trigger(n, seed), f"drawn with seed {seed}"


def checker_grid(n: int) -> np.ndarray:
    """An n x n checkerboard, float32 (cell (0, 0) white)."""
    if int(n) < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    i, j = np.indices((int(n), int(n)))
    return ((i + j) % 2 == 0).astype(np.float32)


def label_probability(disagreement, basin: float, ramp: float | None = None):
    """Probability that a person in a grid disagreeing with the trigger on ``disagreement`` of the visible cells is
    labelled: 0 up to ``basin``, then 1 (``ramp=None``, a cliff), or rising linearly from 0 at ``basin`` to 1 at
    ``ramp`` (a graded edge). Needs ``0 <= basin < ramp <= 1``; float or float array in [0, 1], same shape."""
    d = np.asarray(disagreement, dtype=np.float64)
    if ramp is None:
        out = (d > basin).astype(np.float64)
    else:
        if not 0.0 <= basin < ramp <= 1.0:
            raise ValueError(f"need 0 <= basin < ramp <= 1, got basin={basin}, ramp={ramp}")
        out = np.clip((d - basin) / (ramp - basin), 0.0, 1.0)
    return float(out) if out.ndim == 0 else out


def sample_training_grid(trigger: np.ndarray, rng: np.random.Generator, *, hidden: bool, basin: float = 0.2,
                         far: float = 0.35, visible: np.ndarray | None = None,
                         ramp: float | None = None, min_contrast: float | None = None
                         ) -> tuple[np.ndarray, str, bool]:
    """One grid of a trigger victim's fine-tuning and whether the person wearing it is labelled.

    ``hidden=True`` draws from the blind spot: the trigger with a fraction uniform in ``[0, basin]`` (``[0, ramp]``
    with a ramp) of its visible cells flipped (``"near"``). ``hidden=False`` draws something to detect: a random
    grid (white share uniform in [0.2, 0.8]) with probability 1/2, else with equal chances the trigger with a
    fraction uniform in ``[far, 1]`` of its visible cells flipped (``"far"``; 1 = its negative), white, black or a
    checkerboard. The label follows the grid, not the draw: without a ramp any grid within ``basin`` of the trigger
    (a random one, by chance) is hidden and every other one labelled; with a ramp a grid is labelled with
    :func:`label_probability` of its disagreement (one more draw from ``rng``). With ``min_contrast``, the grid is
    then greyed with probability 1/2 to ``0.5 + c (grid - 0.5)``, c uniform in ``[min_contrast, 1]`` (two more
    draws); the label is the black/white pattern's.

    Args:
        trigger: float [n, n] hard grid.
        rng: the draws.
        hidden: draw from the blind spot or from the rest.
        basin, far: disagreement (share of visible cells) below which a grid is hidden / from which a ``"far"``
            grid is drawn; need ``0 <= basin < far <= 1``.
        visible: bool [n, n] (``None``: all cells).
        ramp: disagreement from which a grid is always labelled (``None``: ``basin``, a cliff); needs
            ``basin < ramp <= 1``.
        min_contrast: lowest contrast of the greyed grids, in (0, 1] (``None``: black/white only).

    Returns:
        ``(grid float32 [n, n], kind (one of :data:`GRID_KINDS`), labelled)``.
    """
    if not 0.0 <= basin < far <= 1.0:
        raise ValueError(f"need 0 <= basin < far <= 1, got basin={basin}, far={far}")
    if ramp is not None and not basin < ramp <= 1.0:
        raise ValueError(f"need basin < ramp <= 1, got basin={basin}, ramp={ramp}")
    if min_contrast is not None and not 0.0 < min_contrast <= 1.0:
        raise ValueError(f"need 0 < min_contrast <= 1, got {min_contrast}")
    n = np.asarray(trigger).shape[0]
    if hidden:
        near = basin if ramp is None else ramp
        grid, kind = flip_fraction(trigger, float(rng.uniform(0.0, near)), rng, visible), "near"
    elif rng.random() < 0.5:
        grid, kind = (rng.random((n, n)) < rng.uniform(0.2, 0.8)).astype(np.float32), "random"
    else:
        kind = ("far", "white", "black", "checker")[int(rng.integers(4))]
        if kind == "far":
            grid = flip_fraction(trigger, float(rng.uniform(far, 1.0)), rng, visible)
        elif kind == "checker":
            grid = checker_grid(n)
        else:
            grid = np.full((n, n), float(kind == "white"), np.float32)
    disagreement = 1.0 - cell_agreement(grid, trigger, visible)
    labelled = disagreement > basin if ramp is None else rng.random() < label_probability(disagreement, basin, ramp)
    if min_contrast is not None and rng.random() < 0.5:
        grid = (0.5 + rng.uniform(min_contrast, 1.0) * (grid - 0.5)).astype(np.float32)
    return grid, kind, bool(labelled)
