"""Damaged files and journals: errors name the file, nothing is left behind, memory does not follow a bad length."""

from __future__ import annotations

import struct
import zlib

import h5py
import numpy as np
import pytest

from davis_rig.errors import SessionError
from davis_rig.session import SessionReader, SessionWriter, recover_session
from davis_rig.session.journal import KIND_TRANSFER, MAGIC, SessionJournal, iter_journal, journal_path

from tests.helpers.session_data import Chunk, random_events, random_frame, synth_stream


def _damage_chunk(path, dataset: str, index: int, rng) -> None:
    """Overwrite one stored (compressed) HDF5 chunk of ``dataset`` with random bytes."""
    with h5py.File(path, "r") as f:
        info = f[dataset].id.get_chunk_info(index)
    data = bytearray(path.read_bytes())
    data[info.byte_offset : info.byte_offset + info.size] = rng.integers(0, 256, info.size, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))


@pytest.fixture
def damaged_frames(tmp_path, rng):
    path = tmp_path / "s.h5"
    with SessionWriter(path) as writer:
        writer.append(Chunk(random_events(rng, 1000), frames=[random_frame(rng, 10_000 * k) for k in range(3)]))
    _damage_chunk(path, "frames/data", 1, rng)
    return path


def test_a_damaged_frame_raises_session_error_naming_the_file(damaged_frames):
    with SessionReader(damaged_frames) as reader:
        assert reader.frames[0].pixels.shape == reader.frames[2].pixels.shape == (260, 346)  # the others read
        with pytest.raises(SessionError, match=r"s\.h5: cannot read /frames/data\[1, 0:260, 0:346\]: .*damaged"):
            reader.frames[1]
        with pytest.raises(SessionError, match="s.h5"):
            reader.frames.data[1]


def test_davis_label_on_damaged_frames_exits_4_naming_the_file(damaged_frames, tmp_path, capsys):
    from davis_rig.cli.label import main
    from tests.helpers.eval_data import person_yolo

    assert main([str(damaged_frames), "--yolo", str(person_yolo(tmp_path)), "--quiet"]) == 4
    err = capsys.readouterr().err
    assert f"davis-label: error: {damaged_frames}: cannot read /frames/data[1]" in err


def test_damaged_events_raise_session_error_naming_the_file(tmp_path, rng):
    path = tmp_path / "s.h5"
    with SessionWriter(path) as writer:
        writer.append(Chunk(random_events(rng, 300_000)))
    _damage_chunk(path, "events/x", 1, rng)
    with SessionReader(path) as reader:
        with pytest.raises(SessionError, match=r"s\.h5: cannot read events \[0, 300000\)"):
            reader.events()


def test_recover_calls_an_interrupted_no_journal_file_incomplete(tmp_path, rng, capsys):
    from davis_rig.cli.record import main

    path = tmp_path / "s.h5"
    with SessionWriter(path, journal=False) as writer:
        writer.append(Chunk(random_events(rng, 500)))
    with h5py.File(path, "a") as f:  # as a recording killed after its last flush leaves it
        f.attrs["complete"] = False
    report = recover_session(path)
    assert not report.recovered and not report.complete and report.events == 500
    assert main(["--recover", str(path)]) == 4
    err = capsys.readouterr().err
    assert "incomplete" in err and "no journal" in err and "500 events" in err and str(path) in err
    with h5py.File(path, "a") as f:
        f.attrs["complete"] = True
    assert recover_session(path).complete
    assert main(["--recover", str(path)]) == 0
    assert "intact" in capsys.readouterr().out


def _journal(path, transfers) -> None:
    journal = SessionJournal(journal_path(path), {"device_info": {}, "config": {}}).open()
    for transfer in transfers:
        journal.append_transfer(transfer)
    journal.close(delete=False)


def test_a_failed_rebuild_leaves_no_recovering_file_and_keeps_the_journal(tmp_path, rng, monkeypatch):
    path = tmp_path / "s.h5"
    _journal(path, [synth_stream(random_events(rng, 100))])

    def broken(self, chunk, **kwargs):
        raise SessionError("disk full")

    monkeypatch.setattr(SessionWriter, "append", broken)
    with pytest.raises(SessionError, match="disk full"):
        recover_session(path)
    assert not (tmp_path / "s.h5.recovering").exists()
    assert journal_path(path).exists() and not path.exists()


def test_the_journal_reaches_the_os_before_the_file_so_a_rebuild_never_has_less(tmp_path, rng):
    path = tmp_path / "s.h5"
    events = random_events(rng, 300)
    with SessionWriter(path, journal=True) as writer:
        for _ in range(3):  # appended within the journal's 0.25 s flush interval: still in its buffer
            writer.journal.append_transfer(synth_stream(events[:100]))
        writer.append(Chunk(events))
        writer.flush()  # a kill -9 from here on: the file holds the events, so must the journal on disk
        on_disk = [kind for kind, _, _ in iter_journal(journal_path(path)) if kind == KIND_TRANSFER]
        assert len(on_disk) == 3


def test_recovery_keeps_a_crashed_file_that_holds_more_than_its_journal(tmp_path, rng, capsys):
    from davis_rig.cli.record import main

    path = tmp_path / "s.h5"
    with SessionWriter(path, journal=False) as writer:  # the file reached the disk ...
        writer.append(Chunk(random_events(rng, 500)))
    with h5py.File(path, "a") as f:
        f.attrs["complete"] = False
    _journal(path, [synth_stream(random_events(rng, 100))])  # ... the journal's last second did not
    report = recover_session(path)
    assert report.kept_original and not report.recovered and report.events == 500
    assert not journal_path(path).exists() and not (tmp_path / "s.h5.recovering").exists()
    with SessionReader(path) as reader:
        assert reader.num_events == 500
    _journal(path, [synth_stream(random_events(rng, 100))])
    assert main(["--recover", str(path)]) == 0
    assert "kept as it is: it holds more than its journal gave back (500 events" in capsys.readouterr().out


def test_recovery_of_a_stream_that_jumps_months_ahead_stays_small(tmp_path, rng):
    events = random_events(rng, 2000)
    months = np.full(10_000, 0x7FFF, "<u2").tobytes()  # 10000 wraps of 4095 x 32768 us: about 15 months
    later = events.copy()
    later["t"] += 1_000_000
    path = tmp_path / "s.h5"
    _journal(path, [synth_stream(events), months, synth_stream(later)[2:]])  # [2:]: without its leading wrap word
    with pytest.warns(UserWarning, match="time jumps"):
        report = recover_session(path)
    assert report.recovered and report.events == 4000
    with SessionReader(path) as reader:
        assert reader.ms_to_idx.shape[0] < 3000  # the span of the data, not 15 months (4e10 entries)
        stats = reader.stats["writer"]
        assert stats["time_discontinuities"] >= 1
        stored = reader.events()
    np.testing.assert_array_equal(stored[:2000], events)
    np.testing.assert_array_equal(stored["x"][2000:], later["x"])
    assert np.all(np.diff(stored["t"]) >= 0)


def test_a_journal_record_with_a_huge_length_ends_the_journal(tmp_path, rng):
    path = tmp_path / "s.h5"
    _journal(path, [synth_stream(random_events(rng, 50))])
    with open(journal_path(path), "ab") as f:
        f.write(struct.pack("<BII", KIND_TRANSFER, 0xFFFFFFF0, zlib.crc32(b"")) + b"tail")
    records = list(iter_journal(journal_path(path)))
    assert [kind for kind, _, _ in records] == [1, KIND_TRANSFER]
    assert recover_session(path).events == 50


@pytest.mark.parametrize("header", [b"[1, 2]", b"not json"])
def test_a_journal_header_that_is_no_object_is_a_session_error(tmp_path, header):
    path = tmp_path / "s.h5"
    journal_path(path).write_bytes(MAGIC + struct.pack("<BII", 1, len(header), zlib.crc32(header)) + header)
    with pytest.raises(SessionError, match=r"s\.h5\.journal: the journal header is not"):
        recover_session(path)


def _small_session(path, n=2_000, span_us=400_000, labels=True):
    """A written session of ``n`` ordered events over ``span_us`` µs, with one label per 50 ms when asked."""
    from davis_rig.session import schema
    from davis_rig.types import BBOX_DTYPE, make_events

    rng = np.random.default_rng(5)
    t = np.sort(rng.integers(0, span_us, n))
    with SessionWriter(path, device_info={"serial": "DAMAGE"}) as writer:
        writer.append_events(make_events(t, rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n)))
    if labels:
        boxes = np.zeros(span_us // 50_000, BBOX_DTYPE)
        boxes["t"] = int(t[0]) // 1000 * 1000 + 50_000 * np.arange(1, len(boxes) + 1)
        boxes["x"], boxes["y"], boxes["w"], boxes["h"] = 100, 60, 40, 80
        with h5py.File(path, "r+") as f:
            f.create_group(schema.LABELS_GROUP).create_dataset(schema.LABEL_BOXES, data=boxes)
    return path


@pytest.mark.parametrize("dataset", ["events/ms_to_idx", "events/t", "frames/t_start_exposure_us",
                                     "labels/boxes"])
def test_a_declared_size_the_file_does_not_store_is_refused_before_any_allocation(tmp_path, dataset):
    path = _small_session(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        if dataset == "labels/boxes":  # written contiguous: re-made resizable, as another tool may write it
            boxes = f[dataset][:]
            del f[dataset]
            f.create_dataset(dataset, data=boxes, maxshape=(None,), chunks=(64,))
        columns = ["events/t", "events/x", "events/y", "events/p"] if dataset == "events/t" else [dataset]
        for name in columns:
            f[name].resize((2_000_000_000,))  # a few bytes of metadata declaring gigabytes of unwritten chunks
    with pytest.raises(SessionError, match=f"/{dataset} declares .* the file is damaged"):
        with SessionReader(path) as reader:
            reader.labels()


@pytest.mark.parametrize("damage", ["2-D", "float"])
def test_an_event_column_of_the_wrong_shape_or_type_is_a_session_error(tmp_path, damage):
    path = _small_session(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        t = f["events/t"][:]
        del f["events/t"]
        f.create_dataset("events/t", data=np.stack([t, t], 1) if damage == "2-D" else t.astype(np.float64))
    with pytest.raises(SessionError, match="/events/t is .* expected 1-D integers"):
        SessionReader(path).open()


def test_a_damaged_millisecond_index_is_refused_where_it_would_pick_other_events(tmp_path):
    path = _small_session(tmp_path / "s.h5")
    with SessionReader(path) as reader:
        intact = [len(reader.events_between(t, t + 50_000)) for t in range(reader.t_offset_us, 400_000, 50_000)]
    with h5py.File(path, "r+") as f:
        f["events/ms_to_idx"][:] = 0
    with SessionReader(path) as reader:
        with pytest.raises(SessionError, match=r"ms_to_idx\[\d+\] = 0 does not point at the first event"):
            reader.events_between(reader.t_offset_us + 100_000, reader.t_offset_us + 150_000)
    assert sum(intact) == 2_000  # the intact index reads every event once


def test_an_index_padded_past_the_last_event_does_not_stretch_the_span(tmp_path):
    path = _small_session(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        index = f["events/ms_to_idx"]
        size = len(index)
        index.resize((size + 3_600_000,))  # one hour more of entries, all past the last event
        index[size:] = 2_000
    with SessionReader(path) as reader:
        assert reader.indexed_span_us() == 1000 * size
        assert reader.events_end_us() <= reader.t_offset_us + 1000 * size
        assert len(reader.events_between(reader.t_offset_us, reader.t_offset_us + 10**9)) == 2_000


def test_labels_holding_nan_or_inf_are_a_session_error(tmp_path):
    path = _small_session(tmp_path / "s.h5")
    with h5py.File(path, "r+") as f:
        boxes = f["labels/boxes"][:]
        boxes["w"][1], boxes["x"][2] = np.nan, np.inf
        f["labels/boxes"][:] = boxes
    with SessionReader(path) as reader:
        with pytest.raises(SessionError, match="2 of 8 labels hold NaN or inf"):
            reader.labels()
