"""RecordingView: davis-eval's window grid, and what each window shows."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import SessionError, ShapeError
from davis_rig.viewer.recording import RecordingView, window_grid
from davis_rig.viewer.render import LABEL_RGB

from tests.helpers.viewer_data import CROP, FRAME_T0, FRAME_US, person_box, write_scene


def test_window_grid_covers_the_last_time():
    np.testing.assert_array_equal(window_grid(1000, 101_000, 50_000), [51_000, 101_000])
    np.testing.assert_array_equal(window_grid(1000, 101_001, 50_000), [51_000, 101_000, 151_000])
    np.testing.assert_array_equal(window_grid(1000, 1000, 50_000), [51_000])


def test_windows_events_aps_and_labels(scene):
    with RecordingView(scene) as view:
        assert view.t0_us == 0 and view.num_windows == 25 and view.crop_origin_xy == CROP
        assert view.window_end_us[0] == 50_000 and view.window_end_us[-1] == 1_250_000  # ms_to_idx reaches 1.201 s
        events = view.events(10)
        assert events["t"].min() >= 500_000 and events["t"].max() <= 550_000 and len(events) > 4000
        x1, y1, x2, y2 = person_box(525_000)
        assert events["x"].min() > x1 and events["x"].max() < x2 - 1
        # APS: the latest frame with its exposure middle (start + 2100 µs) <= 550 ms is frame 13 (527.1 ms)
        assert view.aps_index(10) == 13 and view.aps_index(0) == 1  # 47.1 ms <= 50 ms
        assert (FRAME_T0 + 13 * FRAME_US + 2100) <= 550_000 < (FRAME_T0 + 14 * FRAME_US + 2100)
        labels = view.labels_of(10)
        assert labels["t"].tolist() == [527_100]
        assert (labels["x"][0] + CROP[0], labels["y"][0] + CROP[1]) == (x1, y1)
        assert len(view.labels_of(23)) == len(view.labels_of(24)) == 0  # after 1150 ms: no frame
        image = view.render(10)
        assert (image[y1:y2, x1] == LABEL_RGB).all()
        info = view.info()
        assert info["num_windows"] == 25 and info["num_labels"] == 29 and info["detections"] is None
        with pytest.raises(IndexError):
            view.events(25)


def test_a_session_without_labels_is_viewable_with_a_centred_crop(tmp_path):
    with RecordingView(write_scene(tmp_path / "bare.h5", labels=False)) as view:
        assert not view.has_labels and len(view.labels) == 0 and view.crop_origin_xy == (21, 10)
        assert len(view.labels_of(3)) == 0 and view.render(3).shape == (260, 696, 3)


def test_crop_origin_must_match_the_labels_and_fit(scene):
    with pytest.raises(SessionError, match="crop origin"):
        RecordingView(scene, crop_origin_xy=(0, 0))
    path = write_scene(scene.parent / "unlabelled.h5", labels=False)
    with pytest.raises(ShapeError, match="crop"):
        RecordingView(path, crop_origin_xy=(50, 0))


def test_an_empty_session_is_refused(tmp_path):
    from davis_rig.session.writer import SessionWriter

    with SessionWriter(tmp_path / "empty.h5"):
        pass
    with pytest.raises(SessionError, match="neither events nor APS"):
        RecordingView(tmp_path / "empty.h5")
