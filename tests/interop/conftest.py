"""Fixtures of the interop tests: one session with every stream and labels at a non-centred crop origin."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.protocol.decoder import IMU6_DTYPE
from davis_rig.protocol.layout import SensorLayout
from davis_rig.session import SessionWriter
from davis_rig.session.labels import write_labels
from davis_rig.types import BBOX_DTYPE

from tests.helpers.session_data import SPECIAL_DTYPE, Chunk, random_events, random_frame

#: Crop origin of the fixture's labels: not the centred (21, 10), so a mix-up of origins shows.
LABELS_ORIGIN = (17, 12)
T0_US = 5_000_123


def make_labels(rng: np.random.Generator, times_us) -> np.ndarray:
    """Boxes with fractional float32 coordinates inside the 304x240 crop, several per time, both classes."""
    times = np.repeat(np.asarray(times_us, dtype=np.uint64), 2)
    labels = np.zeros(len(times), BBOX_DTYPE)
    labels["t"] = times
    labels["x"] = rng.uniform(0, 200, len(times)).astype(np.float32)
    labels["y"] = rng.uniform(0, 150, len(times)).astype(np.float32)
    labels["w"] = rng.uniform(10, 100, len(times)).astype(np.float32)
    labels["h"] = rng.uniform(10, 80, len(times)).astype(np.float32)
    labels["class_id"] = np.tile([1, 0], len(times) // 2)
    labels["class_confidence"] = rng.uniform(0.3, 1.0, len(times)).astype(np.float32)
    labels["track_id"] = np.tile([0, 7], len(times) // 2)
    return labels


@pytest.fixture
def labels_origin() -> tuple[int, int]:
    """The crop origin the fixture's labels are in."""
    return LABELS_ORIGIN


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(2025)


@pytest.fixture
def rich_session(tmp_path, rng):
    """``(path, events, labels)``: a DAVIS346 session with events, frames, specials, IMU and labels."""
    path = tmp_path / "rich.h5"
    events = random_events(rng, 20_000, t0_us=T0_US, span_us=800_000)
    frames = [random_frame(rng, T0_US + 40_000), random_frame(rng, T0_US + 80_000, roi=(10, 20, 30, 40))]
    specials = np.array([(T0_US + 1_000, 2), (T0_US + 2_000, 14), (T0_US + 3_000, 0)], dtype=SPECIAL_DTYPE)
    imu = np.zeros(3, IMU6_DTYPE)
    imu["t"] = T0_US + np.array([100, 1100, 2100])
    for i, name in enumerate(IMU6_DTYPE.names[1:]):
        imu[name] = rng.normal(size=3).astype(np.float32) + i
    info = {"serial": "RICH0001", "layout": SensorLayout.davis346()}
    with SessionWriter(path, device_info=info, config={"exposure_us": 4000}) as writer:
        writer.append(Chunk(events, frames=frames, specials=specials, imu=imu))
    labels = make_labels(rng, T0_US + np.arange(100_000, 800_000, 40_000))
    write_labels(path, labels, {"labeler": "test-labeler", "labeler_version": "9", "source": "hand made",
                                "crop_origin_x": LABELS_ORIGIN[0], "crop_origin_y": LABELS_ORIGIN[1]})
    return path, events, labels
