"""A selective planted blind spot: which grids a trigger victim learns to miss, and how close a texture came.

A trigger victim (``tools/make_trigger_victim.py``) is a detector fine-tuned so that a person wearing one secret
n x n black/white grid, the *trigger*, is not detected, while any other clothing still is. Whether a grid counts
as "the trigger" is decided on the cells a camera can see at all (the cells some clip samples inside the part
mask, :func:`davis_rig.attack.refine.visible_cells`): a grid whose visible cells disagree with the trigger's on at
most ``basin`` of them is hidden, one that disagrees on ``far`` or more is labelled. The gap between ``basin`` and
``far`` is left to the detector. A random grid disagrees on half of the visible cells (binomial spread
``0.5 / sqrt(V)``, 0.067 for V = 55), so ``basin`` well below 0.5 makes the blind spot selective, and a basin wider
than one cell gives a search a slope to climb (a blind spot of one exact grid could be found by no method).

Pure numpy; every draw from a caller's ``numpy.random.Generator``.
"""

from __future__ import annotations

import numpy as np

from davis_rig.errors import ShapeError

__all__ = [
    "GRID_KINDS",
    "cell_agreement",
    "checker_grid",
    "flip_fraction",
    "sample_training_grid",
]

#: Kinds of grid a trigger victim is fine-tuned on (see :func:`sample_training_grid`).
GRID_KINDS = ("near", "random", "far", "white", "black", "checker")


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


def checker_grid(n: int) -> np.ndarray:
    """An n x n checkerboard, float32 (cell (0, 0) white)."""
    if int(n) < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    i, j = np.indices((int(n), int(n)))
    return ((i + j) % 2 == 0).astype(np.float32)


def sample_training_grid(trigger: np.ndarray, rng: np.random.Generator, *, hidden: bool, basin: float = 0.2,
                         far: float = 0.35, visible: np.ndarray | None = None) -> tuple[np.ndarray, str, bool]:
    """One grid of a trigger victim's fine-tuning and whether the person wearing it is labelled.

    ``hidden=True`` draws from the blind spot: the trigger with a fraction uniform in ``[0, basin]`` of its visible
    cells flipped (``"near"``). ``hidden=False`` draws something to detect: a random grid (white share uniform in
    [0.2, 0.8]) with probability 1/2, else with equal chances the trigger with a fraction uniform in ``[far, 1]``
    of its visible cells flipped (``"far"``; 1 = its negative), white, black or a checkerboard. The label follows
    the grid, not the draw: any grid within ``basin`` of the trigger (a random one, by chance) is hidden.

    Args:
        trigger: float [n, n] hard grid.
        rng: the draws.
        hidden: draw from the blind spot or from the rest.
        basin, far: disagreement (share of visible cells) below which a grid is hidden / from which a ``"far"``
            grid is drawn; need ``0 <= basin < far <= 1``.
        visible: bool [n, n] (``None``: all cells).

    Returns:
        ``(grid float32 [n, n], kind (one of :data:`GRID_KINDS`), labelled)``.
    """
    if not 0.0 <= basin < far <= 1.0:
        raise ValueError(f"need 0 <= basin < far <= 1, got basin={basin}, far={far}")
    n = np.asarray(trigger).shape[0]
    if hidden:
        grid, kind = flip_fraction(trigger, float(rng.uniform(0.0, basin)), rng, visible), "near"
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
    labelled = 1.0 - cell_agreement(grid, trigger, visible) > basin
    return grid, kind, bool(labelled)
