"""The linear probe of backbone features: box pooling on hand-made maps, the cross-validated fit on made-up data."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from davis_rig.controls.feature_probe import box_features, linear_probe, stage_stride  # noqa: E402
from davis_rig.errors import ShapeError  # noqa: E402


def test_stage_strides_are_rvts():
    assert [stage_stride(s) for s in (1, 2, 3, 4)] == [4, 8, 16, 32]
    with pytest.raises(ValueError):
        stage_stride(0)


def test_box_features_pool_the_cells_under_the_box():
    fmap = torch.arange(2 * 6 * 5, dtype=torch.float32).reshape(1, 2, 6, 5)  # stage 2: stride 8
    # box x 8..24, y 16..48 px -> columns 1..2, rows 2..5 (ceil(48 / 8) = 6)
    out = box_features({2: fmap}, (8.0, 16.0, 24.0, 48.0), stages=(2,), cells=(2, 1))
    crop = fmap[0, :, 2:6, 1:3].numpy()
    expected = np.stack([crop[:, :2].mean((1, 2)), crop[:, 2:].mean((1, 2))], axis=1).reshape(-1)  # [C, rows]
    np.testing.assert_allclose(out, expected)
    assert out.dtype == np.float32 and out.shape == (4,)


def test_box_features_keep_one_cell_for_a_box_at_the_border_and_join_stages():
    feats = {2: torch.ones(1, 3, 4, 4), 3: torch.full((1, 5, 2, 2), 2.0)}
    out = box_features(feats, (100.0, 100.0, 101.0, 101.0), stages=(2, 3), cells=(4, 2))  # beyond the map
    assert out.shape == (3 * 8 + 5 * 8,)
    assert (out[:24] == 1).all() and (out[24:] == 2).all()


@pytest.mark.parametrize("box", [(0, 0, 0, 5), (np.nan, 0, 4, 4), (0, 0, 4)])
def test_box_features_refuse_bad_boxes(box):
    with pytest.raises(ShapeError):
        box_features({2: torch.zeros(1, 1, 4, 4)}, box, stages=(2,))


def test_box_features_refuse_a_missing_stage_or_a_batch():
    with pytest.raises(ShapeError, match="stage 3 missing"):
        box_features({2: torch.zeros(1, 1, 4, 4)}, (0, 0, 8, 8), stages=(3,))
    with pytest.raises(ShapeError, match=r"\[1, C, H, W\]"):
        box_features({2: torch.zeros(2, 1, 4, 4)}, (0, 0, 8, 8), stages=(2,))


def _groups(n_groups: int, per_group: int) -> np.ndarray:
    return np.repeat(np.arange(n_groups), per_group)


def test_a_separable_task_is_learned_on_held_out_groups():
    rng = np.random.default_rng(0)
    groups = _groups(12, 10)
    y = np.tile([0, 1], 60)
    x = rng.normal(size=(120, 20))
    x[:, 3] += 4.0 * (2 * y - 1)  # one feature carries the label
    res = linear_probe(x, y, groups, folds=3)
    assert res.accuracy == 1.0 and res.train_accuracy == 1.0 and len(res.fold_accuracy) == 3


def test_labels_the_features_do_not_carry_stay_at_chance():
    rng = np.random.default_rng(1)
    groups = _groups(30, 10)
    y = np.tile([0, 1], 150)
    res = linear_probe(rng.normal(size=(300, 50)), y, groups, folds=3, weight_decay=0.0)
    assert res.train_accuracy > 0.7  # it fits its own folds...
    assert 0.38 < res.accuracy < 0.62  # ...and learns nothing that holds out


def test_groups_are_never_split_so_a_scene_cannot_stand_in_for_the_label():
    # every group is one scene: identical features for its samples and one random label per group; a probe that
    # saw the group in training would recognise it, one that never does is at chance
    rng = np.random.default_rng(2)
    groups = _groups(40, 6)
    group_x, group_y = rng.normal(size=(40, 30)), rng.integers(0, 2, 40)
    x, y = group_x[groups], group_y[groups]
    res = linear_probe(x, y, groups, folds=4, weight_decay=0.0)
    assert res.train_accuracy > 0.9
    assert res.accuracy < 0.75
    shuffled = linear_probe(x, y, rng.permutation(groups.size) % 40, folds=4, weight_decay=0.0)  # groups ignored
    assert shuffled.accuracy > 0.9  # the leak the grouping closes


def test_linear_probe_is_deterministic_and_refuses_bad_input():
    rng = np.random.default_rng(3)
    x, y, groups = rng.normal(size=(40, 5)), np.tile([0, 1], 20), _groups(8, 5)
    a, b = linear_probe(x, y, groups), linear_probe(x, y, groups)
    assert a.fold_accuracy == b.fold_accuracy and (a.correct == b.correct).all()
    with pytest.raises(ShapeError):
        linear_probe(x[:, 0], y, groups)
    with pytest.raises(ShapeError):
        linear_probe(x, y + 1, groups)
    with pytest.raises(ValueError, match="folds"):
        linear_probe(x, y, groups, folds=9)
    with pytest.raises(ValueError, match="one class"):
        linear_probe(x, (groups == 0).astype(int), groups, folds=2)  # fold 0 trains on zeros only
