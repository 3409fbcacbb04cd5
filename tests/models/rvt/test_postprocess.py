"""Tests for the numpy RVT post-processing: exact vs the official outputs, hand-made NMS cases, both CPU paths."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import ShapeError
from davis_rig.models.rvt.postprocess import (
    batched_nms,
    nms,
    postprocess,
    postprocess_thresholds,
    torch_cpu_unstable_argsort_desc,
)

THRESHOLDS = {"0p001": 0.001, "0p1": 0.1, "0p25": 0.25}


def _check_fixture(fx):
    for step in range(fx.num_steps):
        decoded = fx[f"step{step}.head.decoded"]
        before = decoded.copy()
        for name, conf in THRESHOLDS.items():
            expected = fx[f"step{step}.post.conf{name}"]
            (got,) = postprocess(decoded, conf_threshold=conf, nms_threshold=0.45)
            if expected.shape[0] == 0:
                assert got is None, f"step{step} conf {conf}: expected no detections, got {got.shape}"
            else:
                assert got is not None and got.dtype == np.float32
                np.testing.assert_array_equal(got, expected, err_msg=f"step{step} conf {conf}")
        np.testing.assert_array_equal(decoded, before)  # the input is not modified


def test_thresholds_at_once_match_official_postprocess_rvt_t(rvt_t_fixture):
    for step in range(rvt_t_fixture.num_steps):
        got = postprocess_thresholds(rvt_t_fixture[f"step{step}.head.decoded"], THRESHOLDS.values(), 0.45)
        assert sorted(got) == sorted(THRESHOLDS.values())
        for name, conf in THRESHOLDS.items():
            expected = rvt_t_fixture[f"step{step}.post.conf{name}"]
            if expected.shape[0] == 0:
                assert got[conf][0] is None
            else:
                np.testing.assert_array_equal(got[conf][0], expected, err_msg=f"step{step} conf {conf}")


def test_matches_official_postprocess_mini(mini_fixture):
    _check_fixture(mini_fixture)


def test_matches_official_postprocess_rvt_t(rvt_t_fixture):
    # at 0.001 the RVT-T steps have > 1000 candidates (torchvision's per-class loop), at 0.1/0.25 the offset path
    _check_fixture(rvt_t_fixture)


def test_torch_tensor_input_and_batch(mini_fixture):
    torch = pytest.importorskip("torch")
    batch = np.concatenate([mini_fixture[f"step{s}.head.decoded"] for s in range(3)])
    out = postprocess(torch.from_numpy(batch.copy()), conf_threshold=0.1)
    assert len(out) == 3
    for step in range(3):
        np.testing.assert_array_equal(out[step], mini_fixture[f"step{step}.post.conf0p1"])


# --- hand-made cases -------------------------------------------------------------------------------------------
def _det(cx, cy, w, h, obj, p_car, p_ped):
    return [cx, cy, w, h, obj, p_car, p_ped]


def test_corner_conversion_and_row_layout():
    (out,) = postprocess(np.array([[_det(50, 40, 20, 10, 0.8, 0.25, 0.5)]], np.float32), conf_threshold=0.1)
    np.testing.assert_array_equal(out, np.array([[40, 35, 60, 45, 0.8, 0.5, 1.0]], np.float32))


def test_confidence_threshold_is_inclusive():
    decoded = np.array([[_det(10, 10, 4, 4, 0.5, 0.5, 0.0), _det(100, 100, 4, 4, 0.5, 0.25, 0.0)]], np.float32)
    (out,) = postprocess(decoded, conf_threshold=0.25)
    assert out.shape == (1, 7)  # 0.5 * 0.5 == 0.25 kept, 0.125 dropped
    assert postprocess(decoded, conf_threshold=0.26) == [None]


def test_iou_exactly_at_threshold_is_not_suppressed_and_above_is():
    # A = [0,0,20,10] (area 200); B = [0,0,9,10] (area 90, inside A): IoU = 90 / 200 = 0.45 -> both kept
    boxes = np.array([[0, 0, 20, 10], [0, 0, 9, 10]], np.float32)
    scores = np.array([0.9, 0.8], np.float32)
    np.testing.assert_array_equal(nms(boxes, scores, 0.45), [0, 1])
    # B = [0,0,9.5,10]: IoU = 95 / 200 = 0.475 > 0.45 -> B suppressed
    boxes[1, 2] = 9.5
    np.testing.assert_array_equal(nms(boxes, scores, 0.45), [0])


def test_nms_keeps_the_lower_index_on_score_ties():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60]], np.float32)
    scores = np.array([0.5, 0.5, 0.7], np.float32)
    np.testing.assert_array_equal(nms(boxes, scores, 0.45), [2, 0])
    np.testing.assert_array_equal(nms(boxes[[1, 0, 2]], scores, 0.45), [2, 0])


def test_nms_is_class_wise():
    # two identical boxes: same class -> one survives; different classes -> both survive
    same = np.array([[_det(50, 50, 20, 20, 0.9, 0.1, 0.8), _det(50, 50, 20, 20, 0.9, 0.2, 0.7)]], np.float32)
    (out,) = postprocess(same, conf_threshold=0.1)
    np.testing.assert_array_equal(out[:, 6], [1.0])
    np.testing.assert_allclose(out[:, 5], [0.8])
    diff = np.array([[_det(50, 50, 20, 20, 0.9, 0.1, 0.8), _det(50, 50, 20, 20, 0.9, 0.7, 0.2)]], np.float32)
    (out,) = postprocess(diff, conf_threshold=0.1)
    np.testing.assert_array_equal(out[:, 6], [1.0, 0.0])  # ordered by decreasing obj * class_conf


def test_empty_and_shape_errors():
    assert postprocess(np.zeros((2, 5, 7), np.float32), conf_threshold=0.1) == [None, None]
    with pytest.raises(ShapeError, match=r"expected \[B, A, 5 \+ num_classes\], got \(5, 7\)"):
        postprocess(np.zeros((5, 7), np.float32), conf_threshold=0.1)
    with pytest.raises(ShapeError, match="nms: expected boxes"):
        nms(np.zeros((3, 3)), np.zeros(3), 0.5)
    with pytest.raises(ShapeError, match="batched_nms"):
        batched_nms(np.zeros((3, 4)), np.zeros(3), np.zeros(2), 0.5)
    with pytest.raises(ValueError, match="path"):
        batched_nms(np.zeros((3, 4)), np.zeros(3), np.zeros(3), 0.5, path="gpu")


def _random_boxes(rng, n, classes=2):
    xy = rng.uniform(0, 300, size=(n, 2)).astype(np.float32)
    wh = rng.uniform(5, 80, size=(n, 2)).astype(np.float32)
    boxes = np.concatenate([xy, xy + wh], axis=1)
    scores = rng.uniform(0, 1, size=n).astype(np.float32)
    idxs = rng.integers(0, classes, size=n).astype(np.float32)
    return boxes, scores, idxs


def test_both_batched_nms_paths_agree_without_ties():
    rng = np.random.default_rng(7)
    for n in (5, 200, 1200):
        boxes, scores, idxs = _random_boxes(rng, n)
        per_class = batched_nms(boxes, scores, idxs, 0.45, path="per_class")
        offset = batched_nms(boxes, scores, idxs, 0.45, path="offset")
        np.testing.assert_array_equal(per_class, offset)
        np.testing.assert_array_equal(batched_nms(boxes, scores, idxs, 0.45), per_class)


# --- against transcriptions of torchvision's code run in torch -----------------------------------------------------
def _torch_nms(torch, boxes, scores, iou_threshold):
    """Greedy NMS transcribed from torchvision's ``nms_kernel.cpp`` (float32 tensor arithmetic)."""
    x1, y1, x2, y2 = boxes.unbind(1)
    areas = (x2 - x1) * (y2 - y1)
    order = scores.sort(stable=True, dim=0, descending=True)[1]
    suppressed = torch.zeros(len(scores), dtype=torch.bool)
    keep = []
    for i in order.tolist():
        if suppressed[i]:
            continue
        keep.append(i)
        xx1 = torch.maximum(x1[i], x1)
        yy1 = torch.maximum(y1[i], y1)
        xx2 = torch.minimum(x2[i], x2)
        yy2 = torch.minimum(y2[i], y2)
        inter = (xx2 - xx1).clamp(min=0) * (yy2 - yy1).clamp(min=0)
        ovr = inter / (areas[i] + areas - inter)
        suppressed |= ovr.double() > iou_threshold
    return torch.tensor(keep, dtype=torch.int64)


def _torch_batched_nms(torch, boxes, scores, idxs, iou_threshold):
    """``torchvision.ops.boxes.batched_nms`` (CPU dispatch), transcribed."""
    if boxes.numel() > 4000:
        keep_mask = torch.zeros_like(scores, dtype=torch.bool)
        for class_id in torch.unique(idxs):
            curr = torch.where(idxs == class_id)[0]
            keep_mask[curr[_torch_nms(torch, boxes[curr], scores[curr], iou_threshold)]] = True
        keep = torch.where(keep_mask)[0]
        return keep[scores[keep].sort(descending=True)[1]]
    max_coordinate = boxes.max()
    offsets = idxs.to(boxes) * (max_coordinate + torch.tensor(1).to(boxes))
    return _torch_nms(torch, boxes + offsets[:, None], scores, iou_threshold)


@pytest.mark.parametrize("n", [3, 60, 1001, 1300])
def test_batched_nms_matches_torch_transcription_with_ties(n):
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(n)
    boxes, scores, idxs = _random_boxes(rng, n, classes=3)
    scores = np.round(scores * 8).astype(np.float32) / 8  # many exact score ties
    expected = _torch_batched_nms(torch, *(torch.from_numpy(a) for a in (boxes, scores, idxs)), 0.45).numpy()
    np.testing.assert_array_equal(batched_nms(boxes, scores, idxs, 0.45), expected)


def test_unstable_sort_emulation_matches_torch():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(3)
    for trial in range(300):
        n = int(rng.integers(1, 40 if trial % 2 else 3000))
        values = rng.integers(0, int(rng.integers(1, 30)), n).astype(np.float32)
        if trial % 5 == 0:
            values[rng.integers(0, n, 2)] = np.nan
        expected = torch.from_numpy(values).sort(descending=True)[1].numpy()
        np.testing.assert_array_equal(torch_cpu_unstable_argsort_desc(values), expected, err_msg=f"trial {trial}")


def test_degenerate_and_duplicate_boxes_match_torch_transcription():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(11)
    boxes, scores, idxs = _random_boxes(rng, 400, classes=2)
    boxes[:40, 2] = boxes[:40, 0]  # zero width
    boxes[40:80, [0, 2]] = boxes[40:80, [2, 0]]  # inverted x (negative width)
    boxes[80:120] = boxes[120:160]  # exact duplicates
    scores[80:100] = scores[120:140]  # ... some with the same score
    for path_boxes in (boxes, boxes * np.float32(37.3)):  # large coordinates: offsets change the rounding
        expected = _torch_batched_nms(torch, *(torch.from_numpy(a) for a in (path_boxes, scores, idxs)), 0.45)
        np.testing.assert_array_equal(batched_nms(path_boxes, scores, idxs, 0.45), expected.numpy())


def _mcilroy_adversary(n: int) -> np.ndarray:
    """McIlroy's "killer adversary" against libstdc++'s median-of-3 introsort (drives it to the heap sort).

    The sort's keys are objects whose ``>`` (the only comparison the emulation makes) freezes "gas" values
    lazily, so the sort itself builds its worst-case input.
    """
    from davis_rig.models.rvt.postprocess import _libstdcxx_sort_keys

    gas = n
    values = [gas] * n
    state = {"solid": 0, "candidate": 0}

    class _Key:
        def __init__(self, index: int) -> None:
            self.index = index

        def __gt__(self, other: "_Key") -> bool:  # "self goes before other"
            a, b = self.index, other.index
            if values[a] == gas and values[b] == gas:
                frozen = a if a == state["candidate"] else b
                values[frozen] = state["solid"]
                state["solid"] += 1
            if values[a] == gas:
                state["candidate"] = a
            elif values[b] == gas:
                state["candidate"] = b
            return values[a] < values[b]

    _libstdcxx_sort_keys([_Key(i) for i in range(n)])
    return -np.asarray(values, dtype=np.float32)


@pytest.mark.parametrize("n", [1000, 3000])
def test_unstable_sort_emulation_matches_torch_past_the_depth_limit(n):
    # Quantized adversarial inputs: many ties, and deep enough recursion to reach libstdc++'s heap-sort fallback
    # (checked while writing this test by instrumenting the emulation).
    torch = pytest.importorskip("torch")
    values = -np.floor(-_mcilroy_adversary(n) / 3).astype(np.float32)
    expected = torch.from_numpy(values).sort(descending=True)[1].numpy()
    got = torch_cpu_unstable_argsort_desc(values)
    np.testing.assert_array_equal(got, expected)
    assert not np.array_equal(got, np.argsort(-values, kind="stable"))  # ties really are reordered


def test_candidate_sweep_and_dense_blocks_give_the_same_nms(monkeypatch):
    import davis_rig.models.rvt.postprocess as postprocess_module

    rng = np.random.default_rng(5)
    cases = []
    for trial in range(60):
        n = int(rng.integers(1, 400))
        boxes, scores, idxs = _random_boxes(rng, n)
        boxes[rng.integers(0, n, 2), 2] -= 60  # some inverted boxes
        if trial % 3 == 0:
            boxes = np.round(boxes / 10) * 10  # touching edges, duplicates
            scores = np.round(scores * 4) / 4
        if trial % 5 == 0:
            boxes[rng.integers(0, n, 2), rng.integers(0, 4, 2)] = np.nan
        cases.append((boxes, scores, idxs))
    sweep = [batched_nms(b, s, c, 0.45) for b, s, c in cases]
    monkeypatch.setattr(postprocess_module, "_MAX_SWEEP_PAIRS", 0)  # force the dense block comparisons
    for (b, s, c), expected in zip(cases, sweep):
        np.testing.assert_array_equal(batched_nms(b, s, c, 0.45), expected)


# --- several thresholds at once ----------------------------------------------------------------------------------
def _postprocess_reference(pred, threshold, nms_threshold=0.45):
    """One image, one threshold: confidence filter, then :func:`batched_nms` (checked against torch above)."""
    class_pred = np.argmax(pred[:, 5:], axis=1)
    class_conf = pred[np.arange(len(pred)), 5 + class_pred]
    keep = pred[:, 4] * class_conf >= np.float32(threshold)
    if not keep.any():
        return None
    half_w, half_h = pred[:, 2] / np.float32(2), pred[:, 3] / np.float32(2)
    rows = np.stack([pred[:, 0] - half_w, pred[:, 1] - half_h, pred[:, 0] + half_w, pred[:, 1] + half_h,
                     pred[:, 4], class_conf, class_pred.astype(np.float32)], axis=1)[keep]
    return rows[batched_nms(rows[:, :4], rows[:, 4] * rows[:, 5], rows[:, 6], nms_threshold)]


def _decoded(rng, anchors, levels):
    """Random decoded output [1, A, 7] with scores quantized to ``levels`` values (many exact ties)."""
    cxcy = rng.uniform(0, 320, (anchors, 2))
    wh = rng.uniform(4, 90, (anchors, 2))
    obj = np.round(rng.uniform(0, 1, anchors) * levels) / levels
    probs = rng.uniform(0, 1, (anchors, 2))
    return np.concatenate([cxcy, wh, obj[:, None], probs], axis=1)[None].astype(np.float32)


@pytest.mark.parametrize("anchors, levels", [(1680, 8), (1680, 1000), (2600, 5), (300, 3), (50, 1000)])
def test_postprocess_thresholds_equals_one_call_per_threshold(anchors, levels):
    # thresholds whose candidate counts fall on both sides of torchvision's 1000-box path switch, equal counts,
    # and sets whose largest coordinate (the offset path's class offset) changes or stays between thresholds
    rng = np.random.default_rng(anchors + levels)
    thresholds = (0.001, 0.01, 0.1, 0.2, 0.25, 0.3, 0.45, 0.6, 0.9, 1.0)
    for trial in range(3):
        decoded = _decoded(rng, anchors, levels)
        if trial == 1:
            decoded[0, 0, :4] = (400, 400, 30, 30)  # the largest coordinate on a high-score box ...
            decoded[0, 0, 4:6] = 1.0
        if trial == 2:
            decoded[0, 0, 4] = 0.02  # ... and on a low-score one
        got = postprocess_thresholds(decoded, thresholds[::-1] + (0.1,))
        assert sorted(got) == sorted(thresholds)
        for threshold in thresholds:
            expected = _postprocess_reference(decoded[0], threshold)
            if expected is None:
                assert got[threshold] == [None]
            else:
                np.testing.assert_array_equal(got[threshold][0], expected, err_msg=f"threshold {threshold}")
                np.testing.assert_array_equal(postprocess(decoded, threshold)[0], expected)


def test_postprocess_thresholds_batch_and_errors():
    rng = np.random.default_rng(1)
    decoded = np.concatenate([_decoded(rng, 200, 10), _decoded(rng, 200, 10)])
    got = postprocess_thresholds(decoded, [0.1, 0.5])
    for image in range(2):
        for threshold in (0.1, 0.5):
            np.testing.assert_array_equal(got[threshold][image], _postprocess_reference(decoded[image], threshold))
    with pytest.raises(ValueError, match="at least one"):
        postprocess_thresholds(decoded, [])
    with pytest.raises(ShapeError, match="expected"):
        postprocess_thresholds(decoded[0], [0.1])
