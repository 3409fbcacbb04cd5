"""Adversarial loss on hand-made decoded detector outputs."""

import pytest
import torch

from davis_rig.attack.loss import adversarial_loss, anchors_near_boxes
from davis_rig.errors import ShapeError


def _decoded(rows):
    """[B=1, A, 7] from rows (cx, cy, w, h, obj, p_car, p_ped)."""
    return torch.tensor([rows], dtype=torch.float64)


W1 = _decoded([[10, 10, 4, 4, 0.5, 0.9, 0.2], [50, 60, 8, 8, 0.1, 0.0, 0.6]])
W2 = _decoded([[20, 30, 4, 4, 0.3, 0.2, 0.4], [100, 100, 8, 8, 0.9, 0.1, 1.0]])


def test_paper_loss_is_mean_over_all_anchors_of_all_windows():
    out = adversarial_loss([W1, W2])
    obj = (0.5 + 0.1 + 0.3 + 0.9) / 4
    ped = (0.2 + 0.6 + 0.4 + 1.0) / 4
    assert out.obj.item() == pytest.approx(obj)
    assert out.cls.item() == pytest.approx(ped)
    assert out.total.item() == pytest.approx(1e4 * obj + 1e4 * ped)
    assert out.num_anchors.item() == 4
    stacked = adversarial_loss(torch.stack([W1, W2]))  # [W, B, A, 7] gives the same
    assert stacked.total.item() == pytest.approx(out.total.item())


def test_weights_and_class_choice():
    out = adversarial_loss([W1], lambda_obj=2.0, lambda_cls=0.0)
    assert out.total.item() == pytest.approx(2.0 * 0.3)
    car = adversarial_loss([W1], lambda_obj=0.0, lambda_cls=1.0, class_id=0)
    assert car.total.item() == pytest.approx((0.9 + 0.0) / 2)


def test_gradient_is_lambda_over_count_on_obj_and_ped_only():
    x = torch.cat([W1, W2]).clone().requires_grad_(True)  # [B=2, A=2, 7]
    adversarial_loss(x, lambda_obj=3.0, lambda_cls=5.0).total.backward()
    expected = torch.zeros_like(x)
    expected[..., 4] = 3.0 / 4
    expected[..., 6] = 5.0 / 4
    assert torch.allclose(x.grad, expected)


def test_gradient_through_detector_like_head_decreases_loss():
    torch.manual_seed(0)
    texture_param = torch.zeros(8, requires_grad=True)
    head = torch.nn.Linear(8, 3 * 7)
    opt = torch.optim.Adam([texture_param], lr=0.1)
    losses = []
    for _ in range(5):
        decoded = torch.sigmoid(head(texture_param)).view(1, 3, 7)
        loss = adversarial_loss([decoded, decoded * 0.5]).total
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0]


def test_restrict_to_anchors_near_the_person_box():
    boxes = torch.tensor([[0.0, 0.0, 30.0, 40.0]])  # [B=1, 4], one box for every window
    keep = anchors_near_boxes(torch.stack([W1, W2]), boxes)
    assert keep.tolist() == [[[True, False]], [[True, False]]]
    out = adversarial_loss([W1, W2], boxes=boxes)
    assert out.num_anchors.item() == 2
    assert out.obj.item() == pytest.approx((0.5 + 0.3) / 2)
    assert out.cls.item() == pytest.approx((0.2 + 0.4) / 2)
    grown = adversarial_loss([W1, W2], boxes=boxes, box_margin_px=25.0)  # reaches (50, 60)
    assert grown.num_anchors.item() == 3
    per_window = torch.tensor([[[0.0, 0.0, 30.0, 40.0]], [[90.0, 90.0, 110.0, 110.0]]])  # [W, B, 4]
    out = adversarial_loss([W1, W2], boxes=per_window)
    assert out.obj.item() == pytest.approx((0.5 + 0.9) / 2)


def test_no_anchor_in_any_box_gives_zero_with_zero_gradient():
    x = W1.clone().requires_grad_(True)
    out = adversarial_loss([x], boxes=torch.tensor([[float("nan")] * 4]))
    assert out.total.item() == 0.0 and out.num_anchors.item() == 0
    out.total.backward()
    assert torch.equal(x.grad, torch.zeros_like(x))


def test_top_reduction_scores_the_most_confident_anchor_of_each_window():
    # W1: obj*ped = 0.10 (anchor 0) vs 0.06; W2: 0.12 vs 0.90 (anchor 1)
    out = adversarial_loss([W1, W2], reduction="top")
    assert out.obj.item() == pytest.approx((0.5 + 0.9) / 2)
    assert out.cls.item() == pytest.approx((0.2 + 1.0) / 2)
    assert out.total.item() == pytest.approx(1e4 * 0.7 + 1e4 * 0.6)
    assert out.num_anchors.item() == 2
    in_box = adversarial_loss([W1, W2], boxes=torch.tensor([[0.0, 0.0, 30.0, 40.0]]), reduction="top")
    assert (in_box.obj.item(), in_box.cls.item()) == pytest.approx(((0.5 + 0.3) / 2, (0.2 + 0.4) / 2))


def test_top_reduction_gradient_reaches_only_the_top_anchors():
    x = torch.stack([W1, W2]).clone().requires_grad_(True)  # [W=2, B=1, A=2, 7]
    adversarial_loss(x, lambda_obj=3.0, lambda_cls=5.0, reduction="top").total.backward()
    expected = torch.zeros_like(x)
    for window, anchor in ((0, 0), (1, 1)):
        expected[window, 0, anchor, 4] = 3.0 / 2
        expected[window, 0, anchor, 6] = 5.0 / 2
    assert torch.allclose(x.grad, expected)
    empty = W1.clone().requires_grad_(True)
    out = adversarial_loss([empty], boxes=torch.tensor([[float("nan")] * 4]), reduction="top")
    assert out.total.item() == 0.0 and out.num_anchors.item() == 0
    out.total.backward()
    assert torch.equal(empty.grad, torch.zeros_like(empty))
    with pytest.raises(ValueError, match="reduction"):
        adversarial_loss([W1], reduction="max")


def test_inputs_not_modified_and_validation():
    before = W1.clone()
    adversarial_loss([W1], boxes=[[0.0, 0.0, 30.0, 40.0]], box_margin_px=1.0)
    assert torch.equal(W1, before)
    with pytest.raises(ShapeError):
        adversarial_loss(torch.zeros(1, 3, 6))  # no pedestrian column
    with pytest.raises(ShapeError):
        adversarial_loss([W1, torch.zeros(1, 3, 7, dtype=torch.float64)])
    with pytest.raises(ShapeError):
        adversarial_loss([])
    with pytest.raises(ShapeError):
        adversarial_loss([W1], boxes=torch.zeros(3, 4))  # 3 boxes for 1 window x 1 batch
    with pytest.raises(ValueError):
        adversarial_loss([W1], boxes=torch.zeros(1, 4), box_margin_px=-1)


def test_anchor_cells_follow_the_heads_anchor_order():
    from davis_rig.attack.loss import anchor_cells
    from davis_rig.models.rvt.head import YOLOXHead

    strides, hw = (8, 16, 32), (256, 320)
    head = YOLOXHead(2, strides, (8, 16, 32))
    feats = [torch.zeros(1, 1, hw[0] // s, hw[1] // s) for s in strides]
    grids, stride = head.decode_grids(feats, torch.float32, torch.device("cpu"))
    cells = anchor_cells(hw, strides)
    assert cells.shape == (sum((hw[0] // s) * (hw[1] // s) for s in strides), 4)
    assert torch.equal(cells[:, :2], grids[0] * stride[0]) and torch.equal(cells[:, 2:] - cells[:, :2],
                                                                          stride[0].expand(-1, 2))


def test_anchors_on_boxes_keep_the_cells_the_person_overlaps():
    from davis_rig.attack.loss import anchors_on_boxes

    cells = torch.tensor([[0.0, 0, 8, 8], [8, 0, 16, 8], [0, 8, 8, 16], [0, 0, 32, 32]])
    boxes = torch.tensor([[[9.0, 1, 12, 7]], [[float("nan")] * 4]])  # [W=2, B=1, 4]
    keep = anchors_on_boxes(cells, boxes)
    assert keep.shape == (2, 1, 4)
    assert keep[0, 0].tolist() == [False, True, False, True] and not keep[1].any()
    touching = anchors_on_boxes(cells, torch.tensor([8.0, 8, 9, 9]))  # only edges/corners shared with cells 0-2
    assert touching.tolist() == [False, False, False, True]


def test_loss_on_person_anchors_scores_only_them():
    decoded = torch.rand(3, 2, 5, 7, generator=torch.Generator().manual_seed(0))  # [W, B, A, 7]
    mask = torch.zeros(3, 2, 5, dtype=torch.bool)
    mask[..., 1] = True
    mask[0, 0, 3] = True
    loss = adversarial_loss(decoded, 1.0, 1.0, anchor_mask=mask)
    assert int(loss.num_anchors) == int(mask.sum())
    assert loss.obj.item() == pytest.approx(decoded[..., 4][mask].mean().item())
    assert loss.cls.item() == pytest.approx(decoded[..., 6][mask].mean().item())
    top = adversarial_loss(decoded, 1.0, 1.0, anchor_mask=mask, reduction="top")
    assert int(top.num_anchors) == 6  # every window and clip has a kept anchor
    with pytest.raises(ShapeError):
        adversarial_loss(decoded, anchor_mask=mask[0])
