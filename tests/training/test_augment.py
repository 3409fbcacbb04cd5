"""Flip / zoom augmentation: exact pixel and box maps, consistency over a chunk, no mutation, determinism."""

from __future__ import annotations

import pytest
import torch

from davis_rig.errors import ConfigError, ShapeError
from davis_rig.training.augment import (
    AugmentConfig,
    AugmentParams,
    apply_augment,
    hflip,
    sample_params,
    zoom_in,
    zoom_out,
)

H, W = 240, 304


def _box_hist(boxes: list[tuple[float, float, float, float]], length: int = 2) -> torch.Tensor:
    hist = torch.zeros(length, 20, H, W)
    for x, y, w, h in boxes:
        hist[:, 3, int(y):int(y + h), int(x):int(x + w)] = 1.0
    return hist


def _extent(mask: torch.Tensor) -> tuple[int, int, int, int]:
    rows = mask.any(1).nonzero().flatten()
    cols = mask.any(0).nonzero().flatten()
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def test_hflip_exact_and_involution():
    hist = _box_hist([(10, 20, 30, 40)])
    boxes = [torch.tensor([[1.0, 10, 20, 30, 40]]), None]
    out, out_boxes = hflip(hist, boxes)
    assert out_boxes[0].tolist() == [[1.0, W - 40, 20, 30, 40]]
    assert out_boxes[1] is None
    assert _extent(out[0, 3] > 0) == (W - 40, 20, W - 10, 60)
    back, back_boxes = hflip(out, out_boxes)
    assert torch.equal(back, hist) and torch.equal(back_boxes[0], boxes[0])


def test_zoom_in_factor_two_exact():
    hist = _box_hist([(110, 80, 20, 30)])
    boxes = [torch.tensor([[1.0, 110, 80, 20, 30]])] * 2
    out, out_boxes = zoom_in(hist, boxes, 2.0, x0=100, y0=60)
    # window 152 × 120 at (100, 60), scale exactly 2: pixel (c, r) -> (2(c − 100), 2(r − 60))
    assert _extent(out[1, 3] > 0) == (20, 40, 60, 100)
    assert out_boxes[1].tolist() == [[1.0, 20, 40, 40, 60]]


def test_zoom_in_clips_and_drops_boxes():
    hist = _box_hist([(0, 0, 10, 10)], length=1)
    boxes = [torch.tensor([[1.0, 90, 50, 20, 20], [1.0, 0, 0, 10, 10]])]
    _, out_boxes = zoom_in(hist, boxes, 2.0, x0=100, y0=60)
    # first box partly left of the window -> clipped to x ≥ 0; second entirely outside -> dropped
    assert out_boxes[0].tolist() == [[1.0, 0, 0, 20, 20]]


def test_zoom_out_factor_two_exact():
    hist = _box_hist([(100, 60, 40, 60)], length=1)
    boxes = [torch.tensor([[1.0, 100, 60, 40, 60], [1.0, 0, 0, 1.5, 1.5]])]
    out, out_boxes = zoom_out(hist, boxes, 2.0, x0=10, y0=20)
    assert _extent(out[0, 3] > 0) == (60, 50, 80, 80)
    assert out_boxes[0].tolist() == [[1.0, 60, 50, 20, 30]]  # tiny box (0.75 px) dropped
    assert out[0, :, :20].abs().sum() == 0 and out[0, :, :, :10].abs().sum() == 0


def test_apply_does_not_mutate_and_is_consistent_over_chunk():
    hist = _box_hist([(120, 90, 30, 50)], length=3)
    boxes = [torch.tensor([[1.0, 120, 90, 30, 50]]), None, torch.tensor([[1.0, 120, 90, 30, 50]])]
    hist_copy, boxes_copy = hist.clone(), [b.clone() if b is not None else None for b in boxes]
    params = AugmentParams(hflip=True, zoom_in=1.25, x0=40, y0=30)
    out, out_boxes = apply_augment(hist, boxes, params)
    assert torch.equal(hist, hist_copy) and all(
        (a is None and b is None) or torch.equal(a, b) for a, b in zip(boxes, boxes_copy))
    assert torch.equal(out[0], out[2]) and out_boxes[1] is None
    assert torch.equal(out_boxes[0], out_boxes[2])
    x1, y1, x2, y2 = _extent(out[0, 3] > 0)
    b = out_boxes[0][0].tolist()
    assert abs(x1 - b[1]) <= 1 and abs(y1 - b[2]) <= 1 and abs(x2 - (b[1] + b[3])) <= 1 and abs(y2 - (b[2] + b[4])) <= 1


def test_sample_params_deterministic_and_keeps_a_box_in_view():
    config = AugmentConfig(zoom_prob=1.0, zoom_in_weight=1.0, zoom_out_weight=0.0)
    box = torch.tensor([[1.0, 250, 180, 30, 40]])
    first = [sample_params(config, torch.Generator().manual_seed(s), (H, W), box) for s in range(40)]
    again = [sample_params(config, torch.Generator().manual_seed(s), (H, W), box) for s in range(40)]
    assert first == again
    hist = _box_hist([(250, 180, 30, 40)], length=1)
    for params in first:
        assert params.zoom_in >= 1.0 and params.zoom_out == 1.0
        _, out_boxes = apply_augment(hist, [box], params)
        assert out_boxes[0].shape[0] == 1  # the chosen box's centre stays in the window


def test_sample_params_off_and_no_zoom_in_without_boxes():
    gen = torch.Generator().manual_seed(0)
    assert all(sample_params(AugmentConfig.off(), gen, (H, W), None) == AugmentParams() for _ in range(10))
    config = AugmentConfig(prob_hflip=0.0, zoom_prob=1.0, zoom_in_weight=1.0, zoom_out_weight=0.0)
    assert sample_params(config, gen, (H, W), None) == AugmentParams()


def test_bad_inputs():
    with pytest.raises(ShapeError):
        apply_augment(torch.zeros(2, 20, H, W), [None], AugmentParams())
    with pytest.raises(ShapeError):
        zoom_in(torch.zeros(1, 20, H, W), [None], 2.0, x0=200, y0=0)
    for kwargs, field in (({"zoom_in_range": (0.5, 1.0)}, "zoom_in_range"), ({"zoom_prob": 1.5}, "zoom_prob"),
                          ({"zoom_in_weight": 0.0, "zoom_out_weight": 0.0}, "zoom_in_weight")):
        with pytest.raises(ConfigError) as info:
            AugmentConfig(**kwargs)
        assert info.value.field == field
