"""session.h5 write -> read round trips, time slicing, ms_to_idx, validation and damaged files."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from davis_rig.errors import FormatError, SessionError
from davis_rig.session import SessionReader, SessionWriter, schema
from davis_rig.session.journal import journal_path
from davis_rig.types import BBOX_DTYPE, EVENT_DTYPE, make_events

from tests.helpers.session_data import SPECIAL_DTYPE, Chunk, random_events, random_frame, split_chunks

IMU_DTYPE = np.dtype([("t", "<i8"), ("accel_x_g", "<f4"), ("gyro_z_dps", "<f4"), ("temperature_c", "<f4")])


def write_session(path, chunks, **kwargs):
    with SessionWriter(path, device_info={"serial": "00000001", "layout": {"aps_height": 260, "aps_width": 346}},
                       config={"exposure_us": 4000, "frame_interval_us": 40000, "biases": {"PrBp": 1}},
                       **kwargs) as writer:
        for chunk in chunks:
            writer.append(chunk)
    return path


def brute_ms_to_idx(t_rel: np.ndarray) -> np.ndarray:
    last_ms = int(t_rel[-1]) // 1000
    return np.searchsorted(t_rel, np.arange(last_ms + 2) * 1000, side="left")


def test_round_trip_all_streams(tmp_path, rng):
    events = random_events(rng, 50_000, t0_us=7_654_321, span_us=2_000_000)
    parts = split_chunks(events, rng.integers(1, 1000, 200))
    frames = [random_frame(rng, 7_700_000 + 40_000 * i) for i in range(3)]
    roi_frame = random_frame(rng, 8_000_000, roi=(10, 20, 100, 50))
    specials = np.array([(7_654_400, 2), (8_000_000, 9)], dtype=SPECIAL_DTYPE)
    imu = np.zeros(4, IMU_DTYPE)
    imu["t"] = [7_700_000, 7_701_000, 7_702_000, 7_703_000]
    imu["accel_x_g"] = [0.5, -1.0, 0.25, 2.0]
    chunks = [Chunk(part) for part in parts]
    chunks[0] = Chunk(parts[0], frames=frames, specials=specials[:1], imu=imu)
    chunks[50] = Chunk(parts[50], frames=[roi_frame], specials=specials[1:])
    path = write_session(tmp_path / "s.h5", chunks, flush_interval_s=0.0)

    with SessionReader(path) as reader:
        assert reader.complete
        assert reader.num_events == len(events)
        np.testing.assert_array_equal(reader.events(), events)
        assert reader.events().dtype == EVENT_DTYPE
        assert reader.t_offset_us == 7_654_000
        assert len(reader.frames) == 4
        for stored, original in zip(reader.frames, [*frames, roi_frame]):
            np.testing.assert_array_equal(stored.pixels, original.pixels)
            assert (stored.position_x, stored.position_y) == (original.position_x, original.position_y)
            assert stored.t_start_exposure_us == original.t_start_exposure_us
            assert stored.t_end_of_frame_us == original.t_end_of_frame_us
        np.testing.assert_array_equal(reader.frames.roi[3], [10, 20, 100, 50])
        assert reader.frames.data.shape == (4, 260, 346)
        assert reader.frames.data[3, 0, 0] == 0  # outside the ROI
        np.testing.assert_array_equal(reader.frames.times_us("t_start_of_frame_us"),
                                      [f.t_start_of_frame_us for f in [*frames, roi_frame]])
        exposure_starts = [f.t_start_exposure_us for f in [*frames, roi_frame]]
        assert reader.frames.index_range(exposure_starts[1], exposure_starts[3]) == range(1, 3)
        assert reader.frames.index_range(exposure_starts[1] + 1, exposure_starts[2] + 1) == range(2, 3)
        assert reader.frames.index_range(0, exposure_starts[0]) == range(0, 0)
        np.testing.assert_array_equal(reader.specials(), specials)
        got_imu = reader.imu()
        for name in IMU_DTYPE.names:
            np.testing.assert_array_equal(got_imu[name], imu[name])
        assert reader.device_info["serial"] == "00000001"
        assert reader.config["exposure_us"] == 4000
        assert reader.biases == {"PrBp": 1}
        assert reader.stats["writer"]["events"] == len(events)
        assert reader.labels() is None


def test_ms_to_idx_follows_dsec_convention(tmp_path, rng):
    events = random_events(rng, 20_000, t0_us=1_000_500, span_us=300_000)
    path = write_session(tmp_path / "s.h5", [Chunk(p) for p in split_chunks(events, [7] * 3000)])
    with h5py.File(path, "r") as f:
        t_rel = f["events/t"][:]
        t_offset = int(f["events"].attrs["t_offset"])
        ms_to_idx = f["events/ms_to_idx"][:]
    assert t_offset == 1_000_000
    np.testing.assert_array_equal(t_rel + t_offset, events["t"])
    np.testing.assert_array_equal(ms_to_idx, brute_ms_to_idx(t_rel))
    assert ms_to_idx[-1] == len(events)
    with h5py.File(path, "r") as f:  # where DSEC's EventSlicer looks
        np.testing.assert_array_equal(f["ms_to_idx"][:], ms_to_idx)
        assert int(f["t_offset"][()]) == t_offset


def test_events_between_is_half_open(tmp_path):
    t = np.array([1000, 1000, 1999, 2000, 2000, 2001, 5000, 5000, 9999], dtype=np.int64)
    events = make_events(t, np.arange(9), np.arange(9), np.arange(9) % 2)
    path = write_session(tmp_path / "s.h5", [Chunk(events[:4]), Chunk(events[4:])])
    with SessionReader(path) as reader:
        np.testing.assert_array_equal(reader.events_between(1000, 2000)["t"], [1000, 1000, 1999])
        np.testing.assert_array_equal(reader.events_between(2000, 2001)["t"], [2000, 2000])
        np.testing.assert_array_equal(reader.events_between(2001, 5000)["t"], [2001])
        np.testing.assert_array_equal(reader.events_between(5000, 5001)["t"], [5000, 5000])
        assert len(reader.events_between(5001, 9999)) == 0
        np.testing.assert_array_equal(reader.events_between(9999, 10**9)["t"], [9999])
        np.testing.assert_array_equal(reader.events_between(-(10**9), 10**9), events)
        assert len(reader.events_between(3000, 3000)) == 0
        with pytest.raises(ValueError, match="t1_us"):
            reader.events_between(10, 5)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 3000),
    t0_us=st.integers(0, 2**40),
    span_us=st.integers(1, 50_000),
    windows=st.lists(st.tuples(st.integers(-2000, 52_000), st.integers(0, 20_000)), min_size=1, max_size=8),
)
def test_write_read_property(tmp_path_factory, seed, n, t0_us, span_us, windows):
    rng = np.random.default_rng(seed)
    events = random_events(rng, n, t0_us=t0_us, span_us=span_us)
    parts = split_chunks(events, rng.integers(1, 500, 200)) if n else []
    path = write_session(tmp_path_factory.mktemp("prop") / "s.h5", [Chunk(p) for p in parts])
    with SessionReader(path) as reader:
        np.testing.assert_array_equal(reader.events(), events)
        for start, length in windows:
            t0, t1 = t0_us + start, t0_us + start + length
            expected = events[(events["t"] >= t0) & (events["t"] < t1)]
            np.testing.assert_array_equal(reader.events_between(t0, t1), expected)


def test_iter_windows_covers_everything_once(tmp_path, rng):
    events = random_events(rng, 10_000, t0_us=123_456, span_us=1_000_000)
    path = write_session(tmp_path / "s.h5", [Chunk(events)])
    with SessionReader(path) as reader:
        windows = list(reader.iter_windows(50_000))
        assert windows[0][0] == 123_000 and all(b[0] - a[0] == 50_000 for a, b in zip(windows, windows[1:]))
        for t0, window in windows:
            np.testing.assert_array_equal(window, events[(events["t"] >= t0) & (events["t"] < t0 + 50_000)])
        np.testing.assert_array_equal(np.concatenate([w for _, w in windows]), events)
        partial = list(reader.iter_windows(100_000, t_start_us=500_000, t_end_us=650_000))
        assert [t0 for t0, _ in partial] == [500_000, 600_000]
        np.testing.assert_array_equal(partial[1][1], events[(events["t"] >= 600_000) & (events["t"] < 650_000)])
        with pytest.raises(ValueError, match="window_us"):
            next(reader.iter_windows(0))


def test_empty_session(tmp_path):
    path = write_session(tmp_path / "s.h5", [])
    with SessionReader(path) as reader:
        assert reader.num_events == 0
        assert len(reader.events()) == 0
        assert len(reader.events_between(0, 10**6)) == 0
        assert len(reader.frames) == 0
        assert len(reader.specials()) == 0
        assert reader.imu() is None


def test_events_whose_timestamp_alone_goes_back_are_kept_at_the_previous_time(tmp_path):
    first = make_events([100, 200, 300], [1, 2, 3], [1, 2, 3], [0, 1, 0])
    second = make_events([250, 400, 350, 500], [4, 5, 6, 7], [4, 5, 6, 7], [1, 1, 1, 1])
    with pytest.warns(UserWarning, match="goes back or sticks out"):
        path = write_session(tmp_path / "s.h5", [Chunk(first), Chunk(second)])
    with SessionReader(path) as reader:
        events = reader.events()
        np.testing.assert_array_equal(events["t"], [100, 200, 300, 300, 400, 400, 500])
        np.testing.assert_array_equal(events["x"], np.arange(1, 8))
        assert reader.stats["writer"]["events_time_repaired"] == 2
        assert reader.stats["writer"]["time_discontinuities"] == 0


def test_wrong_event_dtype_is_rejected(tmp_path):
    with SessionWriter(tmp_path / "s.h5") as writer:
        with pytest.raises(FormatError, match="expected dtype"):
            writer.append(Chunk(np.zeros(3, dtype=[("t", "<i4"), ("x", "<u2")])))


def test_existing_file_needs_overwrite(tmp_path):
    path = write_session(tmp_path / "s.h5", [])
    with pytest.raises(SessionError, match="file exists"):
        SessionWriter(path).open()
    write_session(path, [], overwrite=True)


def test_flushed_data_is_visible_while_recording(tmp_path, rng):
    """Another process (as after a crash) reads everything up to the last flush while the writer is open."""
    events = random_events(rng, 5000)
    path = tmp_path / "s.h5"
    probe = (
        "import sys, json; from davis_rig.session import SessionReader\n"
        "with SessionReader(sys.argv[1]) as r:\n"
        "    e = r.events(); print(json.dumps([len(e), int(e['t'].sum()), r.complete]))"
    )
    with SessionWriter(path) as writer:
        writer.append(Chunk(events))
        writer.flush()
        writer.append(Chunk(random_events(rng, 10, t0_us=2_000_000)))  # buffered, not flushed
        out = subprocess.run([sys.executable, "-c", probe, str(path)], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == [len(events), int(events["t"].sum()), False]


def test_labels_group_is_read_when_present(tmp_path):
    path = write_session(tmp_path / "s.h5", [])
    boxes = np.zeros(2, BBOX_DTYPE)
    boxes["t"] = [10, 20]
    boxes["class_id"] = 1
    with h5py.File(path, "a") as f:
        group = f.create_group(schema.LABELS_GROUP)
        group.create_dataset(schema.LABEL_BOXES, data=boxes)
        group.attrs["labeler"] = "yolo"
    with SessionReader(path) as reader:
        np.testing.assert_array_equal(reader.labels(), boxes)
        assert reader.labels_attrs()["labeler"] == "yolo"


def _digest(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_truncated_file_raises_session_error(tmp_path, rng):
    path = write_session(tmp_path / "s.h5", [Chunk(random_events(rng, 20_000))])
    data = open(path, "rb").read()
    truncated = tmp_path / "t.h5"
    truncated.write_bytes(data[: len(data) // 2])
    before = _digest(truncated)
    with pytest.raises(SessionError, match="truncated or corrupt"):
        SessionReader(truncated).open()
    assert _digest(truncated) == before  # reading never modifies the file


def test_empty_file_raises_session_error_and_names_the_journal_when_there_is_one(tmp_path):
    empty = tmp_path / "empty.h5"
    empty.write_bytes(b"")
    with pytest.raises(SessionError) as info:
        SessionReader(empty).open()
    assert str(info.value) == f"{empty}: the file is empty (0 bytes), not a recorded session"
    journal_path(empty).write_bytes(b"x")  # e.g. a power cut: the journal was fsync'd, the HDF5 file not
    with pytest.raises(SessionError) as info:
        SessionReader(empty).open()
    assert str(info.value) == (f"{empty}: the file is empty (0 bytes), not a recorded session; empty.h5.journal "
                               f"exists next to it: run `davis-record --recover {empty}`")
    assert empty.stat().st_size == 0  # reading never modifies the file


def test_a_file_being_recorded_is_not_sent_to_recovery(tmp_path):
    from davis_rig.session.journal import SessionJournal

    empty = tmp_path / "live.h5"
    empty.write_bytes(b"")  # nothing flushed yet
    recorder = SessionJournal(journal_path(empty), {"format": "davis_rig.journal"}).open()  # a recording holds it
    try:
        with pytest.raises(SessionError) as info:
            SessionReader(empty).open()
    finally:
        recorder.close()
    assert str(info.value) == (f"{empty}: the file is empty (0 bytes), not a recorded session; it is being recorded "
                               "right now: read it once the recording has ended")


def test_missing_group_and_foreign_files(tmp_path):
    missing = tmp_path / "missing.h5"
    with pytest.raises(SessionError, match="no such session file"):
        SessionReader(missing).open()
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.create_dataset("x", data=[1])
    with pytest.raises(SessionError, match="not a session file"):
        SessionReader(foreign).open()
    broken = write_session(tmp_path / "broken.h5", [])
    with h5py.File(broken, "a") as f:
        del f["frames"]
    with pytest.raises(SessionError, match="missing group /frames"):
        SessionReader(broken).open()
    uneven = write_session(tmp_path / "uneven.h5", [Chunk(make_events([1, 2], [0, 0], [0, 0], [0, 0]))])
    with h5py.File(uneven, "a") as f:
        f["events/x"].resize((1,))
    with pytest.raises(SessionError, match="different lengths"):
        SessionReader(uneven).open()
    not_hdf5 = tmp_path / "text.h5"
    not_hdf5.write_text("hello")
    with pytest.raises(SessionError, match="cannot open as HDF5"):
        SessionReader(not_hdf5).open()


def test_a_folder_or_unreadable_file_is_one_line_naming_the_file_and_the_journal_only_when_there_is_one(tmp_path):
    folder = tmp_path / "folder.h5"
    folder.mkdir()
    with pytest.raises(SessionError) as info:
        SessionReader(folder).open()
    assert str(info.value) == f"{folder}: not a file (a session.h5 is one HDF5 file)"
    not_hdf5 = tmp_path / "text.h5"
    not_hdf5.write_text("hello")
    with pytest.raises(SessionError) as info:
        SessionReader(not_hdf5).open()
    message = str(info.value)
    assert "\n" not in message and "truncated or corrupt" in message and "--recover" not in message
    journal_path(not_hdf5).write_bytes(b"x")
    with pytest.raises(SessionError, match=r"text\.h5\.journal exists next to it: run `davis-record --recover"):
        SessionReader(not_hdf5).open()


def test_root_attributes(tmp_path):
    path = write_session(tmp_path / "s.h5", [], start_unix_us=1_700_000_000_000_000)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == schema.FORMAT_NAME
        assert f.attrs["format_version"] == schema.FORMAT_VERSION
        assert f.attrs["recording_start_utc"] == "2023-11-14T22:13:20+00:00"
        assert json.loads(f.attrs["config"])["frame_interval_us"] == 40000
        assert f["events/t"].compression is not None or "32001" in str(f["events/t"]._filters)


# --- disk full -------------------------------------------------------------------------------------
def _fill_until_error(writer, rng, max_batches=400):
    written = []
    t0 = 0
    with pytest.raises(SessionError, match="disk nearly full") as info:
        for _ in range(max_batches):
            events = random_events(rng, 100_000, t0_us=t0, span_us=100_000)
            t0 += 100_000
            written.append(events)
            writer.append(Chunk(events))
    return np.concatenate(written), info.value


def test_disk_full_simulated_free_space_probe(tmp_path, rng, monkeypatch):
    """Monkeypatches SessionWriter._free_bytes (the statvfs probe) to report shrinking free space."""
    path = tmp_path / "s.h5"
    free = {"bytes": 12 << 20}

    def fake_free(self):
        free["bytes"] -= 2 << 20
        return free["bytes"]

    monkeypatch.setattr(SessionWriter, "_free_bytes", fake_free)
    writer = SessionWriter(path, flush_interval_s=0.0, min_free_bytes=2 << 20, journal=True).open()
    sent, error = _fill_until_error(writer, rng)
    assert "closed cleanly" in str(error) and str(path) in str(error)
    with SessionReader(path) as reader:
        assert reader.complete
        kept = reader.events()
        assert 0 < len(kept) < len(sent)
        np.testing.assert_array_equal(kept, sent[: len(kept)])
        assert "disk nearly full" in reader.stats["stopped_by"]
    assert (tmp_path / "s.h5.journal").exists()  # the journal is kept: it may hold the discarded tail
    with pytest.raises(SessionError, match="earlier error"):
        writer.append(Chunk(sent[:1]))


def test_abort_on_a_nearly_full_disk_never_marks_the_file_complete(tmp_path, rng, monkeypatch):
    path = tmp_path / "s.h5"
    free = {"bytes": 1 << 40}
    monkeypatch.setattr(SessionWriter, "_free_bytes", lambda self: free["bytes"])
    first = random_events(rng, 1000, t0_us=0, span_us=100_000)
    with pytest.raises(RuntimeError, match="camera bug"):
        with SessionWriter(path, journal=True) as writer:
            writer.append(Chunk(first))
            writer.flush()
            writer.append(Chunk(random_events(rng, 1000, t0_us=200_000, span_us=100_000)))
            free["bytes"] = 0  # the disk fills up before the error makes the writer abort
            raise RuntimeError("camera bug")
    with SessionReader(path) as reader:
        assert not reader.complete
        np.testing.assert_array_equal(reader.events(), first)
    assert journal_path(path).exists()  # kept for recovery: it holds the unwritten tail


def test_disk_full_on_a_real_tiny_filesystem(tmp_path, rng):
    """A 12 MiB tmpfs mounted in the test (needs root; skipped otherwise)."""
    mount_point = tmp_path / "tiny"
    mount_point.mkdir()
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=12m", "tmpfs", str(mount_point)],
                            capture_output=True, text=True)
    if result.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {result.stderr.strip()}")
    try:
        path = mount_point / "s.h5"
        writer = SessionWriter(path, flush_interval_s=0.0, min_free_bytes=1 << 20).open()
        sent, error = _fill_until_error(writer, rng)
        with SessionReader(path) as reader:
            kept = reader.events()
            assert len(kept) > 0
            np.testing.assert_array_equal(kept, sent[: len(kept)])
            stat = os.statvfs(mount_point)
            assert stat.f_bavail * stat.f_frsize > 0  # stopped before the disk was full
    finally:
        subprocess.run(["umount", str(mount_point)], check=False)
