"""Tests of synthetic scene → session.h5: direct writer path, the encoder + virtual USB camera path (identical
content), geometry (crop embedding), ground-truth labels in RVT crop coordinates, validation."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from davis_rig.errors import SessionError, ShapeError
from davis_rig.events.simulator import SimulatorConfig
from davis_rig.scene.aps import ApsConfig
from davis_rig.training.recording import (
    SYNTHETIC_LABELER,
    embed_in_sensor,
    labels_to_crop,
    simulate_recording,
    write_clip_session,
    write_synthetic_session,
)
from davis_rig.session.reader import SessionReader
from davis_rig.types import BBOX_DTYPE, DAVIS346_HW, RVT_HW

T_FRAMES = 45  # 220 ms at 200 fps: 6 APS frames at 25 fps (SOF 2, 42, ..., 202 ms)


def bar_video(height: int = RVT_HW[0], width: int = RVT_HW[1]) -> tuple[np.ndarray, np.ndarray]:
    """A bright bar moving right by 2 px per frame over a dark ramp; float32 [T, H, W], t_us [T]."""
    yy, xx = np.mgrid[0:height, 0:width]
    background = 0.1 + 0.2 * xx / width
    frames = [np.where((xx >= 2 * k + 20) & (xx < 2 * k + 40) & (yy > 40) & (yy < 200), 0.8, background)
              for k in range(T_FRAMES)]
    return np.stack(frames).astype(np.float32), np.arange(T_FRAMES, dtype=np.int64) * 5000 + 2000


def person_labels() -> np.ndarray:
    labels = np.zeros(3, dtype=BBOX_DTYPE)
    labels["t"] = [2000, 102_000, 202_000]
    labels["x"], labels["y"], labels["w"], labels["h"] = [20, 60, 300], [41, 41, 41], [20, 20, 30], [159, 159, 250]
    labels["class_id"] = 1
    labels["class_confidence"] = 1.0
    return labels


def _read(path):
    with SessionReader(path) as reader:
        frames = [reader.frames[i] for i in range(len(reader.frames))]
        return reader.events(), frames, reader.labels(), reader.labels_attrs()


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    video, t_us = bar_video()
    tmp = tmp_path_factory.mktemp("synthetic")
    direct = write_synthetic_session(tmp / "direct.h5", video, t_us, labels=person_labels())
    usb = write_synthetic_session(tmp / "usb.h5", video, t_us, labels=person_labels(), through_usb=True)
    return video, t_us, direct, usb


def test_direct_session_holds_the_simulated_scene(sessions):
    video, t_us, direct, _ = sessions
    sensor_video, origin = embed_in_sensor(video)
    assert origin == (21, 10)
    events, frames = simulate_recording(sensor_video, t_us)
    stored_events, stored_frames, _, _ = _read(direct.path)
    assert direct.events == len(events) > 10_000 and direct.frames == len(frames) == 6
    assert np.array_equal(stored_events, events)
    # the crop's events, shifted by the origin: nothing fires outside it
    assert stored_events["x"].min() >= 21 and stored_events["x"].max() < 21 + 304
    assert stored_events["y"].min() >= 10 and stored_events["y"].max() < 10 + 240
    for stored, frame in zip(stored_frames, frames):
        assert np.array_equal(stored.pixels, frame.pixels)
        assert stored.t_start_exposure_us == frame.t_start_exposure_us
        assert stored.t_end_of_frame_us == frame.t_end_of_frame_us


def test_usb_path_writes_the_same_content(sessions):
    _, _, direct, usb = sessions
    assert usb.through_usb and usb.events == direct.events and usb.frames == direct.frames
    ev_a, frames_a, labels_a, _ = _read(direct.path)
    ev_b, frames_b, labels_b, _ = _read(usb.path)
    assert np.array_equal(ev_a, ev_b)
    assert len(frames_a) == len(frames_b) == 6
    for a, b in zip(frames_a, frames_b):
        assert np.array_equal(np.asarray(a.pixels), np.asarray(b.pixels))
        assert (a.t_start_of_frame_us, a.t_start_exposure_us, a.t_end_exposure_us, a.t_end_of_frame_us) == \
            (b.t_start_of_frame_us, b.t_start_exposure_us, b.t_end_exposure_us, b.t_end_of_frame_us)
    assert np.array_equal(labels_a, labels_b)


def test_labels_are_stored_in_crop_coordinates(sessions):
    _, _, direct, _ = sessions
    _, _, labels, attrs = _read(direct.path)
    assert direct.labels == 3 and labels.dtype == BBOX_DTYPE
    # video = crop: boxes unchanged except the clamp to [0, 303] x [0, 239]
    assert labels["t"].tolist() == [2000, 102_000, 202_000]
    assert labels["x"].tolist() == [20, 60, 300] and labels["w"].tolist() == [20, 20, 3]
    assert labels["h"].tolist() == [159, 159, 239 - 41]
    assert attrs["labeler"] == SYNTHETIC_LABELER


def test_sensor_sized_video_and_label_mapping():
    video = np.zeros((2, *DAVIS346_HW), dtype=np.float32)
    out, origin = embed_in_sensor(video)
    assert origin == (0, 0) and out.shape == (2, *DAVIS346_HW)
    labels = person_labels()
    mapped = labels_to_crop(labels, origin)
    assert mapped["x"].tolist() == [0, 39, 279] and mapped["y"].tolist() == [31, 31, 31]
    assert mapped["w"].tolist() == [19, 20, 24]  # first box clipped at the crop's left edge (x 20 → 21)
    with pytest.raises(ShapeError):
        embed_in_sensor(np.zeros((2, 300, 400)))


def test_write_clip_session_and_settings(tmp_path):
    video, t_us = bar_video(240, 304)
    clip = SimpleNamespace(video=video[:21], t_us=t_us[:21], labels=lambda: np.zeros(0, dtype=BBOX_DTYPE))
    summary = write_clip_session(tmp_path / "clip.h5", clip, simulator=SimulatorConfig(threshold_on=0.3),
                                 aps=ApsConfig(frame_rate_hz=50.0))
    assert summary.labels == 0 and summary.frames == 5
    import json

    import h5py

    with h5py.File(summary.path, "r") as f:
        config = json.loads(f.attrs["config"])
    assert config["synthetic"]["simulator"]["threshold_on"] == 0.3
    assert config["frame_interval_us"] == 20_000
    with pytest.raises(SessionError):
        write_clip_session(tmp_path / "clip.h5", clip)


def test_recorded_session_histograms_equal_the_differentiable_v2e(tmp_path):
    """End to end: session.h5 → crop → official RVT histograms == V2E of the same (crop) video, noise-free."""
    import torch

    from davis_rig.events.crop import crop_events
    from davis_rig.events.histogram import stacked_histograms
    from davis_rig.events.v2e_torch import v2e_histograms

    video, t_us = bar_video()
    video = video[:23].astype(np.float64)
    t_us = t_us[:23]
    summary = write_synthetic_session(tmp_path / "e2e.h5", video, t_us,
                                      simulator=SimulatorConfig(timestamps="frame_end", dtype="float32"))
    with SessionReader(summary.path) as reader:
        events = crop_events(reader.events())
    ends = np.array([t_us[-1] - 50_000, t_us[-1]])
    recorded = stacked_histograms(events, ends)
    digital = v2e_histograms(torch.tensor(video, dtype=torch.float32), t_us, ends, binning="rvt_frame_end")
    assert recorded.sum() > 1000
    assert np.array_equal(digital.numpy(), recorded.astype(np.float32))
