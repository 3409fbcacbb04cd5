"""Tests for the differentiable torch histogram: same binning as the official one, gradients w.r.t. weights."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from davis_rig.errors import FormatError, ShapeError  # noqa: E402
from davis_rig.events import stacked_histogram, window_indices  # noqa: E402
from davis_rig.events.histogram_torch import (  # noqa: E402
    StackedHistogramTorch,
    stacked_histogram_torch,
    stacked_histograms_torch,
    time_bins_torch,
)


def test_unweighted_counts_wrap_and_clip_to_the_official_histogram(reference_windows):
    ref = reference_windows
    t_all = ref["events_t_us"]
    for step, end_us in enumerate(ref["window_end_ts_us"].tolist()):
        start, stop = window_indices(t_all, end_us)
        cols = [torch.from_numpy(ref[f"events_{k}"][start:stop].astype(np.int64)) for k in ("x", "y", "t_us", "p")]
        counts = stacked_histogram_torch(*cols)
        assert counts.dtype == torch.float32
        assert counts.shape == (20, 240, 304)
        assert float(counts.sum()) == stop - start
        wrapped = (counts.to(torch.int64) % 256).clamp(max=10).to(torch.uint8).numpy()
        np.testing.assert_array_equal(wrapped, ref["hist_uint8_unpadded"][step])


def test_multi_window_version_matches_the_official_histograms(reference_windows):
    ref = reference_windows
    cols = [torch.from_numpy(ref[f"events_{k}"].astype(np.int64)) for k in ("x", "y", "t_us", "p")]
    weights = torch.ones(cols[0].shape[0], requires_grad=True)
    counts = stacked_histograms_torch(*cols, ref["window_end_ts_us"], weights)
    assert counts.shape == (3, 20, 240, 304)
    wrapped = (counts.detach().to(torch.int64) % 256).clamp(max=10).to(torch.uint8).numpy()
    np.testing.assert_array_equal(wrapped, ref["hist_uint8_unpadded"])
    counts.sum().backward()
    # events on a window boundary count in both windows -> gradient 2, others 1 or 0 (outside every window)
    t_all = ref["events_t_us"]
    in_windows = np.zeros(t_all.shape[0], np.int64)
    for end in ref["window_end_ts_us"].tolist():
        start, stop = window_indices(t_all, end)
        in_windows[start:stop] += 1
    np.testing.assert_array_equal(weights.grad.numpy(), in_windows.astype(np.float32))
    assert stacked_histograms_torch(*cols, []).shape == (0, 20, 240, 304)


def test_counts_are_not_wrapped_or_clipped():
    n = 260
    counts = stacked_histogram_torch(np.full(n, 3), np.full(n, 4), np.zeros(n, np.int64), np.ones(n, np.int64))
    assert float(counts[10, 4, 3]) == 260.0
    assert stacked_histogram(np.full(n, 3), np.full(n, 4), np.zeros(n, np.int64), np.ones(n, np.int64))[10, 4, 3] == 4


def test_weights_are_summed_per_cell_and_receive_gradients():
    x = torch.tensor([0, 0, 1])
    y = torch.tensor([0, 0, 1])
    t_us = torch.tensor([0, 0, 100])
    p = torch.tensor([1, 1, 0])
    w = torch.tensor([0.25, 0.5, 2.0], requires_grad=True)
    hist = stacked_histogram_torch(x, y, t_us, p, w, height=2, width=2, num_bins=2)
    assert hist.shape == (4, 2, 2)
    values = hist.detach()
    assert float(values[2, 0, 0]) == 0.75  # both ON events at t0 -> bin 0 of polarity 1
    assert float(values[1, 1, 1]) == 2.0  # last event -> bin 1 of polarity 0
    assert float(values.sum()) == 2.75
    (hist * torch.arange(16.0).reshape(4, 2, 2)).sum().backward()
    # flat indices: events 0/1 -> channel 2, (0,0) -> 8; event 2 -> channel 1, (1,1) -> 7
    assert w.grad.tolist() == [8.0, 8.0, 7.0]


def test_gradcheck_float64_weights():
    x = torch.tensor([0, 1, 1, 2, 0])
    y = torch.tensor([0, 0, 1, 1, 0])
    t_us = torch.tensor([0, 3, 5, 9, 9])
    p = torch.tensor([0, 1, 1, 0, 0])
    w = torch.rand(5, dtype=torch.float64, requires_grad=True)

    def fn(weights):
        return stacked_histogram_torch(x, y, t_us, p, weights, height=2, width=3, num_bins=3)

    assert torch.autograd.gradcheck(fn, (w,), eps=1e-6, atol=1e-8)
    assert fn(w).dtype == torch.float64


def test_time_bins_match_numpy_including_float32_rounding():
    from davis_rig.events import time_bins

    t_us = np.array([0, 8_388_608, 10_066_330, 16_777_217])
    np.testing.assert_array_equal(time_bins_torch(torch.from_numpy(t_us)).numpy(), time_bins(t_us))


def test_empty_window_keeps_the_graph():
    w = torch.zeros(0, requires_grad=True)
    hist = stacked_histogram_torch(torch.zeros(0, dtype=torch.int64), [], torch.zeros(0, dtype=torch.int64), [], w)
    assert hist.shape == (20, 240, 304)
    assert not hist.any()
    hist.sum().backward()
    assert w.grad.shape == (0,)


def test_transform_object_matches_function():
    transform = StackedHistogramTorch(height=3, width=4, num_bins=2)
    args = ([0, 3], [2, 1], [0, 10], [0, 1])
    torch.testing.assert_close(transform(*args), stacked_histogram_torch(*args, height=3, width=4, num_bins=2))
    assert "height=3" in repr(transform)


def test_validation_errors():
    with pytest.raises(ShapeError, match=r"weights: expected shape \(2,\)"):
        stacked_histogram_torch([0, 1], [0, 0], [0, 1], [0, 0], torch.ones(3))
    with pytest.raises(ShapeError, match="0 <= x < 304"):
        stacked_histogram_torch([304], [0], [0], [0])
    with pytest.raises(ShapeError, match=r"y: expected shape \(1,\)"):
        stacked_histogram_torch([0], [0, 1], [0], [0])
    with pytest.raises(FormatError, match="polarity"):
        stacked_histogram_torch([0], [0], [0], [2])
    with pytest.raises(FormatError, match="non-decreasing"):
        stacked_histogram_torch([0, 1], [0, 0], [5, 4], [0, 0])


def test_gradient_reaches_event_weights_through_the_detector(reference_windows):
    """Events -> float histogram -> mini RVT -> loss: d loss / d w_e equals d loss / d hist at the event's cell."""
    from pathlib import Path

    from davis_rig.models.rvt.checkpoint import load_detector
    from davis_rig.models.rvt.detector import pad_to_input

    mini_path = Path(__file__).resolve().parents[1] / "fixtures" / "rvt_mini_fixture.safetensors"
    model = load_detector(mini_path)
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    ref = reference_windows
    start, stop = window_indices(ref["events_t_us"], int(ref["window_end_ts_us"][0]))
    cols = [torch.from_numpy(ref[f"events_{k}"][start:stop].astype(np.int64)) for k in ("x", "y", "t_us", "p")]
    weights = torch.ones(stop - start, dtype=torch.float32, requires_grad=True)
    hist = stacked_histogram_torch(*cols, weights)
    hist_leaf = hist.detach().clone().requires_grad_(True)
    for source in (hist, hist_leaf):
        decoded, _ = model(pad_to_input(source[None]))
        (decoded[..., 4] * decoded[..., 5:].max(-1).values).sum().backward()
    x, y, t_us, p = cols
    channel = p * 10 + time_bins_torch(t_us)
    expected = hist_leaf.grad[channel, y, x]
    assert torch.count_nonzero(weights.grad) > 0
    torch.testing.assert_close(weights.grad, expected, rtol=1e-5, atol=1e-8)
