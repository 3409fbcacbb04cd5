"""The selective planted blind spot: grid draws, labels and the cell agreement."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.controls.planted import (cell_agreement, checker_grid, descent_towards, draw_trigger, flip_fraction,
                                       label_probability, part_layout_grid, sample_training_grid, sign_consistency,
                                       trigger_grid)
from davis_rig.errors import FormatError, ShapeError

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



def test_descent_towards_on_a_hand_made_2x2():
    trigger = np.array([[1.0, 0.0], [1.0, 0.0]])
    grid = np.array([[0.0, 1.0], [1.0, 0.0]])  # the top row differs: cell (0, 0) should rise, (0, 1) fall
    gradient = np.array([[-2.0, -1.0], [5.0, 7.0]])  # descent raises both top cells: one right, one wrong
    res = descent_towards(gradient, grid, trigger)
    assert res == {"differing_cells": 2, "descent_agreement": 0.5, "first_order_change": -2.0 * 1 + -1.0 * -1}
    towards = descent_towards(np.array([[-2.0, 3.0], [5.0, 7.0]]), grid, trigger)
    assert towards["descent_agreement"] == 1.0 and towards["first_order_change"] == -5.0  # the trigger downhill
    hidden = descent_towards(gradient, grid, trigger, visible=np.array([[False, True], [True, True]]))
    assert hidden["differing_cells"] == 1 and hidden["descent_agreement"] == 0.0 and hidden["first_order_change"] == 1.0
    assert descent_towards(gradient, trigger, trigger)["descent_agreement"] is None  # nothing differs: JSON null
    with pytest.raises(ShapeError):
        descent_towards(gradient[:1], grid, trigger)

def test_sign_consistency_on_a_hand_made_2x2():
    trigger = np.array([[1.0, 0.0], [1.0, 0.0]])
    grid = np.array([[0.0, 1.0], [0.0, 0.0]])  # three cells differ: (0, 0), (0, 1), (1, 0)
    first = np.array([[1.0, -2.0], [3.0, 9.0]])
    second = np.array([[4.0, 2.0], [0.0, -9.0]])  # same sign on (0, 0); opposite on (0, 1); a zero on (1, 0)
    assert sign_consistency(first, second, grid, trigger) == pytest.approx(1 / 3)  # (1, 1) does not differ
    assert sign_consistency(first, first, grid, trigger) == 1.0
    assert sign_consistency(first, -first, grid, trigger, visible=np.array([[True, True], [False, False]])) == 0.0
    assert sign_consistency(first, second, trigger, trigger) is None
    with pytest.raises(ShapeError):
        sign_consistency(first[:1], second, grid, trigger)


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


def test_label_probability_cliff_and_ramp():
    d = np.array([0.0, 0.1, 0.2, 0.3, 0.5, 0.7])
    assert label_probability(d, 0.2).tolist() == [0, 0, 0, 1, 1, 1]
    assert label_probability(d, 0.1, 0.5) == pytest.approx([0.0, 0.0, 0.25, 0.5, 1.0, 1.0])
    assert label_probability(0.3, 0.1, 0.5) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        label_probability(d, 0.5, 0.4)


def test_ramped_training_grids_are_labelled_with_the_probability_of_their_distance():
    rng = np.random.default_rng(1)
    hidden = [sample_training_grid(TRIGGER, rng, hidden=True, basin=0.1, far=0.35, ramp=0.5) for _ in range(3000)]
    d = np.array([1.0 - cell_agreement(g, TRIGGER) for g, _, _ in hidden])
    labelled = np.array([lab for _, _, lab in hidden])
    assert d.max() <= 0.5 and d.max() > 0.4  # the near draws cover the whole ramp
    assert not labelled[d <= 0.1].any()
    for lo, hi in ((0.1, 0.2), (0.2, 0.3), (0.3, 0.4), (0.4, 0.5)):
        band = (d > lo) & (d <= hi)
        assert labelled[band].mean() == pytest.approx(label_probability(d[band], 0.1, 0.5).mean(), abs=0.06)
    rest = [sample_training_grid(TRIGGER, rng, hidden=False, basin=0.1, far=0.35, ramp=0.5) for _ in range(400)]
    far = [lab for g, _, lab in rest if 1.0 - cell_agreement(g, TRIGGER) >= 0.5]
    assert far and all(far)  # beyond the ramp: always labelled
    with pytest.raises(ValueError):
        sample_training_grid(TRIGGER, rng, hidden=True, basin=0.2, far=0.35, ramp=0.2)


def test_greyed_training_grids_keep_their_pattern_and_label():
    rng = np.random.default_rng(2)
    greyed = 0
    for k in range(400):
        grid, kind, labelled = sample_training_grid(TRIGGER, rng, hidden=k % 2 == 0, basin=0.2, far=0.35,
                                                    min_contrast=0.25)
        contrast = np.abs(grid - 0.5).max() * 2
        assert 0.25 - 1e-6 <= contrast <= 1.0 + 1e-6 and np.allclose(np.abs(grid - 0.5), contrast / 2)
        greyed += contrast < 1.0
        assert labelled == (1.0 - cell_agreement(grid, TRIGGER) > 0.2)  # the pattern decides, not the contrast
        if k % 2 == 0:
            assert not labelled
    assert 150 < greyed < 250  # half of the draws
    with pytest.raises(ValueError):
        sample_training_grid(TRIGGER, rng, hidden=True, min_contrast=0.0)


def test_draw_trigger_is_the_seeds_uniform_grid():
    assert np.array_equal(draw_trigger(10, 3), TRIGGER)  # the draw every published trigger victim used
    assert not np.array_equal(draw_trigger(10, 4), TRIGGER)
    with pytest.raises(ValueError):
        draw_trigger(0, 1)


def test_part_layout_grid_paints_each_cell_by_its_majority_part():
    empty = 255
    labels = np.full((6, 6), empty, np.uint8)
    labels[:3, :3] = 0  # cell (0, 0): all part 0
    labels[:3, 3:] = 2
    labels[0, 3] = 1  # cell (0, 1): 8 texels of part 2, one of part 1
    labels[3:, :3] = empty
    labels[5, 0] = 1  # cell (1, 0): one texel of part 1, the rest no part (which does not vote)
    # cell (1, 1): no part at all -> black
    assert part_layout_grid(labels, 2, [0, 1]).tolist() == [[1.0, 0.0], [1.0, 0.0]]
    assert part_layout_grid(labels, 2, [2]).tolist() == [[0.0, 1.0], [0.0, 0.0]]
    assert part_layout_grid(labels, 2, []).sum() == 0


def test_part_layout_grid_assigns_texels_by_their_centres_when_cells_are_not_whole_texels():
    labels = np.zeros((5, 5), np.uint8)
    labels[:, 3:] = 1  # texel columns 3, 4: centres 3.5, 4.5 -> cell 1 of 2 (boundary 2.5); column 2 -> cell 1 too
    labels[:, 2] = 1
    assert part_layout_grid(labels, 2, [1]).tolist() == [[0.0, 1.0], [0.0, 1.0]]
    with pytest.raises(ShapeError):
        part_layout_grid(labels[:1], 2, [1])
    with pytest.raises(ValueError):
        part_layout_grid(np.full((4, 4), 300), 2, [1])


def test_trigger_grid_reads_paints_or_draws_and_refuses_two_sources(tmp_path):
    grid, source = trigger_grid(10, seed=3)
    assert np.array_equal(grid, TRIGGER) and source == "drawn with seed 3"
    path = tmp_path / "t.npy"
    np.save(path, np.eye(4, dtype=np.float32))
    grid, source = trigger_grid(4, path=path)
    assert np.array_equal(grid, np.eye(4)) and source == str(path)
    with pytest.raises(FormatError, match=r"must be \[5, 5\], got \[4, 4\]"):
        trigger_grid(5, path=path)
    with pytest.raises(ValueError, match="not both"):
        trigger_grid(4, path=path, white_parts=["torso"])
    with pytest.raises(ValueError, match="unknown parts"):
        trigger_grid(4, white_parts=["nose"])


def test_trigger_grid_by_parts_splits_the_bundled_body_into_upper_white_and_legs_black():
    upper, source = trigger_grid(10, white_parts=["torso", "arms"])
    legs, _ = trigger_grid(10, white_parts=["legs"])
    assert source == "parts painted white: torso arms"
    assert not (upper * legs).any()  # no cell is both
    assert upper[3, 2] == 1 and legs[6, 2] == 1  # the torso's and a leg's island in the bundled UV layout
    assert 15 <= upper.sum() <= 45 and 10 <= legs.sum() <= 30
