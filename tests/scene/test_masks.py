"""Tests of davis_rig.scene.masks: UV part label map, part masks, seam padding, combinations."""

import numpy as np
import pytest

from davis_rig.scene import masks
from davis_rig.scene.body import PART_NAMES
from davis_rig.scene.masks import (
    EMPTY_LABEL,
    PAINTABLE_COMBINATIONS,
    combination_masks,
    part_label_map,
    part_mask,
    uv_to_texel,
)


def centroid_texels(asset, size):
    xy = np.round(uv_to_texel(asset.face_uvs.astype(np.float64).mean(axis=1), size)).astype(np.int64)
    xy = np.clip(xy, 0, size - 1)
    return xy[:, 1], xy[:, 0]


def test_uv_to_texel_convention():
    corners = uv_to_texel(np.array([[0.0, 1.0], [1.0, 0.0], [0.5, 0.5]]), 8)
    np.testing.assert_array_equal(corners, [[-0.5, -0.5], [7.5, 7.5], [3.5, 3.5]])


def test_triangle_rasterizer_exact_on_hand_made_triangles():
    # right triangle with legs of 4 texels from texel centre (1, 2): centres with x >= 1, y >= 2, (x-1)+(y-2) <= 4
    tri = np.array([[[1.0, 2.0], [5.0, 2.0], [1.0, 6.0]], [[1.0, 2.0], [1.0, 6.0], [5.0, 2.0]]])  # both windings
    faces, rows, cols = masks._triangle_texels(tri, 16)
    for f in (0, 1):
        got = set(zip(rows[faces == f].tolist(), cols[faces == f].tolist()))
        expected = {(y, x) for y in range(16) for x in range(16) if x >= 1 and y >= 2 and (x - 1) + (y - 2) <= 4}
        assert got == expected  # 15 texels; the centroid texel (3, 2) is among them
    # a sub-texel triangle still marks its centroid's texel
    faces, rows, cols = masks._triangle_texels(np.array([[[3.1, 3.1], [3.3, 3.1], [3.1, 3.3]]]), 16)
    assert set(zip(rows.tolist(), cols.tolist())) == {(3, 3)}


def test_label_map_shape_dtype_and_cache():
    labels = part_label_map()
    assert labels.shape == (1024, 1024) and labels.dtype == np.uint8
    assert set(np.unique(labels)) == set(range(len(PART_NAMES))) | {EMPTY_LABEL}
    assert part_label_map() is labels and not labels.flags.writeable
    small = part_label_map(size=256)
    assert small.shape == (256, 256)


def test_every_face_covers_its_own_part(asset):
    for size in (1024, 256):
        labels = part_label_map(size=size, padding_px=0)
        rows, cols = centroid_texels(asset, size)
        assert (labels[rows, cols] != EMPTY_LABEL).all()
        # only faces smaller than a texel can lose their centroid texel to a neighbour of another part
        own = labels[rows, cols] == asset.face_parts
        assert own.mean() > (0.999 if size == 1024 else 0.99)
    for part in PART_NAMES:
        mask = part_mask([part], padding_px=0)
        faces = asset.face_part_mask([part])
        rows, cols = centroid_texels(asset, 1024)
        assert mask[rows[faces], cols[faces]].mean() > 0.999


def test_parts_are_disjoint_and_cover_the_label_map():
    singles = {p: part_mask([p]) for p in PART_NAMES}
    total = np.zeros((1024, 1024), dtype=np.int64)
    for mask in singles.values():
        assert mask.dtype == bool and mask.shape == (1024, 1024) and mask.any()
        total += mask
    assert total.max() == 1
    np.testing.assert_array_equal(total == 1, part_label_map() != EMPTY_LABEL)
    paintable = part_mask(("torso", "arms", "legs"))
    excluded = part_mask(("head", "hands", "feet"))
    assert not (paintable & excluded).any()


def test_seam_padding_grows_islands_into_empty_space_only():
    bare = part_label_map(padding_px=0)
    padded = part_label_map(padding_px=4)
    kept = bare != EMPTY_LABEL
    np.testing.assert_array_equal(padded[kept], bare[kept])  # labelled texels keep their part
    grown = (padded != EMPTY_LABEL) & ~kept
    assert grown.sum() > 10000
    # every texel within 4 texels (chessboard distance) of an island is now labelled
    import cv2

    near = cv2.dilate(kept.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert (padded[near] != EMPTY_LABEL).all()
    # a grown texel takes the part of an island texel within 4 texels
    for code in range(len(PART_NAMES)):
        reach = cv2.dilate((bare == code).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        assert reach[grown & (padded == code)].all()


def test_seven_paintable_combinations():
    assert len(PAINTABLE_COMBINATIONS) == 7 and len(set(PAINTABLE_COMBINATIONS)) == 7
    combos = combination_masks(size=256)
    assert list(combos) == ["torso", "arms", "legs", "torso+arms", "torso+legs", "arms+legs", "torso+arms+legs"]
    singles = {p: part_mask([p], size=256) for p in ("torso", "arms", "legs")}
    for name, mask in combos.items():
        expected = np.logical_or.reduce([singles[p] for p in name.split("+")])
        np.testing.assert_array_equal(mask, expected)
    assert combos["torso"].sum() > combos["arms"].sum() > 0


def test_explicit_asset_gives_same_map(asset):
    np.testing.assert_array_equal(part_label_map(size=256, asset=asset), part_label_map(size=256))


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown body parts"):
        part_mask(["torso", "tail"])
    with pytest.raises(ValueError, match="size"):
        part_label_map(size=8)
    with pytest.raises(ValueError, match="padding_px"):
        part_label_map(padding_px=-1)
