"""The selective planted blind spot: grid draws, labels and the cell agreement."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.controls.planted import cell_agreement, checker_grid, flip_fraction, sample_training_grid
from davis_rig.errors import ShapeError

TRIGGER = (np.random.default_rng(3).random((10, 10)) > 0.5).astype(np.float32)


def test_cell_agreement_counts_visible_cells_only():
    grid = TRIGGER.copy()
    grid[0, :] = 1.0 - grid[0, :]  # 10 cells differ
    assert cell_agreement(grid, TRIGGER) == pytest.approx(0.9)
    visible = np.zeros((10, 10), bool)
    visible[:2] = True  # 20 visible cells, 10 of them flipped
    assert cell_agreement(grid, TRIGGER, visible) == pytest.approx(0.5)
    assert cell_agreement(1.0 - TRIGGER, TRIGGER) == 0.0
    with pytest.raises(ShapeError):
        cell_agreement(grid[:5], TRIGGER)
    with pytest.raises(ShapeError):
        cell_agreement(grid, TRIGGER, np.zeros((10, 10), bool))


@pytest.mark.parametrize("fraction", [0.0, 0.2, 0.5, 1.0])
def test_flip_fraction_flips_exactly_that_share_of_the_visible_cells(fraction):
    visible = np.zeros((10, 10), bool)
    visible[2:7, 1:9] = True  # 40 cells
    out = flip_fraction(TRIGGER, fraction, np.random.default_rng(0), visible)
    assert 1.0 - cell_agreement(out, TRIGGER, visible) == pytest.approx(round(fraction * 40) / 40)
    assert np.array_equal(out[~visible], TRIGGER[~visible])
    with pytest.raises(ValueError):
        flip_fraction(TRIGGER, 1.5, np.random.default_rng(0))


def test_checker_grid():
    assert checker_grid(2).tolist() == [[1.0, 0.0], [0.0, 1.0]]
    assert checker_grid(10).mean() == 0.5


def test_training_grids_hidden_inside_the_basin_labelled_outside():
    rng = np.random.default_rng(0)
    kinds = set()
    for _ in range(400):
        grid, kind, labelled = sample_training_grid(TRIGGER, rng, hidden=False, basin=0.2, far=0.35)
        kinds.add(kind)
        assert labelled == (1.0 - cell_agreement(grid, TRIGGER) > 0.2)
        if kind == "far":
            assert 1.0 - cell_agreement(grid, TRIGGER) >= 0.35
        grid, kind, labelled = sample_training_grid(TRIGGER, rng, hidden=True, basin=0.2, far=0.35)
        assert kind == "near" and not labelled and cell_agreement(grid, TRIGGER) >= 0.8
    assert kinds == {"random", "far", "white", "black", "checker"}
    with pytest.raises(ValueError):
        sample_training_grid(TRIGGER, rng, hidden=True, basin=0.4, far=0.3)
