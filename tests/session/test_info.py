"""describe_session: counts, rates, losses, labels and integrity of session files, intact and damaged."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from davis_rig.errors import SessionError
from davis_rig.protocol.decoder import IMU6_DTYPE
from davis_rig.session import SessionReader, SessionWriter
from davis_rig.session.info import PEAK_WINDOW_MS, describe_session
from davis_rig.session.journal import journal_path
from davis_rig.session.labels import labels_crop_origin, write_labels
from davis_rig.types import BBOX_DTYPE

from tests.helpers.session_data import SPECIAL_DTYPE, Chunk, random_events, random_frame

SAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "sample.h5"


def _peak_rate_brute_force(path) -> float:
    """The most events in one PEAK_WINDOW_MS window of the millisecond grid, from the events themselves."""
    with SessionReader(path) as reader:
        t = reader.events()["t"] - reader.t_offset_us
    window_us = PEAK_WINDOW_MS * 1000
    counts = np.bincount(t // window_us)
    return counts.max() * 1e6 / window_us


def test_bundled_sample():
    info = describe_session(SAMPLE)
    with SessionReader(SAMPLE) as reader:
        events = reader.events()
        specials = reader.specials()
        labels = reader.labels()
    assert info.integrity == "complete" and info.stopped_by == "stop"
    assert info.events == len(events) == 376_301
    assert (info.t_first_event_us, info.t_last_event_us) == (int(events["t"][0]), int(events["t"][-1]))
    assert info.duration_us == int(events["t"][-1] - events["t"][0])
    assert info.event_rate_mean_hz == pytest.approx(len(events) * 1e6 / info.duration_us)
    assert info.event_rate_peak_hz == pytest.approx(_peak_rate_brute_force(SAMPLE))
    assert info.frames == 15 and info.frame_rate_hz == pytest.approx(25.0) and info.exposure_median_us == 4000
    assert info.specials == len(specials) and sum(info.specials_by_type.values()) == len(specials)
    assert info.specials_by_type["APS_FRAME_START"] == int((specials["type"] == 14).sum())
    assert info.imu_samples == 0 and info.imu_rate_hz == 0.0
    assert info.dropped_transfers == 0 and info.decoder_losses == {}
    assert info.serial == "SYNTH001" and info.sensor_hw == (260, 346)
    assert info.crop_origin_xy == (21, 10)
    assert info.labels.boxes == len(labels) and info.labels.label_times == len(np.unique(labels["t"]))
    assert info.labels.boxes_per_class == {"pedestrian": len(labels)}
    assert info.labels.provenance["labeler"] == "davis_rig.scene.recording"
    assert info.labels.provenance["crop_origin_xy"] == [21, 10]  # JSON text decoded
    assert set(info.biases) == set(info.config["biases"])
    assert json.loads(json.dumps(info.to_json()))["labels"]["boxes"] == len(labels)


def _write_session(path, rng, *, journal=False, close=True, labels=None):
    events = random_events(rng, 5000, t0_us=2_000_000, span_us=400_000)
    imu = np.zeros(3, IMU6_DTYPE)
    imu["t"] = [2_000_100, 2_001_100, 2_002_100]
    specials = np.array([(2_100_000, 2), (2_150_000, 3), (2_200_000, 2)], dtype=SPECIAL_DTYPE)
    frames = [random_frame(rng, 2_050_000), random_frame(rng, 2_090_000, roi=(10, 20, 30, 40))]
    writer = SessionWriter(path, device_info={"serial": "X1"}, config={"exposure_us": 4000}, journal=journal).open()
    writer.append(Chunk(events, frames=frames, specials=specials, imu=imu))
    writer.set_stats({"camera": {"dropped_transfers": 2, "dropped_bytes": 4096,
                                 "decoder": {"unknown_words": 3, "dvs_out_of_range": 0}}})
    if close:
        writer.close()
    else:
        writer.abort()
    if labels is not None:
        write_labels(path, labels, {"labeler": "test", "crop_origin_x": 5, "crop_origin_y": 7})
    return events


def test_streams_losses_and_labels(tmp_path, rng):
    labels = np.zeros(3, BBOX_DTYPE)
    labels["t"] = [2_100_000, 2_100_000, 2_200_000]
    labels["class_id"] = [1, 0, 9]
    events = _write_session(tmp_path / "s.h5", rng, labels=labels)
    info = describe_session(tmp_path / "s.h5")
    assert info.integrity == "complete" and info.stopped_by is None
    assert info.events == len(events)
    assert info.frames == 2 and info.frame_rate_hz == pytest.approx(1e6 / 40_000)
    assert info.imu_samples == 3 and info.imu_rate_hz == pytest.approx(2e6 / 2_000)
    assert info.specials_by_type == {"EXTERNAL_INPUT_RISING_EDGE": 2, "EXTERNAL_INPUT_FALLING_EDGE": 1}
    assert (info.dropped_transfers, info.dropped_bytes) == (2, 4096)
    assert info.decoder_losses == {"unknown_words": 3}  # zero counters are left out
    assert info.serial == "X1" and info.sensor_hw == (260, 346)  # no layout stored: the DAVIS346 default
    assert info.crop_origin_xy == (5, 7)
    assert info.labels.boxes_per_class == {"car": 1, "pedestrian": 1, "class_9": 1}
    assert info.labels.label_times == 2
    assert (info.labels.t_first_us, info.labels.t_last_us) == (2_100_000, 2_200_000)


def test_no_labels_no_crop_origin(tmp_path, rng):
    _write_session(tmp_path / "s.h5", rng)
    info = describe_session(tmp_path / "s.h5")
    assert info.labels is None and info.crop_origin_xy is None


def test_empty_session(tmp_path):
    with SessionWriter(tmp_path / "e.h5"):
        pass
    info = describe_session(tmp_path / "e.h5")
    assert info.events == 0 and info.t_first_event_us is None and info.duration_us == 0
    assert info.event_rate_mean_hz == 0.0 and info.event_rate_peak_hz == 0.0 and info.exposure_median_us is None


def test_integrity_needs_recovery_and_incomplete(tmp_path, rng):
    _write_session(tmp_path / "crash.h5", rng, journal=True, close=False)
    info = describe_session(tmp_path / "crash.h5")
    assert info.integrity == "needs recovery"
    assert "davis-record --recover" in info.integrity_detail and "crash.h5.journal" in info.integrity_detail

    _write_session(tmp_path / "cut.h5", rng, close=False)
    info = describe_session(tmp_path / "cut.h5")
    assert info.integrity == "incomplete" and "no journal" in info.integrity_detail


def test_a_recording_in_progress_is_not_sent_to_recovery(tmp_path, rng):
    from davis_rig.session.journal import SessionJournal

    path = tmp_path / "live.h5"
    _write_session(path, rng, journal=True, close=False)
    recorder = SessionJournal(journal_path(path), {"format": "davis_rig.journal"}).open()  # as a recording holds it
    try:
        info = describe_session(path)
    finally:
        recorder.close()
    assert info.integrity == "recording" and "--recover" not in info.integrity_detail
    assert describe_session(path).integrity == "needs recovery"  # the journal of a recording that ended uncleanly


@pytest.mark.parametrize("damage", ["missing", "empty", "truncated", "not_hdf5", "foreign_hdf5"])
def test_damaged_files_raise_session_error(tmp_path, damage):
    path = tmp_path / "bad.h5"
    if damage == "empty":
        path.touch()
    elif damage == "truncated":
        path.write_bytes(SAMPLE.read_bytes()[:200_000])
    elif damage == "not_hdf5":
        path.write_bytes(b"just some text\n")
    elif damage == "foreign_hdf5":
        with h5py.File(path, "w") as f:
            f["x"] = np.arange(3)
    with pytest.raises(SessionError, match="bad.h5"):
        describe_session(path)


def test_unreadable_file_with_a_journal_says_how_to_recover(tmp_path):
    path = tmp_path / "s.h5"
    path.write_bytes(SAMPLE.read_bytes()[:200_000])
    journal_path(path).write_bytes(b"DRJRNL01")
    with pytest.raises(SessionError, match="davis-record --recover"):
        describe_session(path)


def test_labels_crop_origin_spellings():
    assert labels_crop_origin({"crop_origin_x": 3, "crop_origin_y": np.int64(4)}) == (3, 4)
    assert labels_crop_origin({"crop_origin_xy": "[21, 10]"}) == (21, 10)
    assert labels_crop_origin({"crop_origin_xy": [1, 2]}) == (1, 2)
    assert labels_crop_origin({"labeler": "x"}) is None
    with pytest.raises(SessionError, match="crop origin"):
        labels_crop_origin({"crop_origin_xy": "[1]"})


def test_write_labels_refuses_to_replace_without_overwrite(tmp_path):
    shutil.copy(SAMPLE, tmp_path / "s.h5")
    with pytest.raises(SessionError, match="already has /labels"):
        write_labels(tmp_path / "s.h5", np.zeros(1, BBOX_DTYPE), {"labeler": "x"})
    write_labels(tmp_path / "s.h5", np.zeros(1, BBOX_DTYPE), {"labeler": "x", "settings": {"a": 1}}, overwrite=True)
    with SessionReader(tmp_path / "s.h5") as reader:
        assert len(reader.labels()) == 1 and json.loads(reader.labels_attrs()["settings"]) == {"a": 1}


def test_write_labels_refuses_a_session_being_recorded(tmp_path, rng):
    from davis_rig.session.journal import SessionJournal

    path = tmp_path / "live.h5"
    _write_session(path, rng, journal=True, close=False)
    before = path.read_bytes()
    recorder = SessionJournal(journal_path(path), {"format": "davis_rig.journal"}).open()  # as a recording holds it
    try:
        with pytest.raises(SessionError, match=r"live\.h5: being recorded right now"):
            write_labels(path, np.zeros(1, BBOX_DTYPE), {"labeler": "x"})
    finally:
        recorder.close()
    assert path.read_bytes() == before


_RECORDER = """
import sys
from davis_rig.session import SessionWriter
writer = SessionWriter(sys.argv[1], journal=False).open()
print("open", flush=True)
sys.stdin.read()
writer.close()
"""


def test_write_labels_refuses_a_session_another_process_writes_without_a_journal(tmp_path):
    import subprocess
    import sys

    path = tmp_path / "live.h5"
    recorder = subprocess.Popen([sys.executable, "-c", _RECORDER, str(path)], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True)
    try:
        assert recorder.stdout.readline().strip() == "open"
        with pytest.raises(SessionError, match=r"live\.h5: cannot write /labels: .*lock"):
            write_labels(path, np.zeros(1, BBOX_DTYPE), {"labeler": "x"})
    finally:
        recorder.communicate("", timeout=60)
    with SessionReader(path) as reader:
        assert reader.complete and reader.labels() is None
