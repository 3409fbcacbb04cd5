"""label_session on a session recorded through the virtual DAVIS346; bad inputs leave the file untouched."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import DavisRigError, ModelFormatError, SessionError
from davis_rig.labelers.session_labels import label_session
from davis_rig.session import SessionReader, SessionWriter

from tests.helpers.eval_data import PERSON_BOX_CROP, person_yolo, scene_session, sha256


@pytest.fixture
def session(tmp_path_factory):
    return scene_session(tmp_path_factory.mktemp("labels"))


def test_labels_are_stored_in_the_crop_with_settings(session, tmp_path):
    summary = label_session(session, person_yolo(tmp_path))
    assert summary.frames == 49 and summary.boxes == 49 and summary.frames_with_boxes == 49
    with SessionReader(session) as reader:
        labels = reader.labels()
        attrs = reader.labels_attrs()
        t_mid = reader.frames.times_us("t_start_exposure_us") + 2_000  # 4 ms exposure
    np.testing.assert_array_equal(labels["t"], t_mid)
    box = np.stack([labels["x"], labels["y"], labels["x"] + labels["w"], labels["y"] + labels["h"]], 1)
    np.testing.assert_allclose(box, np.tile(PERSON_BOX_CROP, (49, 1)), atol=1e-3)
    assert (labels["class_id"] == 1).all() and labels["class_confidence"] == pytest.approx(0.9)
    assert attrs["labeler"] == "davis_rig.labelers.yolo" and attrs["source"] == "person_yolo.onnx"
    assert (attrs["crop_origin_x"], attrs["crop_origin_y"]) == (21, 10)
    assert '"layout": "yolov8"' in attrs["settings"] and '"conf_threshold": 0.25' in attrs["settings"]


def test_custom_crop_origin_moves_the_boxes(session, tmp_path):
    label_session(session, person_yolo(tmp_path), crop_origin_xy=(0, 0))
    with SessionReader(session) as reader:
        labels = reader.labels()
    assert labels["x"][0] == pytest.approx(120) and labels["y"][0] == pytest.approx(60)


def test_existing_labels_need_overwrite_and_file_stays_untouched(session, tmp_path):
    model = person_yolo(tmp_path)
    label_session(session, model)
    before = sha256(session)
    with pytest.raises(SessionError, match="--overwrite"):
        label_session(session, model)
    assert sha256(session) == before
    assert label_session(session, person_yolo(tmp_path, score=0.95), overwrite=True).boxes == 49
    with SessionReader(session) as reader:
        assert reader.labels()["class_confidence"] == pytest.approx(0.95)


def test_wrong_onnx_and_unknown_class_leave_the_session_untouched(session, tmp_path):
    before = sha256(session)
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x08\x07garbage")
    with pytest.raises(ModelFormatError):
        label_session(session, bad)
    with pytest.raises(ModelFormatError, match="not in the model's classes"):
        label_session(session, person_yolo(tmp_path), classes=["car"])
    assert sha256(session) == before


def test_a_session_being_recorded_is_refused_before_any_frame_is_labelled(session, tmp_path, monkeypatch):
    import davis_rig.labelers.session_labels as session_labels
    from davis_rig.session.journal import SessionJournal, journal_path

    labelled = []
    monkeypatch.setattr(session_labels, "label_frames", lambda *args, **kwargs: labelled.append(1))
    before = sha256(session)
    recorder = SessionJournal(journal_path(session), {"format": "davis_rig.journal"}).open()  # holds its journal
    try:
        with pytest.raises(SessionError, match="being recorded right now"):
            label_session(session, person_yolo(tmp_path))
    finally:
        recorder.close()
        journal_path(session).unlink()
    assert labelled == [] and sha256(session) == before


def test_session_without_frames_or_with_another_sensor_is_refused(tmp_path):
    from davis_rig.types import make_events

    events = make_events([10, 20], [1, 2], [1, 2], [0, 1])
    empty = tmp_path / "noframes.h5"
    with SessionWriter(empty) as writer:
        writer.append_events(events)
    before = sha256(empty)
    with pytest.raises(SessionError, match="no APS frames"):
        label_session(empty, person_yolo(tmp_path))
    assert sha256(empty) == before

    from davis_rig.protocol.frames import ApsFrame

    other = tmp_path / "dvxplorer.h5"
    info = {"layout": {"aps_size_columns": 240, "aps_size_rows": 180}}
    with SessionWriter(other, device_info=info) as writer:
        writer.append_events(events)
        writer.append_frame(ApsFrame(np.zeros((180, 240), np.uint16), 0, 0, 0, 1, 2, 3))
    before = sha256(other)
    with pytest.raises(SessionError, match="expected DAVIS346 346x260"):
        label_session(other, person_yolo(tmp_path))
    assert sha256(other) == before


@pytest.mark.parametrize("damage", ["empty", "truncated", "not_hdf5", "missing"])
def test_damaged_files_raise_a_toolkit_error(session, tmp_path, damage):
    path = tmp_path / "damaged.h5"
    data = session.read_bytes()
    if damage == "empty":
        path.write_bytes(b"")
    elif damage == "truncated":
        path.write_bytes(data[: len(data) // 3])
    elif damage == "not_hdf5":
        path.write_text("hello")
    before = sha256(path) if path.exists() else None
    with pytest.raises(DavisRigError):
        label_session(path, person_yolo(tmp_path))
    assert (sha256(path) if path.exists() else None) == before
