"""record_session: the camera -> session.h5 loop (fake camera over the real decoder)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from davis_rig.errors import SessionError
from davis_rig.session import SessionReader
from davis_rig.session.journal import journal_path
from davis_rig.session.record import record_session

from tests.helpers.session_data import FakeCamera, cut, random_events, synth_stream


def test_records_everything_and_configures_the_camera(tmp_path, rng):
    events = random_events(rng, 40_000, t0_us=100, span_us=3_000_000)
    camera = FakeCamera(cut(synth_stream(events)))
    summary = record_session(camera, tmp_path / "s.h5", exposure_us=8000, frame_interval_us=50_000)
    assert camera.calls == ["send_default_config", ("set_exposure", 8000), ("set_frame_interval", 50_000),
                            "start", "stop"]
    assert summary.stopped_by == "end" and summary.events == len(events)
    with SessionReader(tmp_path / "s.h5") as reader:
        np.testing.assert_array_equal(reader.events(), events)
        assert reader.config["exposure_us"] == 8000 and reader.config["frame_interval_us"] == 50_000
        assert reader.biases == {"PrBp": 1}
        assert reader.device_info["serial"] == "FAKE0001"
        assert reader.stats["camera"]["transfers"] == len(camera.transfers)
        assert reader.stats["stopped_by"] == "end"
        assert reader.complete


def test_unplug_keeps_the_data_before_it(tmp_path, rng):
    events = random_events(rng, 40_000, span_us=2_000_000)
    transfers = cut(synth_stream(events), 2048)
    camera = FakeCamera(transfers, disconnect_after=20)
    summary = record_session(camera, tmp_path / "s.h5")
    assert summary.stopped_by == "disconnected"
    expected = np.concatenate([FakeCamera(transfers).decoder.feed(b"".join(transfers[:20])).events])
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.complete
        np.testing.assert_array_equal(reader.events(), expected)
        assert reader.stats["stopped_by"] == "disconnected"
    assert not journal_path(tmp_path / "s.h5").exists()


@pytest.mark.filterwarnings("ignore:.*go back in time")
def test_garbage_bytes_are_recorded_with_corrupt_words_counted(tmp_path, rng):
    events = random_events(rng, 5000, span_us=500_000)
    data = bytearray(synth_stream(events))
    noise = np.random.default_rng(3)
    positions = noise.choice(len(data), 400, replace=False)
    for pos in positions:
        data[pos] = int(noise.integers(0, 256))
    record_session(FakeCamera(cut(bytes(data), 1000) + [b"\x01"]), tmp_path / "s.h5")
    with SessionReader(tmp_path / "s.h5") as reader:
        decoder = reader.stats["camera"]["decoder"]
        assert decoder["words"] == len(data) // 2
        assert decoder["odd_bytes_dropped"] == 1
        assert decoder["unknown_words"] + decoder["dvs_out_of_range"] + decoder["non_monotonic_timestamps"] > 0
        recorded = reader.events()
        assert 0 < len(recorded)
        assert np.all(np.diff(recorded["t"]) >= 0)


def test_stop_event_and_duration(tmp_path, rng):
    transfers = cut(synth_stream(random_events(rng, 20_000, span_us=10_000_000)), 512)
    stop = threading.Event()
    stop.set()
    summary = record_session(FakeCamera(transfers), tmp_path / "a.h5", stop_event=stop)
    assert summary.stopped_by == "stop" and summary.events < 20_000
    summary = record_session(FakeCamera(transfers, delay_s=0.01), tmp_path / "b.h5", duration_s=0.2)
    assert summary.stopped_by == "duration" and 0.2 <= summary.duration_s < 10.0
    with SessionReader(tmp_path / "b.h5") as reader:
        assert reader.num_events == summary.events


def test_progress_is_reported(tmp_path, rng):
    transfers = cut(synth_stream(random_events(rng, 20_000, span_us=1_000_000)), 512)
    seen = []
    record_session(FakeCamera(transfers, delay_s=0.002), tmp_path / "s.h5", progress=seen.append,
                   progress_interval_s=0.05)
    assert seen and seen[-1].events <= 20_000 and seen[-1].dropped_transfers == 0
    assert all(p.event_rate_hz >= 0 for p in seen)


def test_existing_file_is_not_overwritten(tmp_path, rng):
    path = tmp_path / "s.h5"
    path.write_bytes(b"precious")
    with pytest.raises(SessionError, match="file exists"):
        record_session(FakeCamera([]), path)
    assert path.read_bytes() == b"precious"


def test_a_writer_error_stops_the_camera_and_propagates(tmp_path, rng, monkeypatch):
    from davis_rig.session.writer import SessionWriter

    def failing_append(self, chunk):
        raise SessionError(f"{self.path}: disk nearly full")

    monkeypatch.setattr(SessionWriter, "append", failing_append)
    camera = FakeCamera(cut(synth_stream(random_events(rng, 1000))))
    with pytest.raises(SessionError, match="disk nearly full"):
        record_session(camera, tmp_path / "s.h5")
    assert camera.calls[-1] == "stop" and not camera.running
    assert camera.listeners == []


def test_a_camera_that_fails_to_start_leaves_no_file_and_no_listener(tmp_path, rng):
    from davis_rig.errors import DeviceError, TransportError

    path = tmp_path / "s.h5"
    camera = FakeCamera([], start_error=TransportError("write config (0, 1) = 1 failed: pipe error"))
    with pytest.raises(DeviceError, match="did not start.*pipe error.*nothing was recorded") as info:
        record_session(camera, path)
    assert isinstance(info.value.__cause__, TransportError)
    assert not path.exists() and not journal_path(path).exists()
    assert camera.listeners == []
    # The same command again is not refused with "file exists".
    summary = record_session(FakeCamera(cut(synth_stream(random_events(rng, 1000)))), path)
    assert summary.events == 1000


def test_a_start_interrupted_by_ctrl_c_leaves_no_file(tmp_path):
    path = tmp_path / "s.h5"
    camera = FakeCamera([], start_error=KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        record_session(camera, path, journal=False)
    assert not path.exists() and not journal_path(path).exists() and camera.listeners == []


def test_camera_default_aps_settings_are_stored_not_null(tmp_path, rng):
    transfers = cut(synth_stream(random_events(rng, 1000)))
    record_session(FakeCamera(transfers), tmp_path / "a.h5")
    record_session(FakeCamera(transfers), tmp_path / "b.h5", exposure_us=8000)
    record_session(FakeCamera(transfers), tmp_path / "c.h5", send_default_config=False)
    with SessionReader(tmp_path / "a.h5") as reader:
        assert (reader.config["exposure_us"], reader.config["frame_interval_us"]) == (4000, 40000)
    with SessionReader(tmp_path / "b.h5") as reader:
        assert (reader.config["exposure_us"], reader.config["frame_interval_us"]) == (8000, 40000)
    with SessionReader(tmp_path / "c.h5") as reader:  # nothing sent: the device's values are unknown
        assert (reader.config["exposure_us"], reader.config["frame_interval_us"]) == (None, None)
