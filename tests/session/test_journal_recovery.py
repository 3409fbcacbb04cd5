"""The raw-transfer journal and recover_session: truncated tails, corrupt records, kill -9 of a recorder."""

from __future__ import annotations

import fcntl
import json
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from davis_rig.errors import SessionError
from davis_rig.session import SessionReader, SessionWriter, recover_session
from davis_rig.session.journal import (KIND_NOTE, KIND_TRANSFER, MAGIC, SessionJournal, journal_path,
                                       read_journal)
from davis_rig.session.record import record_session

from tests.helpers.session_data import FakeCamera, cut, random_events, synth_stream

REPO_ROOT = Path(__file__).resolve().parents[2]  # the recorder subprocess imports tests.helpers from here


def test_journal_round_trip_and_damaged_tail(tmp_path):
    path = tmp_path / "j.journal"
    with SessionJournal(path, {"device_info": {"serial": "A"}}) as journal:
        journal.append_transfer(b"\x01\x02\x03")
        journal.note({"dropped_transfers": 2})
        journal.append_transfer(memoryview(b"\x04" * 1000))
        journal.sync(force=True)
        journal._file.flush()
        intact = path.read_bytes()
        # The context manager deletes the journal on a clean exit; keep a copy to damage.
    assert not path.exists()
    path.write_bytes(intact)
    contents = read_journal(path)
    assert contents.header == {"device_info": {"serial": "A"}}
    assert contents.records == [(KIND_TRANSFER, b"\x01\x02\x03"), (KIND_NOTE, {"dropped_transfers": 2}),
                                (KIND_TRANSFER, b"\x04" * 1000)]
    assert contents.discarded_bytes == 0
    path.write_bytes(intact[:-10])  # the last record cut short by a crash
    contents = read_journal(path)
    assert len(contents.records) == 2 and contents.discarded_bytes == len(intact) - 10 - contents.valid_bytes
    corrupt = bytearray(intact)
    corrupt[-1] ^= 0xFF  # bad CRC in the last record
    path.write_bytes(bytes(corrupt))
    assert len(read_journal(path).records) == 2
    path.write_bytes(b"garbage!")
    with pytest.raises(SessionError, match="not a davis_rig journal"):
        read_journal(path)
    path.write_bytes(MAGIC)
    with pytest.raises(SessionError, match="no intact header"):
        read_journal(path)


def test_journal_is_kept_on_error_and_deleted_on_clean_close(tmp_path, rng):
    data = synth_stream(random_events(rng, 2000))
    clean = tmp_path / "clean.h5"
    record_session(FakeCamera(cut(data)), clean)
    assert not journal_path(clean).exists()
    failed = tmp_path / "failed.h5"
    with pytest.raises(RuntimeError):
        with SessionWriter(failed, journal=True) as writer:
            writer.append_raw(data)
            raise RuntimeError("boom")
    assert journal_path(failed).exists()


def test_recover_rebuilds_an_unreadable_file(tmp_path, rng):
    events = random_events(rng, 30_000, t0_us=1_000_000, span_us=2_000_000)
    transfers = cut(synth_stream(events), 4096)
    path = tmp_path / "s.h5"
    camera = FakeCamera(transfers)
    writer = SessionWriter(path, device_info=camera.info, journal=True).open()
    for data in transfers:
        writer.append_raw(data)
        writer.append(camera.decoder.feed(data))
    writer.journal._file.flush()  # what the OS has after a kill -9
    fcntl.flock(writer.journal._file.fileno(), fcntl.LOCK_UN)  # and the kernel drops the dead recorder's lock
    path.write_bytes(path.read_bytes()[:1000])  # the HDF5 file is damaged
    with pytest.raises(SessionError, match="truncated or corrupt"):
        SessionReader(path).open()
    report = recover_session(path)
    assert report.recovered and report.transfers == len(transfers) and report.events == len(events)
    assert not journal_path(path).exists()
    with SessionReader(path) as reader:
        np.testing.assert_array_equal(reader.events(), events)
        assert reader.device_info["serial"] == "FAKE0001"
        assert reader.stats["recovered_from_journal"]["transfers"] == len(transfers)
    # A second run finds an intact file and no journal: nothing to do.
    again = recover_session(path)
    assert not again.recovered and again.events == len(events)


def test_recover_without_journal_and_unreadable_file_fails(tmp_path):
    path = tmp_path / "s.h5"
    path.write_bytes(b"not hdf5")
    with pytest.raises(SessionError, match="no journal") as info:
        recover_session(path)
    assert "--recover" not in str(info.value)  # no advice to run what failed


def test_recover_refuses_a_recording_in_progress_and_changes_nothing(tmp_path, rng):
    data = synth_stream(random_events(rng, 2000))
    path = tmp_path / "live.h5"
    writer = SessionWriter(path, journal=True).open()
    try:
        writer.append_raw(data)
        writer.journal.sync(force=True)
        before = path.read_bytes(), journal_path(path).read_bytes()
        with pytest.raises(SessionError, match=r"live\.h5: being recorded right now"):
            recover_session(path)
        assert (path.read_bytes(), journal_path(path).read_bytes()) == before
        assert sorted(p.name for p in tmp_path.iterdir()) == ["live.h5", "live.h5.journal"]
    finally:
        writer.close()
    assert not journal_path(path).exists()


RECORDER = textwrap.dedent(
    """
    import sys, time, json
    sys.path.insert(0, sys.argv[3])
    import numpy as np
    from tests.helpers.session_data import FakeCamera, cut, random_events, synth_stream
    from davis_rig.session.record import record_session

    rng = np.random.default_rng(7)
    # 60 s of events at 20 k ev/s, served at about 10x real time (one 0.1 s transfer every 10 ms).
    events = random_events(rng, 1_200_000, t0_us=0, span_us=60_000_000)
    np.save(sys.argv[2], events)
    data = synth_stream(events)
    bounds = np.searchsorted(events["t"], np.arange(0, 60_000_000, 100_000))
    word_bounds = [0]
    # Each event is 3-4 words; cut at event boundaries via a decoder-independent byte count.
    words_per_event = 3 + (np.diff(np.concatenate([[0], events["t"] >> 15])) > 0)
    byte_offsets = np.concatenate([[0], np.cumsum(words_per_event * 2)])
    transfers = [data[byte_offsets[a]:byte_offsets[b]] for a, b in zip(bounds[:-1], bounds[1:])]
    camera = FakeCamera(transfers, delay_s=0.01)
    def progress(p):
        print(json.dumps({"events": p.events, "wall": time.time()}), flush=True)
    record_session(camera, sys.argv[1], progress=progress, progress_interval_s=0.2)
    """
)


def test_kill_9_then_recover_loses_at_most_one_second(tmp_path):
    path = tmp_path / "s.h5"
    script = tmp_path / "recorder.py"
    script.write_text(RECORDER)
    proc = subprocess.Popen([sys.executable, str(script), str(path), str(tmp_path / "events.npy"), str(REPO_ROOT)],
                            stdout=subprocess.PIPE, text=True)
    progress = []
    for line in proc.stdout:
        progress.append(json.loads(line))
        if progress[-1]["events"] > 200_000:
            break
    proc.send_signal(signal.SIGKILL)
    kill_wall = time.time()
    proc.wait(timeout=30)
    assert journal_path(path).exists()
    report = recover_session(path)
    events = np.load(tmp_path / "events.npy")
    with SessionReader(path) as reader:
        recovered = reader.events()
    # Everything recovered is exactly the head of what the camera produced.
    np.testing.assert_array_equal(recovered, events[: len(recovered)])
    # Data written up to 1 s before the kill is there: the recorder wrote `events` at `wall`.
    before = [p["events"] for p in progress if p["wall"] <= kill_wall - 1.0]
    assert before, "the recorder ran for less than a second"
    assert len(recovered) >= max(before)
    assert report.events == len(recovered)


def test_hdf5_write_failure_keeps_the_journal_for_recovery(tmp_path, rng, monkeypatch):
    """Monkeypatches SessionWriter._write_buffers (the low-level HDF5 write) to fail with ENOSPC."""
    import errno

    events = random_events(rng, 20_000, span_us=1_000_000)
    transfers = cut(synth_stream(events), 4096)
    path = tmp_path / "s.h5"
    camera = FakeCamera(transfers)
    writer = SessionWriter(path, device_info=camera.info, journal=True, flush_interval_s=0.0).open()
    half = len(transfers) // 2
    for data in transfers[:half]:
        writer.append_raw(data)
        writer.append(camera.decoder.feed(data))

    def no_space(self):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(SessionWriter, "_write_buffers", no_space)
    writer.append_raw(transfers[half])
    with pytest.raises(SessionError, match=r"disk full while writing.*davis-record --recover"):
        writer.append(camera.decoder.feed(transfers[half]))
    monkeypatch.undo()
    assert journal_path(path).exists()
    report = recover_session(path)
    assert report.transfers == half + 1
    with SessionReader(path) as reader:
        expected = FakeCamera(transfers).decoder.feed(b"".join(transfers[: half + 1])).events
        np.testing.assert_array_equal(reader.events(), expected)


def test_a_leftover_journal_is_not_overwritten_by_a_new_recording(tmp_path):
    path = tmp_path / "s.h5"
    journal_path(path).write_bytes(b"journal of a crashed recording")
    with pytest.raises(SessionError, match="--recover"):
        SessionWriter(path, journal=True).open()
    assert journal_path(path).read_bytes() == b"journal of a crashed recording"


def test_overwrite_refuses_a_session_that_is_being_recorded(tmp_path):
    path = tmp_path / "s.h5"
    path.write_bytes(b"what a running recording flushed so far")
    recorder = SessionJournal(journal_path(path), {"format": "davis_rig.journal"}).open()  # it holds its journal
    try:
        with pytest.raises(SessionError, match=r"s\.h5: being recorded right now"):
            SessionWriter(path, journal=True, overwrite=True).open()
        assert path.read_bytes() == b"what a running recording flushed so far"
    finally:
        recorder.close()


def test_overwrite_refuses_a_session_another_process_records_without_a_journal(tmp_path):
    import subprocess
    import sys

    path = tmp_path / "s.h5"
    recorder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from davis_rig.session import SessionWriter; "
         "w = SessionWriter(sys.argv[1], journal=False).open(); print('open', flush=True); time.sleep(60)", str(path)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert recorder.stdout.readline().strip() == "open"
        before = path.read_bytes()
        with pytest.raises(SessionError, match=r"s\.h5: being recorded right now"):
            SessionWriter(path, journal=False, overwrite=True).open()
        assert path.read_bytes() == before
    finally:
        recorder.kill()
        recorder.wait()
    SessionWriter(path, journal=False, overwrite=True).open().close()  # the control: once it has ended, it may


def test_a_journal_that_cannot_be_written_leaves_no_files_and_no_open_handle(tmp_path, monkeypatch):
    import davis_rig.session.journal as journal_module

    opened = []

    def tracking_open(*args, **kwargs):
        opened.append(open(*args, **kwargs))
        return opened[-1]

    def failing_fsync(fileno):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(journal_module, "open", tracking_open, raising=False)
    monkeypatch.setattr(journal_module.os, "fsync", failing_fsync)
    path = tmp_path / "s.h5"
    with pytest.raises(SessionError, match="journal.*No space left"):
        SessionWriter(path, journal=True).open()
    assert len(opened) == 1 and opened[0].closed
    assert not path.exists() and not journal_path(path).exists()
    monkeypatch.undo()
    with SessionWriter(path, journal=True) as writer:  # the same recording again is not refused
        writer.append_raw(b"\x00\x01")
    assert path.exists() and not journal_path(path).exists()


def test_journal_in_use_on_a_file_system_without_locks_or_an_unreadable_journal_is_false(tmp_path, monkeypatch):
    import errno

    import davis_rig.session.journal as journal_module
    from davis_rig.session.journal import journal_in_use

    journal = journal_path(tmp_path / "s.h5")
    recorder = SessionJournal(journal, {"format": "davis_rig.journal"}).open()
    try:
        assert journal_in_use(journal)  # the control: a running recording is seen

        def no_locks(fd, operation):
            raise OSError(errno.ENOLCK, "No locks available")

        monkeypatch.setattr(journal_module.fcntl, "flock", no_locks)
        assert not journal_in_use(journal)
    finally:
        monkeypatch.undo()
        recorder.close()
    assert not journal_in_use(tmp_path)  # a folder, not a journal
    assert not journal_in_use(tmp_path / "missing.journal")
