"""ExportSource: bounded pieces that add up to the session, and the crop-origin rules shared by every exporter."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import ConfigError, FormatError
from davis_rig.interop.source import ExportSource
from davis_rig.session import SessionReader, SessionWriter
from davis_rig.session.info import sensor_layout
from davis_rig.session.labels import write_labels
from davis_rig.types import BBOX_DTYPE, RVT_HW

from tests.helpers.session_data import random_events


@pytest.mark.parametrize("max_events", [1, 777, 5000, 10**9])
def test_pieces_are_bounded_and_add_up_to_the_session(rich_session, max_events):
    path, events, _ = rich_session
    with SessionReader(path) as reader:
        per_ms = int(np.diff(reader.ms_to_idx).max())
    with ExportSource(path) as source:
        pieces = list(source.event_chunks(max_events))
    assert all(read == len(piece) for piece, read in pieces)  # no crop: nothing dropped
    assert max(len(piece) for piece, _ in pieces) <= max_events + per_ms
    np.testing.assert_array_equal(np.concatenate([piece for piece, _ in pieces]), events)


def test_cropped_pieces_count_what_was_read(rich_session, labels_origin):
    path, events, _ = rich_session
    with ExportSource(path, crop=True) as source:
        pieces = list(source.event_chunks(4000))
        assert source.origin_xy == labels_origin and source.frame_hw == RVT_HW
    assert sum(read for _, read in pieces) == len(events)
    x = np.concatenate([piece["x"] for piece, _ in pieces])
    assert x.max() < RVT_HW[1] and len(x) < len(events)


def _session(path, rng, *, sensor_wh=(346, 260), labels_attrs=None):
    width, height = sensor_wh
    events = random_events(rng, 500)
    events["x"] %= width
    events["y"] %= height
    with SessionWriter(path, device_info={"layout": sensor_layout(width, height)}) as writer:
        writer.append_events(events)
    if labels_attrs is not None:
        write_labels(path, np.zeros(1, BBOX_DTYPE), labels_attrs)
    return path


def test_origin_rules(tmp_path, rng):
    no_labels = _session(tmp_path / "a.h5", rng)
    with ExportSource(no_labels, crop=True) as source:
        assert source.origin_xy == (21, 10) and source.labels() is None and source.labels_origin_xy is None
    with ExportSource(no_labels, crop=True, crop_origin_xy=(0, 5)) as source:
        assert source.origin_xy == (0, 5)
    with ExportSource(no_labels) as source:
        assert source.origin_xy == (0, 0) and source.frame_hw == (260, 346)

    unplaced = _session(tmp_path / "b.h5", rng, labels_attrs={"labeler": "x"})
    with ExportSource(unplaced) as source:  # labels without a stored origin: davis-eval's centred crop
        assert source.labels_origin_xy == (21, 10) and float(source.labels()["x"][0]) == 21.0

    placed = _session(tmp_path / "c.h5", rng, labels_attrs={"crop_origin_x": 3, "crop_origin_y": 4})
    with pytest.raises(ConfigError, match=r"labels were made for the crop at \(3, 4\)") as err, \
            ExportSource(placed, crop=True, crop_origin_xy=(21, 10)):
        pass
    assert err.value.field == "crop_origin_xy"
    with pytest.raises(ConfigError, match="does not fit"), ExportSource(no_labels, crop=True, crop_origin_xy=(50, 0)):
        pass


def test_a_sensor_smaller_than_the_crop(tmp_path, rng):
    small = _session(tmp_path / "small.h5", rng, sensor_wh=(200, 100))
    with ExportSource(small) as source:
        assert source.frame_hw == (100, 200)
    with pytest.raises(FormatError, match="smaller than the 304x240 window"), ExportSource(small, crop=True):
        pass
