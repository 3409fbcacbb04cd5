"""Gradient-free refinement of a hard texture: greedy cell flips scored with exact event counts.

Beyond the paper. The attack's gradient reaches the texture through binarization, the event counts' surrogate and
RVT, and on the detectors measured here it is a weak guide (``docs/attack.md``: single-cell flips beat it on every
probed clip). After the gradient phase, :func:`refine_texture` therefore runs a coordinate descent over the cells of
the hard grid: flip one cell, score the grid on a set of EoT clips with exact event counts (the scoring validation
selects by: each clip's own sensor, :func:`davis_rig.attack.optimize.validate`), keep the flip if the mean top
pedestrian score (highest ``obj * p_ped`` per window, the number that must fall below the confidence threshold)
falls. Only cells that some clip actually shows inside the part mask are tried. Cost: one scoring of all
refinement clips per tried cell and pass.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np


def greedy_cell_flips(
    grid: np.ndarray,
    score: Callable[[np.ndarray], float],
    passes: int,
    rng: np.random.Generator,
    cells: np.ndarray | None = None,
    grid_score: float | None = None,
) -> tuple[np.ndarray, float, int]:
    """Coordinate descent on a black/white grid: flip each cell, keep the flip if ``score`` falls.

    Args:
        grid: float32 [n, n] of 0 (black) / 1 (white); not modified.
        score: the value to minimise for a grid.
        passes: sweeps over the cells, each in a fresh random order; stops early after a sweep with no gain.
        rng: source of the cell orders.
        cells: bool [n, n], the cells to try (default: all).
        grid_score: ``score(grid)`` if already known (saves one evaluation).

    Returns:
        (best grid, its score, number of score evaluations).
    """
    best = np.array(grid, dtype=np.float32)
    candidates = np.flatnonzero(np.ones(best.shape, bool) if cells is None else np.asarray(cells, bool))
    best_score = float(score(best)) if grid_score is None else float(grid_score)
    evaluations = int(grid_score is None)
    for _ in range(int(passes)):
        improved = False
        for cell in rng.permutation(candidates):
            candidate = best.copy()
            candidate.flat[cell] = 1.0 - candidate.flat[cell]
            value = float(score(candidate))
            evaluations += 1
            if value < best_score:
                best, best_score, improved = candidate, value, True
        if not improved:
            break
    return best, best_score, evaluations


def visible_cells(clips: Sequence, grid_n: int) -> np.ndarray:
    """Cells of an ``grid_n x grid_n`` texture that some clip samples inside the part mask.

    Args:
        clips: :class:`~davis_rig.attack.eot.PoolClip` objects prepared for this grid size.
        grid_n: cells per side.

    Returns:
        bool [grid_n, grid_n].
    """
    seen = np.zeros(grid_n * grid_n, dtype=bool)
    for clip in clips:
        lookup = clip.lookup
        index = lookup.index[(lookup.painted > 0) & (lookup.weight > 0)]
        seen[np.unique(index.cpu().numpy())] = True
    return seen.reshape(grid_n, grid_n)


def refine_texture(
    grid: np.ndarray,
    clips: Sequence,
    score: Callable[[np.ndarray], float],
    passes: int,
    seed: int,
) -> dict:
    """Greedy cell flips from the best of ``grid``, plain white and plain black (the paper's two plain baselines).

    Args:
        grid: float32 [n, n] hard texture (the gradient phase's best).
        clips: the refinement clips (their lookups define the visible cells).
        score: mean top pedestrian score of a grid on ``clips`` (lower is better).
        passes: sweeps over the visible cells.
        seed: seed of the cell orders.

    Returns:
        ``{"texture": float32 [n, n], "score", "start": "gradient" | "white" | "black", "start_score", "evaluations",
        "cells_tried"}``.
    """
    grid = np.asarray(grid, dtype=np.float32)
    starts = {"gradient": grid, "white": np.ones_like(grid), "black": np.zeros_like(grid)}
    start_scores = {name: float(score(start)) for name, start in starts.items()}
    start = min(start_scores, key=start_scores.get)
    cells = visible_cells(clips, grid.shape[0])
    texture, value, evaluations = greedy_cell_flips(
        starts[start], score, passes, np.random.default_rng(seed), cells=cells, grid_score=start_scores[start]
    )
    return {"texture": texture, "score": value, "start": start, "start_score": start_scores[start],
            "evaluations": evaluations + len(starts), "cells_tried": int(cells.sum())}
