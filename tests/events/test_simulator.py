"""Tests of the exact DVS simulator: hand-computed counts and times, an independent per-pixel reference
simulator on slowly drifting videos, streaming, non-idealities (seeded), validation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from davis_rig.errors import ConfigError, FormatError, ShapeError
from davis_rig.events.intensity import lin_log
from davis_rig.events.simulator import EventSimulator, SimulatorConfig, simulate_events
from davis_rig.types import EVENT_DTYPE

LN20_OVER_20 = math.log(20.0) / 20.0


def drifting_video(t_frames: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    """Slowly drifting smooth intensities in [0.02, 0.98]: a sum of per-pixel sines (linear intensity, float64)."""
    rng = np.random.default_rng(seed)
    t = np.arange(t_frames)[:, None, None]
    base = rng.uniform(0.2, 0.6, (1, height, width))
    amp = rng.uniform(0.05, 0.35, (1, height, width))
    freq = rng.uniform(0.02, 0.15, (1, height, width))
    phase = rng.uniform(0, 2 * np.pi, (1, height, width))
    video = base + amp * np.sin(freq * t + phase) + 0.1 * np.sin(0.05 * t + phase)
    return np.clip(video, 0.02, 0.98)


def reference_simulator(video: np.ndarray, t_us: np.ndarray, theta_on: float, theta_off: float) -> np.ndarray:
    """Independent ideal DVS: per-pixel Python loop, one crossing at a time (test only; tiny videos)."""

    def log_of(v: float) -> float:
        x = 255.0 * v
        return x * LN20_OVER_20 if x <= 20.0 else math.log(x)

    rows = []
    t_frames, height, width = video.shape
    for y in range(height):
        for x in range(width):
            ref = log_of(video[0, y, x])
            prev = ref
            for k in range(1, t_frames):
                cur = log_of(video[k, y, x])
                dt = int(t_us[k] - t_us[k - 1])
                while cur - ref >= theta_on:
                    ref += theta_on
                    frac = (ref - prev) / (cur - prev)
                    rows.append((int(t_us[k - 1]) + max(1, min(dt, math.ceil(frac * dt))), x, y, 1))
                while ref - cur >= theta_off:
                    ref -= theta_off
                    frac = (ref - prev) / (cur - prev)
                    rows.append((int(t_us[k - 1]) + max(1, min(dt, math.ceil(frac * dt))), x, y, 0))
                prev = cur
    out = np.array(rows, dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    return out


def _by_pixel(events: np.ndarray) -> np.ndarray:
    return events[np.lexsort((events["t"], events["p"], events["x"], events["y"]))]


# ---------------------------------------------------------------------------------------------- hand-computed
def test_single_pixel_step_hand_computed_counts_and_times():
    # log change +0.45 over 1000 µs: crossings at 0.2 and 0.4 → fractions 4/9, 8/9 → ceil(444.4), ceil(888.9)
    video = np.array([0.5, 0.5 * math.exp(0.45)]).reshape(2, 1, 1)
    ev = simulate_events(video, np.array([0, 1000]))
    assert ev.dtype == EVENT_DTYPE
    assert ev["t"].tolist() == [445, 889]
    assert ev["p"].tolist() == [1, 1]
    assert ev["x"].tolist() == [0, 0] and ev["y"].tolist() == [0, 0]


def test_hysteresis_reference_keeps_the_remainder():
    # up 2.5 θ: 2 ON, reference +0.4; down to −0.1: 0.5 below the reference → 2 OFF; back to +0.25: 0.35 above
    # the reference (−0.0) → 1 ON
    logs = [0.0, 0.5, -0.1, 0.25]
    video = (0.5 * np.exp(np.array(logs))).reshape(4, 1, 1)
    ev = simulate_events(video, np.array([0, 5000, 10000, 15000]))
    assert ev["p"].tolist() == [1, 1, 0, 0, 1]
    # the OFF crossings (levels 0.2 then 0.0, from 0.5 down to −0.1) at fractions 0.3/0.6 and 0.5/0.6
    assert ev["t"].tolist()[2:4] == [5000 + 2500, 5000 + math.ceil(5000 * 5 / 6)]


def test_dark_pixels_use_the_linear_part_of_lin_log():
    # 0.02 → 0.06 is 5.1 → 15.3 DN, below the knee (20): ΔL = 10.2 · ln(20)/20 = 1.5278 → 7 ON events
    video = np.array([0.02, 0.06]).reshape(2, 1, 1)
    ev = simulate_events(video, np.array([0, 5000]))
    assert len(ev) == 7 and set(ev["p"].tolist()) == {1}
    assert float(lin_log(torch.tensor(20.0))) == pytest.approx(math.log(20.0))
    assert float(lin_log(torch.tensor(10.0))) == pytest.approx(10.0 * LN20_OVER_20)


def test_several_thresholds_per_interval_with_separate_on_off_thresholds():
    # +0.95 with θ_on = 0.3 → 3 ON; then −0.95 from reference 0.9 (to 0.0 → −0.9 below) with θ_off = 0.25 → 3 OFF
    video = (0.4 * np.exp(np.array([0.0, 0.95, 0.0]))).reshape(3, 1, 1)
    ev = simulate_events(video, np.array([0, 5000, 10000]), threshold_on=0.3, threshold_off=0.25)
    assert ev["p"].tolist() == [1, 1, 1, 0, 0, 0]


def test_frame_end_timestamps():
    video = drifting_video(12, 3, 4)
    t_us = np.arange(12) * 5000
    ev_interp = simulate_events(video, t_us)
    ev_frame = simulate_events(video, t_us, timestamps="frame_end")
    assert np.isin(ev_frame["t"], t_us[1:]).all()
    # same events, only the times differ: each interpolated time lies in the interval ending at the frame time
    a, b = _by_pixel(ev_interp), _by_pixel(ev_frame)
    assert len(a) == len(b) > 0
    assert (a["x"] == b["x"]).all() and (a["y"] == b["y"]).all() and (a["p"] == b["p"]).all()
    assert ((b["t"] - a["t"] >= 0) & (b["t"] - a["t"] < 5000)).all()


# ---------------------------------------------------------------------------------------------- vs reference
@pytest.mark.parametrize("theta_on, theta_off", [(0.2, 0.2), (0.15, 0.25)])
def test_matches_independent_reference_simulator_on_drifting_video(theta_on, theta_off):
    video = drifting_video(60, 5, 6, seed=3)
    t_us = np.arange(60) * 4167 + 1000  # 240 fps, not on a round grid
    ours = simulate_events(video, t_us, threshold_on=theta_on, threshold_off=theta_off)
    ref = reference_simulator(video, t_us, theta_on, theta_off)
    assert len(ours) > 100
    assert len(ours) == len(ref)
    a, b = _by_pixel(ours), _by_pixel(ref)
    assert (a["x"] == b["x"]).all() and (a["y"] == b["y"]).all() and (a["p"] == b["p"]).all()
    # repeated "ref += θ" vs "ref + n θ" may move a ceil by one µs
    assert int(np.abs(a["t"] - b["t"]).max()) <= 1
    assert (np.diff(ours["t"]) >= 0).all()


def test_streaming_in_pieces_equals_whole_video():
    video = drifting_video(30, 4, 5, seed=1)
    t_us = np.arange(30) * 5000
    whole = simulate_events(video, t_us)
    sim = EventSimulator(4, 5)
    parts = [sim.feed(video[a:b], t_us[a:b]) for a, b in ((0, 7), (7, 8), (8, 30))]
    assert np.array_equal(np.concatenate(parts), whole)


def test_rgb_input_uses_luma():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.1, 0.9, (6, 3, 2, 3))
    luma = 0.299 * rgb[:, 0] + 0.587 * rgb[:, 1] + 0.114 * rgb[:, 2]
    t_us = np.arange(6) * 5000
    assert np.array_equal(simulate_events(rgb, t_us), simulate_events(luma, t_us))


def test_float32_and_torch_input():
    video = drifting_video(20, 3, 3, seed=2)
    t_us = np.arange(20) * 5000
    ev64 = simulate_events(torch.from_numpy(video), torch.from_numpy(t_us))
    ev32 = simulate_events(video.astype(np.float32), t_us, dtype="float32")
    assert len(ev64) > 0
    # float32 may flip a count at a near-tie; on this video it does not
    assert np.array_equal(_by_pixel(ev64)[["x", "y", "p"]], _by_pixel(ev32)[["x", "y", "p"]])


def test_does_not_mutate_inputs():
    video = drifting_video(10, 2, 2)
    t_us = np.arange(10) * 5000
    v0, t0 = video.copy(), t_us.copy()
    simulate_events(video, t_us, threshold_sigma=0.05, shot_noise_rate_hz=5.0, seed=1)
    assert np.array_equal(video, v0) and np.array_equal(t_us, t0)


# ---------------------------------------------------------------------------------------------- non-idealities
def test_noise_is_seeded():
    video = drifting_video(20, 6, 6)
    t_us = np.arange(20) * 5000
    kw = dict(threshold_sigma=0.03, shot_noise_rate_hz=20.0, leak_rate_hz=1.0, refractory_us=200, cutoff_hz=300.0)
    a = simulate_events(video, t_us, seed=7, **kw)
    b = simulate_events(video, t_us, seed=7, **kw)
    c = simulate_events(video, t_us, seed=8, **kw)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert (np.diff(a["t"]) >= 0).all()


def test_threshold_mismatch_spreads_counts_of_a_uniform_ramp():
    t_frames = 40
    video = np.broadcast_to((0.1 * np.exp(np.linspace(0.0, 2.0, t_frames)))[:, None, None], (t_frames, 20, 20))
    t_us = np.arange(t_frames) * 5000
    ideal = simulate_events(video, t_us)
    counts = np.bincount(ideal["y"].astype(int) * 20 + ideal["x"], minlength=400)
    assert (counts == counts[0]).all() and counts[0] in (9, 10)  # 2.0 / 0.2 (the last crossing is a tie)
    noisy = simulate_events(video, t_us, threshold_sigma=0.03, seed=0)
    counts = np.bincount(noisy["y"].astype(int) * 20 + noisy["x"], minlength=400)
    assert counts.min() < 9 and counts.max() > 10
    sim = EventSimulator(20, 20, SimulatorConfig(threshold_sigma=0.03, seed=0))
    sim.feed(video[:1], t_us[:1])
    theta = sim._state["theta_on"].numpy()
    assert abs(theta.mean() - 0.2) < 0.006 and abs(theta.std() - 0.03) < 0.006


def test_refractory_period_drops_events_but_moves_the_reference():
    # one big step: 10 ON crossings within 1000 µs, at fractions j/10.5 → times ceil(1000 j / 10.5)
    video = (0.1 * np.exp(np.array([0.0, 2.1, 2.1]))).reshape(3, 1, 1)
    t_us = np.array([0, 1000, 2000])
    ideal = simulate_events(video, t_us)
    assert len(ideal) == 10
    ev = simulate_events(video, t_us, refractory_us=250)
    times = ev["t"].tolist()
    assert (np.diff(times) >= 250).all()
    expected, last = [], -(10**9)
    for t in ideal["t"].tolist():
        if t - last >= 250:
            expected.append(t)
            last = t
    assert times == expected and len(times) == 4
    # the reference moved by all 10 crossings: a further small rise fires nothing
    sim = EventSimulator(1, 1, SimulatorConfig(refractory_us=250))
    sim.feed(video[:2], t_us[:2])
    assert float(sim.reference) == pytest.approx(float(lin_log(torch.tensor(25.5))) + 2.0)


def test_shot_noise_rate_and_intensity_dependence():
    t_frames, size = 101, 50
    t_us = np.arange(t_frames) * 10_000  # 1 s
    dark = np.zeros((t_frames, size, size))
    ev = simulate_events(dark, t_us, shot_noise_rate_hz=2.0, seed=0)
    expected = 2.0 * 1.0 * size * size  # rate × duration × pixels
    assert abs(len(ev) - expected) < 5 * math.sqrt(expected)
    on = int(ev["p"].sum())
    assert abs(on - expected / 2) < 5 * math.sqrt(expected / 2)
    bright = np.ones((t_frames, size, size))
    ev_bright = simulate_events(bright, t_us, shot_noise_rate_hz=2.0, seed=0)
    assert abs(len(ev_bright) - 0.25 * expected) < 5 * math.sqrt(0.25 * expected)


def test_hot_pixels_fire_at_their_rate_on_a_fixed_set_whatever_the_light():
    t_frames, size = 101, 50
    t_us = np.arange(t_frames) * 10_000  # 1 s
    kw = dict(hot_pixel_fraction=0.02, hot_pixel_rate_hz=40.0, seed=3)
    for level in (0.0, 1.0):  # no intensity dependence, unlike shot noise
        ev = simulate_events(np.full((t_frames, size, size), level), t_us, **kw)
        pixels = np.unique(ev["y"].astype(int) * size + ev["x"])
        assert abs(len(pixels) - 0.02 * size * size) < 5 * math.sqrt(0.02 * size * size)
        expected = 40.0 * len(pixels)  # rate × 1 s × hot pixels
        assert abs(len(ev) - expected) < 5 * math.sqrt(expected)
        assert abs(int(ev["p"].sum()) - expected / 2) < 5 * math.sqrt(expected / 2)
        if level == 0.0:
            dark_pixels = pixels
    assert np.array_equal(pixels, dark_pixels)  # the set is fixed by the seed
    sim = EventSimulator(size, size, SimulatorConfig(**kw))
    assert not sim.config.ideal
    # a sensor without hot pixels draws exactly what it drew before the option existed
    noisy = dict(threshold_sigma=0.03, shot_noise_rate_hz=20.0, leak_rate_hz=1.0, seed=7)
    video = drifting_video(20, 6, 6)
    assert np.array_equal(simulate_events(video, t_us[:20], **noisy),
                          simulate_events(video, t_us[:20], hot_pixel_fraction=0.5, hot_pixel_rate_hz=0.0, **noisy))
    with pytest.raises(ConfigError):
        SimulatorConfig(hot_pixel_fraction=1.5)


def test_leak_fires_on_events_at_the_leak_rate():
    t_us = np.arange(251) * 10_000  # 2.5 s
    video = np.full((251, 3, 3), 0.5)
    ev = simulate_events(video, t_us, leak_rate_hz=1.0)
    assert set(ev["p"].tolist()) == {1}
    # one ON event per pixel and second, from a random phase in [0, 1) s: 2 or 3 events per pixel in 2.5 s
    counts = np.bincount(ev["y"].astype(int) * 3 + ev["x"], minlength=9)
    assert set(counts.tolist()) <= {2, 3} and len(set(counts.tolist())) == 2
    for pixel in range(9):
        t = ev["t"][(ev["y"].astype(int) * 3 + ev["x"]) == pixel]
        assert np.abs(np.diff(t) - 1_000_000).max() <= 10_000  # one frame of jitter
    # a static pixel's leak crossing has no log change to interpolate: it is stamped at the frame time
    assert np.isin(ev["t"], t_us).all()


def test_low_pass_delays_events_without_losing_them():
    t_frames = 200
    logs = np.where(np.arange(t_frames) >= 5, 1.05, 0.0)
    video = np.broadcast_to((0.3 * np.exp(logs))[:, None, None], (t_frames, 1, 1)).copy()
    t_us = np.arange(t_frames) * 1000
    ideal = simulate_events(video, t_us)
    filtered = simulate_events(video, t_us, cutoff_hz=50.0)
    assert len(ideal) == len(filtered) == 5
    assert (filtered["t"] > ideal["t"]).all()
    assert ideal["t"].min() > 4000 and ideal["t"].max() <= 5000  # the step is interpolated from frame 4 to 5


# ---------------------------------------------------------------------------------------------- validation
def test_validation_errors():
    video = np.zeros((3, 2, 2))
    with pytest.raises(ShapeError):
        simulate_events(np.zeros((3, 2)), np.arange(3))
    with pytest.raises(ShapeError):
        simulate_events(video, np.arange(4))
    with pytest.raises(FormatError):
        simulate_events(video, np.array([0.0, 1.0, 2.0]))
    with pytest.raises(FormatError):
        simulate_events(video, np.array([0, 5, 5]))
    with pytest.raises(FormatError):
        simulate_events(np.zeros((3, 2, 2), dtype=np.int32), np.arange(3))
    for kwargs, field in (({"threshold_on": 0.0}, "threshold_on"), ({"timestamps": "start"}, "timestamps"),
                          ({"min_threshold": 0.0}, "min_threshold"), ({"leak_rate_hz": -1.0}, "leak_rate_hz")):
        with pytest.raises(ConfigError) as info:
            SimulatorConfig(**kwargs)
        assert info.value.field == field
    sim = EventSimulator(2, 2)
    sim.feed(video, np.arange(3))
    with pytest.raises(FormatError):
        sim.feed(video, np.arange(3))  # times not after the previous piece
    with pytest.raises(ShapeError):
        sim.feed(np.zeros((1, 3, 3)), np.array([10]))


@pytest.mark.gpu
def test_cuda_matches_cpu():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    video = drifting_video(30, 16, 16, seed=4)
    t_us = np.arange(30) * 5000
    cpu = simulate_events(video, t_us)
    gpu = simulate_events(video, t_us, device="cuda")
    assert np.array_equal(cpu, gpu)
