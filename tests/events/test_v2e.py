"""Tests of the differentiable V2E: hand-computed counts, equality with the exact simulator's histograms,
binning rules, the paper's floor formula vs the DVS model, the official relaxed mode, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from davis_rig.errors import FormatError, ShapeError
from davis_rig.events.histogram import stacked_histograms
from davis_rig.events.intensity import rgb_to_luma
from davis_rig.events.simulator import simulate_events
from davis_rig.events.v2e_torch import (
    OFFICIAL_RELAXED_SCALE,
    DifferentiableV2E,
    floor_ste,
    pair_bins,
    v2e_counts,
    v2e_histograms,
)


def moving_scene(t_frames: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    """A dark bar (sharp edges, 1 px per frame), a bright blob and a slow global drift over a random texture."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    background = 0.3 + 0.2 * rng.uniform(size=(height, width))
    frames = []
    for k in range(t_frames):
        cx, cy = 3 + 0.4 * k, height / 2 + 3 * math.sin(0.1 * k)
        blob = 0.55 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 8.0)
        drift = 1 + 0.15 * math.sin(0.07 * k)
        frame = background * drift + blob
        bar = (xx >= (k % (width + 4)) - 4) & (xx < (k % (width + 4))) & (yy < height - 3)
        frames.append(np.clip(np.where(bar, 0.03, frame), 0.01, 1.5))
    return np.stack(frames)


def ramp_video(t_frames: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    """Per-pixel monotonic log ramps (some up, some down, random speeds): no direction reversals."""
    rng = np.random.default_rng(seed)
    rate = rng.uniform(-0.08, 0.08, (1, height, width))
    base = rng.uniform(0.2, 0.6, (1, height, width))
    return base * np.exp(rate * np.arange(t_frames)[:, None, None])


def _counts_from_events(events, t_us, height, width):
    """Per-interval ON/OFF counts [T-1, H, W] of frame-end stamped events."""
    k = np.searchsorted(t_us, events["t"]) - 1
    on = np.zeros((len(t_us) - 1, height, width))
    off = np.zeros_like(on)
    np.add.at(on, (k[events["p"] == 1], events["y"][events["p"] == 1], events["x"][events["p"] == 1]), 1)
    np.add.at(off, (k[events["p"] == 0], events["y"][events["p"] == 0], events["x"][events["p"] == 0]), 1)
    return on, off


# ---------------------------------------------------------------------------------------------- hand-computed
def test_hand_computed_counts_dvs_and_floor_at_a_reversal():
    # log +0.3 then −0.2 (θ = 0.2, i.e. up 1.5 θ, down 1.0 θ): DVS 1 ON (reference +0.2), then 0.1 below it → no OFF;
    # the paper's grid S = ⌊Ŝ⌋: 0 → 1 → 0 → 1 ON and 1 OFF
    video = torch.tensor([0.5, 0.5 * math.exp(0.3), 0.5 * math.exp(0.1)], dtype=torch.float64).reshape(3, 1, 1)
    on, off = v2e_counts(video, mode="dvs")
    assert on.flatten().tolist() == [1.0, 0.0] and off.flatten().tolist() == [0.0, 0.0]
    on, off = v2e_counts(video, mode="floor")
    assert on.flatten().tolist() == [1.0, 0.0] and off.flatten().tolist() == [0.0, 1.0]


def test_hand_computed_official_relaxed_counts():
    video = torch.tensor([0.5, 0.5 * math.exp(0.3), 0.5 * math.exp(0.1)], dtype=torch.float64).reshape(3, 1, 1)
    on, off = v2e_counts(video, mode="official_relaxed")
    assert on.flatten().tolist() == pytest.approx([1.5 * 10 / 27, 0.0])
    assert off.flatten().tolist() == pytest.approx([0.0, 1.0 * 10 / 27])
    assert OFFICIAL_RELAXED_SCALE == pytest.approx(10 / math.floor(math.log(255) / 0.2))


def test_hand_computed_histogram_layout():
    # 200 fps, one window of 50 ms ending at 50 ms: pair k → bin k (interval binning); +0.45 in pair 3 → 2 ON
    logs = np.zeros(11)
    logs[4:] = 0.45
    logs[8:] = 0.0  # −0.45 from reference 0.4 → 2 OFF in pair 7
    video = torch.tensor(0.5 * np.exp(logs)).reshape(11, 1, 1)
    hist = v2e_histograms(video, np.arange(11) * 5000, 50_000, num_bins=10)
    assert hist.shape == (1, 20, 1, 1)
    expected = np.zeros(20)
    expected[10 + 3] = 2  # ON channel 10 + bin 3
    expected[7] = 2  # OFF channel bin 7
    assert hist.flatten().tolist() == expected.tolist()


# ---------------------------------------------------------------------------------------------- vs simulator
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_dvs_counts_equal_exact_simulator(dtype):
    video = moving_scene(40, 12, 20)
    t_us = np.arange(40) * 5000
    events = simulate_events(video, t_us, timestamps="frame_end", dtype=str(dtype).split(".")[1])
    on_sim, off_sim = _counts_from_events(events, t_us, 12, 20)
    on, off = v2e_counts(torch.tensor(video, dtype=dtype))
    assert on_sim.sum() > 200 and off_sim.sum() > 200
    assert np.array_equal(on.numpy(), on_sim) and np.array_equal(off.numpy(), off_sim)


@pytest.mark.parametrize("fps", [200, 240, 1000])
def test_rvt_frame_end_histograms_equal_official_histogram_of_exact_events(fps):
    height, width = 14, 24
    period_us = round(1e6 / fps)
    t_frames = int(160_000 / period_us) + 2
    video = moving_scene(t_frames, height, width, seed=fps)
    t_us = np.arange(t_frames) * period_us + 1234
    ends = np.array([51_234, 101_234, 151_234])
    events = simulate_events(video, t_us, timestamps="frame_end")
    official = stacked_histograms(events, ends, height=height, width=width)
    ours = v2e_histograms(torch.from_numpy(video), t_us, ends, binning="rvt_frame_end")
    assert official.max() == 10  # the count cut-off is exercised
    assert np.array_equal(ours.numpy(), official.astype(np.float64))


def test_interval_binning_equals_half_open_time_slices_of_interpolated_events():
    height, width = 10, 16
    t_frames = 41  # 200 fps: frame times on the 5 ms bin grid
    video = moving_scene(t_frames, height, width, seed=5)
    t_us = np.arange(t_frames) * 5000
    ends = np.array([50_000, 100_000, 150_000, 200_000])
    events = simulate_events(video, t_us)  # interpolated times
    ours = v2e_histograms(torch.from_numpy(video), t_us, ends, count_cutoff=None).numpy()
    for w, e in enumerate(ends):
        sel = (events["t"] > e - 50_000) & (events["t"] <= e)
        ev = events[sel]
        b = (ev["t"] - (e - 50_000) - 1) // 5000  # half-open-left 5 ms slices (e−50+5b, e−50+5(b+1)]
        ref = np.zeros((20, height, width))
        np.add.at(ref, (ev["p"].astype(int) * 10 + b, ev["y"], ev["x"]), 1)
        assert ref.sum() > 50
        assert np.array_equal(ours[w], ref)


def test_interval_binning_vs_official_rvt_bins_of_interpolated_events():
    """RVT's first/last-event bins of interpolated events differ only by events moving to a neighbouring bin."""
    height, width = 10, 16
    t_frames = 41
    video = moving_scene(t_frames, height, width, seed=6)
    t_us = np.arange(t_frames) * 5000
    ends = np.array([100_000, 150_000, 200_000])
    events = simulate_events(video, t_us)
    # exclude events exactly on the window start (RVT counts them in both windows)
    official = stacked_histograms(events[events["t"] % 50_000 != 0], ends, height=height, width=width,
                                  count_cutoff=255).astype(np.int64)
    ours = v2e_histograms(torch.from_numpy(video), t_us, ends, count_cutoff=None).numpy().astype(np.int64)
    for p in (0, 1):
        a, b = official[:, p * 10:(p + 1) * 10], ours[:, p * 10:(p + 1) * 10]
        assert np.array_equal(a.sum(1), b.sum(1))  # per-pixel totals identical
        # cumulative counts over bins differ by at most the events of one pair (spill into the next bin)
        max_pair = b.max()
        assert np.abs(np.cumsum(a, 1) - np.cumsum(b, 1)).max() <= max_pair


def test_floor_formula_vs_dvs_on_monotonic_signals():
    """The paper's S = ⌊Ŝ⌋ equals the DVS for brightening pixels; for darkening ones its OFF levels are L_0 − nθ for
    n = 0, 1, ... (⌊·⌋ jumps as soon as Ŝ < 0), one θ earlier than the DVS: one extra OFF per darkening pixel."""
    video = torch.from_numpy(ramp_video(50, 8, 9, seed=2))
    on_dvs, off_dvs = v2e_counts(video, mode="dvs")
    on_floor, off_floor = v2e_counts(video, mode="floor")
    assert on_dvs.sum() > 50 and off_dvs.sum() > 50
    assert torch.equal(on_dvs, on_floor)
    darkening = (video[-1] < video[0]).to(torch.float64)
    assert torch.equal(off_floor.sum(0), off_dvs.sum(0) + darkening)


def test_rgb_input_and_callable_transform():
    rng = np.random.default_rng(1)
    rgb = torch.tensor(rng.uniform(0.1, 0.9, (11, 3, 4, 5)))
    luma = rgb_to_luma(rgb)
    assert torch.allclose(luma, 0.299 * rgb[:, 0] + 0.587 * rgb[:, 1] + 0.114 * rgb[:, 2])
    t_us = np.arange(11) * 5000
    v2e = DifferentiableV2E()
    assert torch.equal(v2e(rgb, t_us, 50_000), v2e_histograms(luma, t_us, 50_000))
    assert "mode='dvs'" in repr(v2e)


def test_pair_bins_rules():
    t_us = np.arange(12) * 5000  # pairs end at 5, 10, ..., 55 ms
    w, b, k = pair_bins(t_us, [50_000], binning="interval")
    assert k.tolist() == list(range(10)) and b.tolist() == list(range(10)) and set(w.tolist()) == {0}
    # RVT rule on end times: [0, 50] ms inclusive → pairs ending 5..50 ms, t0 = 5 ms, t1 = 50 ms
    w, b, k = pair_bins(t_us, [50_000], binning="rvt_frame_end")
    assert k.tolist() == list(range(10))
    assert b.tolist() == [min(int(np.float32(5000 * j) / np.float32(45000) * 10), 9) for j in range(10)]
    # a window ending at 55 ms includes the pair ending at its start (5 ms) under the RVT rule only
    assert pair_bins(t_us, [55_000], binning="rvt_frame_end")[2].tolist() == list(range(11))
    assert pair_bins(t_us, [55_000], binning="interval")[2].tolist() == list(range(1, 11))
    # t0/t1 from the firing pairs only
    fired = np.zeros(11, dtype=bool)
    fired[[3, 7]] = True
    _, b, k = pair_bins(t_us, [55_000], fired=fired, binning="rvt_frame_end")
    assert b[k == 3].tolist() == [0] and b[k == 7].tolist() == [9]


# ---------------------------------------------------------------------------------------------- gradients
def test_floor_ste_forward_exact_backward_identity():
    x = torch.tensor([-1.5, -0.2, 0.0, 0.7, 2.0, 3.999], requires_grad=True)
    y = floor_ste(x)
    assert torch.equal(y, torch.floor(x.detach()))
    y.backward(torch.arange(6.0))
    assert x.grad.tolist() == list(np.arange(6.0))


def test_dvs_gradient_follows_the_straight_through_surrogate():
    # one pixel fires 2 ON events in pair 0 (log +0.45), another stays below θ (log +0.1): with the surrogate,
    # dN⁺/dI_1 = d(L_1/θ)/dI_1 = 1 / (θ I_1) in the log region; the sub-threshold pixel gets no gradient (relu)
    i0, i1 = 0.5, 0.5 * math.exp(0.45)
    video = torch.tensor([[[i0, i0]], [[i1, i0 * math.exp(0.1)]]], dtype=torch.float64, requires_grad=True)
    on, off = v2e_counts(video)
    assert on[0, 0].tolist() == [2.0, 0.0]
    on.sum().backward()
    grad = video.grad
    assert grad[1, 0, 0].item() == pytest.approx(1 / (0.2 * i1))
    assert grad[0, 0, 0].item() == pytest.approx(-1 / (0.2 * i0))
    assert grad[:, 0, 1].abs().sum().item() == 0.0


@pytest.mark.parametrize("per_pixel", [False, True])
def test_fused_dvs_equals_the_unrolled_autograd_graph(per_pixel):
    from davis_rig.events.v2e_torch import _dvs_counts_unrolled, log_intensity

    video = torch.tensor(moving_scene(25, 9, 14, seed=3), requires_grad=True)
    rng = np.random.default_rng(0)
    theta_on = torch.tensor(rng.uniform(0.15, 0.25, (9, 14))) if per_pixel else 0.2
    theta_off = torch.tensor(rng.uniform(0.15, 0.25, (9, 14))) if per_pixel else 0.2
    w_on, w_off = torch.rand(2, 24, 9, 14, dtype=torch.float64)
    on, off = v2e_counts(video, threshold_on=theta_on, threshold_off=theta_off)
    ((on * w_on).sum() + (off * w_off).sum()).backward()
    fused = video.grad.clone()
    video.grad = None
    on_ref, off_ref = _dvs_counts_unrolled(log_intensity(video, lin_log_threshold=20.0), theta_on, theta_off)
    ((on_ref * w_on).sum() + (off_ref * w_off).sum()).backward()
    assert torch.equal(on, on_ref) and torch.equal(off, off_ref) and on.sum() > 100
    assert torch.allclose(fused, video.grad, rtol=1e-12, atol=1e-12) and fused.abs().sum() > 0


def test_fused_lin_log_equals_autograd_of_lin_log():
    from davis_rig.events.intensity import lin_log
    from davis_rig.events.v2e_torch import log_intensity

    x = torch.tensor([[[0.0, 0.01, 20 / 255, 0.2]], [[0.5, 0.9, 1.0, 1.3]]], dtype=torch.float64, requires_grad=True)
    y = log_intensity(x, lin_log_threshold=20.0)
    assert torch.equal(y, lin_log(x.detach() * 255.0))
    y.backward(torch.arange(8.0, dtype=torch.float64).reshape(2, 1, 4))
    fused = x.grad.clone()
    x.grad = None
    lin_log(x * 255.0).backward(torch.arange(8.0, dtype=torch.float64).reshape(2, 1, 4))
    assert torch.allclose(fused, x.grad, rtol=1e-14, atol=0)


def test_gradients_reach_the_video_through_the_histogram():
    video = torch.tensor(moving_scene(11, 6, 8), requires_grad=True)
    hist = v2e_histograms(video, np.arange(11) * 5000, 50_000, count_cutoff=None)
    (hist * torch.arange(20.0, dtype=torch.float64)[None, :, None, None]).sum().backward()
    assert torch.isfinite(video.grad).all() and video.grad.abs().sum() > 0


def test_gradcheck_smooth_parts_float64():
    # lin-log + luma + the relaxed (no floor) counts + binning are smooth away from relu kinks
    rng = np.random.default_rng(0)
    base = rng.uniform(0.05, 0.9, (1, 3, 2, 3))
    steps = np.cumprod(np.exp(rng.choice([-0.3, 0.3], (6, 1, 2, 3))), axis=0)
    rgb = torch.tensor(base * steps[:, None, 0].repeat(3, 1), dtype=torch.float64, requires_grad=True)

    def fn(video):
        return v2e_histograms(video, np.arange(6) * 10_000, 50_000, mode="official_relaxed", count_cutoff=None)

    assert torch.autograd.gradcheck(fn, (rgb,), eps=1e-6, atol=1e-6)


def test_count_cutoff_clamps():
    logs = np.zeros(11)
    logs[5:] = 3.0  # 15 ON events in one pair
    video = torch.tensor(0.1 * np.exp(logs)).reshape(11, 1, 1)
    assert v2e_histograms(video, np.arange(11) * 5000, 50_000).max().item() == 10.0
    assert v2e_histograms(video, np.arange(11) * 5000, 50_000, count_cutoff=None).max().item() == 15.0


# ---------------------------------------------------------------------------------------------- validation
def test_validation_errors():
    video = torch.rand(5, 2, 2, dtype=torch.float64)
    with pytest.raises(ValueError):
        v2e_counts(video, mode="bogus")
    with pytest.raises(ValueError):
        v2e_counts(video, mode="floor", threshold_on=0.2, threshold_off=0.3)
    with pytest.raises(ShapeError):
        v2e_counts(video[:1])
    with pytest.raises(ShapeError):
        v2e_counts(torch.rand(5, 2, 2, 2))
    with pytest.raises(FormatError):
        v2e_counts(torch.zeros(5, 2, 2, dtype=torch.int64))
    with pytest.raises(ShapeError):
        v2e_histograms(video, np.arange(4) * 5000, 20_000)
    with pytest.raises(FormatError):
        pair_bins(np.array([0, 5, 5]), 10)
    with pytest.raises(ValueError):
        pair_bins(np.arange(3), 10, binning="bogus")
    with pytest.raises(ValueError):
        DifferentiableV2E(mode="relaxed")


# ---------------------------------------------------------------------------------------------- properties
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    period_us=st.sampled_from([1000, 2500, 4167, 5000]),
    t_frames=st.integers(3, 40),
    step=st.floats(0.05, 1.5),
    t0_us=st.integers(0, 100_000),
)
def test_property_v2e_equals_exact_simulator_histograms(seed, period_us, t_frames, step, t0_us):
    """For any video (random-walk log intensities, dark and bright): V2E "rvt_frame_end" == official histogram of
    the frame-end stamped exact events, and V2E "interval" == half-open 5 ms slices of the interpolated events
    when the frame times lie on the bin grid."""
    rng = np.random.default_rng(seed)
    logs = np.cumsum(rng.normal(0.0, step, (t_frames, 3, 4)), axis=0)
    video = np.clip(0.3 * np.exp(logs), 0.0, 2.0)
    t_us = t0_us + np.arange(t_frames, dtype=np.int64) * period_us
    ends = np.array([t_us[-1], t_us[-1] - 20_000])
    events = simulate_events(video, t_us, timestamps="frame_end")
    official = stacked_histograms(events, ends, height=3, width=4)
    ours = v2e_histograms(torch.from_numpy(video), t_us, ends, binning="rvt_frame_end")
    assert np.array_equal(ours.numpy(), official.astype(np.float64))
    if period_us in (1000, 2500, 5000):
        events = simulate_events(video, t_us)
        ours = v2e_histograms(torch.from_numpy(video), t_us, ends, count_cutoff=None).numpy()
        for w, e in enumerate(ends.tolist()):
            ev = events[(events["t"] > e - 50_000) & (events["t"] <= e)]
            b = (ev["t"] - (e - 50_000) - 1) // 5000
            ref = np.zeros((20, 3, 4))
            np.add.at(ref, (ev["p"].astype(int) * 10 + b, ev["y"], ev["x"]), 1)
            assert np.array_equal(ours[w], ref)


@pytest.mark.gpu
def test_cuda_v2e_matches_cpu():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    video = torch.tensor(moving_scene(11, 24, 30), dtype=torch.float32)
    t_us = np.arange(11) * 5000
    cpu = v2e_histograms(video, t_us, 50_000)
    gpu = v2e_histograms(video.cuda(), t_us, 50_000)
    assert torch.equal(cpu, gpu.cpu())
