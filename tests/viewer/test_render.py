"""The drawing kernels on small numpy images, with exact expected pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from davis_rig.errors import ShapeError
from davis_rig.viewer.render import (BACKGROUND_RGB, CROP_RGB, DETECTION_RGB, GAP_PX, GAP_RGB, LABEL_RGB, OFF_RGB,
                                     ON_RGB, ViewContent, add_event_counts, aps_image, box_pixels, draw_boxes,
                                     draw_outline,
                                     encode_image, event_counts, event_image, render_view, side_by_side)


def test_event_counts_per_pixel_and_polarity():
    counts = event_counts([0, 0, 2, 2, 2], [1, 1, 0, 0, 0], [1, 1, 0, 1, 0], hw=(2, 3))
    expected = np.zeros((2, 2, 3), np.int64)
    expected[1, 1, 0] = 2  # two ON at (x=0, y=1)
    expected[0, 0, 2] = 2  # two OFF and one ON at (x=2, y=0)
    expected[1, 0, 2] = 1
    np.testing.assert_array_equal(counts, expected)


def test_event_counts_added_part_by_part_are_the_counts_of_all_the_events():
    rng = np.random.default_rng(0)
    x, y, p = rng.integers(0, 346, 5_000), rng.integers(0, 260, 5_000), rng.integers(0, 2, 5_000)
    counts = np.zeros((2, 260, 346), np.int32)
    for part in np.array_split(np.arange(5_000), 7):
        add_event_counts(counts, x[part], y[part], p[part])
    np.testing.assert_array_equal(counts, event_counts(x, y, p))
    with pytest.raises(ShapeError, match="outside"):
        add_event_counts(counts, [346], [0], [1])


def test_event_counts_refuses_events_outside_the_image_and_ragged_columns():
    with pytest.raises(ShapeError, match="outside"):
        event_counts([3], [0], [1], hw=(2, 3))
    with pytest.raises(ShapeError, match="equal lengths"):
        event_counts([0, 1], [0], [1], hw=(2, 3))


def test_event_image_colours_the_majority_polarity_ties_to_on():
    counts = np.zeros((2, 1, 4), np.int64)
    counts[1, 0, 0] = 3                      # ON only
    counts[0, 0, 1] = 2                      # OFF only
    counts[:, 0, 2] = [2, 2]                 # tie -> ON
    counts[:, 0, 3] = [0, 0]                 # nothing
    image = event_image(counts)
    assert image.dtype == np.uint8 and image.shape == (1, 4, 3)
    assert [tuple(p) for p in image[0]] == [ON_RGB, OFF_RGB, ON_RGB, BACKGROUND_RGB]


def test_aps_image_shifts_to_8_bit_and_places_the_region():
    pixels = np.array([[0, 1 << 6, 1023 << 6]], np.uint16)
    image = aps_image(pixels, origin_xy=(1, 2), hw=(4, 5))
    expected = np.zeros((4, 5, 3), np.uint8)
    expected[2, 1:4] = np.array([0, 0, 255], np.uint8)[:, None]  # (64 >> 8) = 0, (65472 >> 8) = 255
    np.testing.assert_array_equal(image, expected)
    with pytest.raises(ShapeError, match="does not fit"):
        aps_image(pixels, origin_xy=(3, 0), hw=(4, 5))


def test_box_pixels_round_half_up_and_exclusive_far_corner():
    np.testing.assert_array_equal(box_pixels([[10.5, 2.49, 20.0, 7.5], [3.0, 3.0, 3.2, 3.2]]),
                                  [[11, 2, 19, 7], [3, 3, 3, 3]])


def test_draw_outline_clips_and_does_not_touch_the_input():
    image = np.zeros((5, 6, 3), np.uint8)
    out = draw_outline(image, [[1, 1, 3, 2], [4, -2, 9, 3]], (9, 8, 7))
    assert not image.any()
    drawn = (out == (9, 8, 7)).all(axis=2)
    expected = np.zeros((5, 6), bool)
    expected[1, 1:4] = expected[2, 1:4] = True          # rows of the first box
    expected[1:3, 1] = expected[1:3, 3] = True          # its columns
    expected[3, 4:6] = True                             # the second box's bottom row, clipped at x = 5
    expected[0:4, 4] = True                             # its left column (its right one is outside)
    np.testing.assert_array_equal(drawn, expected)


def test_draw_boxes_offsets_crop_boxes_onto_the_sensor():
    image = np.zeros((20, 30, 3), np.uint8)
    out = draw_boxes(image, [[2, 3, 6, 8]], LABEL_RGB, offset_xy=(10, 5))
    drawn = (out == LABEL_RGB).all(axis=2)
    rows, cols = np.nonzero(drawn)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (8, 12, 12, 15)
    assert drawn[8, 12:16].all() and drawn[12, 12:16].all() and drawn[8:13, 12].all() and drawn[8:13, 15].all()
    assert not drawn[9:12, 13:15].any()


def test_side_by_side_puts_a_gap_between_panels():
    a, b = np.full((2, 3, 3), 1, np.uint8), np.full((2, 2, 3), 2, np.uint8)
    out = side_by_side([a, b], gap_px=2)
    assert out.shape == (2, 7, 3)
    assert (out[:, :3] == 1).all() and (out[:, 3:5] == GAP_RGB).all() and (out[:, 5:] == 2).all()
    with pytest.raises(ShapeError, match="one height"):
        side_by_side([a, np.zeros((3, 1, 3), np.uint8)])


def test_render_view_layers_crop_outline_labels_under_detections():
    counts = np.zeros((2, 260, 346), np.int64)
    counts[1, 100, 150] = 1
    pixels = np.full((260, 346), 128 << 8, np.uint16)
    content = ViewContent(counts=counts, aps=(pixels, (0, 0)), labels_xyxy=np.array([[100.0, 50.0, 140.0, 150.0]]),
                          detections=np.array([[100, 50, 140, 150, 0.9, 0.5, 1]], np.float32), crop_origin_xy=(21, 10))
    image = render_view(content)
    assert image.shape == (260, 2 * 346 + GAP_PX, 3)
    left, right = image[:, :346], image[:, 346 + GAP_PX:]
    assert tuple(left[100, 150]) == ON_RGB and tuple(right[100, 150]) == (128, 128, 128)
    for panel in (left, right):
        # crop outline one pixel outside the 304x240 crop at (21, 10)
        assert tuple(panel[9, 100]) == CROP_RGB and tuple(panel[250, 100]) == CROP_RGB
        assert tuple(panel[100, 20]) == CROP_RGB and tuple(panel[100, 325]) == CROP_RGB
        # the detection (same box as the label) is drawn on top: box at crop (100, 50) -> sensor (121, 60)
        assert tuple(panel[100, 121]) == DETECTION_RGB and tuple(panel[100, 160]) == DETECTION_RGB
    assert tuple(image[0, 346]) == GAP_RGB
    only_labels = render_view(ViewContent(counts=counts, labels_xyxy=content.labels_xyxy,
                                          detections=content.detections, layers=frozenset({"events", "labels"})))
    assert tuple(only_labels[100, 121]) == LABEL_RGB and tuple(only_labels[9, 100]) == BACKGROUND_RGB
    right = only_labels[:, 346 + GAP_PX:]
    assert not right[~(right == LABEL_RGB).all(axis=2)].any()  # no APS layer: black, with the label outline


def test_encode_image_png_is_lossless_and_jpeg_decodes():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    decoded = cv2.imdecode(np.frombuffer(encode_image(image, "png"), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    np.testing.assert_array_equal(decoded, image)
    jpeg = cv2.imdecode(np.frombuffer(encode_image(np.full((8, 8, 3), 200, np.uint8), "jpg"), np.uint8),
                        cv2.IMREAD_COLOR)
    assert jpeg.shape == (8, 8, 3) and abs(int(jpeg.mean()) - 200) <= 2
    with pytest.raises(ValueError, match="png"):
        encode_image(image, "bmp")
