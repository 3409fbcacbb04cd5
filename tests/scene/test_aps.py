"""Tests of the synthetic APS frames: timing, exposure integration, ADC scale, noise statistics, validation."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import ConfigError, FormatError, ShapeError
from davis_rig.scene.aps import ApsConfig, aps_frame_times, synthesize_aps_frames, to_adc

NOISELESS = dict(shot_noise=False, read_noise_dn=0.0)


def test_frame_times_25fps():
    times = aps_frame_times(1000, 200_000, ApsConfig())
    # SOF every 40 ms from 1000; SOE = SOF + 1000; EOE = SOE + 4000; EOF = EOE + 1000; EOE ≤ 200000
    assert times.tolist() == [[1000 + 40000 * i, 2000 + 40000 * i, 6000 + 40000 * i, 7000 + 40000 * i]
                              for i in range(5)]


def test_adc_scale_noiseless():
    cfg = ApsConfig(gain=1.0, offset_dn=0.0, **NOISELESS)
    pixels = to_adc(np.array([[0.0, 0.5, 1.0, 2.0]]), cfg)
    assert pixels.dtype == np.uint16
    assert (pixels >> 6).tolist() == [[0, 512, 1023, 1023]]  # round(511.5) = 512 (half to even), clip at full well
    assert (pixels & 63).max() == 0
    cfg = ApsConfig(gain=0.5, offset_dn=20.0, **NOISELESS)
    assert (to_adc(np.array([[1.0]]), cfg) >> 6).item() == round(0.5 * 1023 + 20)


def test_exposure_integrates_the_frames_inside():
    t_us = np.arange(0, 50_001, 1000)  # 1 kHz video
    video = (t_us / 100_000.0)[:, None, None] * np.ones((1, 2, 3))
    cfg = ApsConfig(gain=1.0, offset_dn=0.0, exposure_us=4000, **NOISELESS)
    frames = synthesize_aps_frames(video, t_us, cfg)
    assert len(frames) == 2  # SOF 0 and 40000 (EOE 45000 ≤ 50000)
    f = frames[1]
    assert (f.t_start_of_frame_us, f.t_start_exposure_us, f.t_end_exposure_us, f.t_end_of_frame_us) == \
        (40_000, 41_000, 45_000, 46_000)
    mean = np.mean(t_us[(t_us >= 41_000) & (t_us <= 45_000)] / 100_000.0)  # 0.43
    assert (f.pixels >> 6).tolist() == [[round(mean * 1023)] * 3] * 2
    assert f.t_exposure_mid_us == 43_000


def test_exposure_between_video_frames_uses_the_nearest_frame():
    t_us = np.array([0, 10_000, 20_000, 30_000, 40_000, 50_000])
    video = np.arange(6, dtype=float)[:, None, None] / 10 * np.ones((1, 1, 1))
    cfg = ApsConfig(gain=1.0, offset_dn=0.0, reset_readout_us=2000, exposure_us=1000, **NOISELESS)
    frames = synthesize_aps_frames(video, t_us, cfg)  # exposure [2000, 3000]: nearest video frame is t = 0
    assert int(frames[0].pixels[0, 0] >> 6) == 0
    assert int(frames[1].pixels[0, 0] >> 6) == round(0.4 * 1023)  # exposure [42000, 43000] → frame at 40000


def test_noise_statistics_and_seed():
    cfg = ApsConfig(gain=1.0, offset_dn=100.0, full_well_e=10_000.0, read_noise_dn=2.0, seed=3)
    flat = np.full((200, 200), 0.5)
    a, b = to_adc(flat, cfg), to_adc(flat, cfg)
    assert np.array_equal(a, b)
    dn = (a >> 6).astype(float)
    # mean 0.5·1023 + 100; variance = shot (1023²/10000 · 0.5·10000 e⁻ ... in DN: 1023² · 0.5 / 10000) + read 4 + 1/12
    expected_var = 1023.0**2 * 0.5 / 10_000 + 4.0 + 1 / 12
    assert dn.mean() == pytest.approx(0.5 * 1023 + 100, abs=0.2)
    assert dn.var() == pytest.approx(expected_var, rel=0.05)
    assert not np.array_equal(a, to_adc(flat, ApsConfig(gain=1.0, offset_dn=100.0, read_noise_dn=2.0, seed=4)))


def test_position_and_torch_input():
    import torch

    video = torch.full((11, 4, 5), 0.25)
    frames = synthesize_aps_frames(video, np.arange(11) * 1000, ApsConfig(frame_rate_hz=100.0, **NOISELESS),
                                   position_xy=(7, 3))
    assert len(frames) == 1 and frames[0].pixels.shape == (4, 5)
    assert (frames[0].position_x, frames[0].position_y) == (7, 3)


def test_validation():
    for kwargs, field in (({"frame_rate_hz": 200.0, "exposure_us": 5000}, "exposure_us"),  # does not fit its interval
                          ({"exposure_us": 0}, "exposure_us"), ({"read_noise_dn": -1.0}, "read_noise_dn")):
        with pytest.raises(ConfigError) as info:
            ApsConfig(**kwargs)
        assert info.value.field == field
    with pytest.raises(ShapeError):
        synthesize_aps_frames(np.zeros((3, 2)), np.arange(3))
    with pytest.raises(ShapeError):
        synthesize_aps_frames(np.zeros((3, 2, 2)), np.arange(4))
    with pytest.raises(FormatError):
        synthesize_aps_frames(np.zeros((3, 2, 2)), np.array([0.0, 1.0, 2.0]))
    with pytest.raises(FormatError):
        synthesize_aps_frames(np.zeros((3, 2, 2)), np.array([0, 2, 1]))
    assert synthesize_aps_frames(np.zeros((0, 2, 2)), np.zeros(0, dtype=np.int64)) == []
