"""SessionWriter on damaged timestamps: nothing dropped, a bounded time span, a bounded ms_to_idx write."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.protocol import SensorLayout, StreamDecoder
from davis_rig.session import SessionReader, SessionWriter, h5file, record_session
from davis_rig.session import writer as writer_module
from davis_rig.types import make_events

from tests.helpers.session_data import Chunk, FakeCamera, random_events, synth_stream


def _decode_and_write(path, data: bytes, transfer_bytes: int = 8192, **kwargs) -> SessionReader:
    decoder = StreamDecoder(SensorLayout.davis346())
    with SessionWriter(path, **kwargs) as writer:
        for start in range(0, len(data), transfer_bytes):
            writer.append(decoder.feed(data[start : start + transfer_bytes]))
    return SessionReader(path)


def test_one_timestamp_word_far_ahead_does_not_drop_the_later_events(tmp_path, rng):
    events = random_events(rng, 20_000, span_us=200_000)
    words = np.frombuffer(synth_stream(events), "<u2").copy()
    ts = np.flatnonzero(words >= 0x8000)
    words[ts[100]] = 0xFFFF  # one corrupt timestamp word: up to 32 ms ahead of its neighbours
    with pytest.warns(UserWarning, match="goes back or sticks out"):
        reader = _decode_and_write(tmp_path / "s.h5", words.tobytes())
    with reader:
        stored = reader.events()
        stats = reader.stats["writer"]
    assert stored.shape == events.shape  # the writer kept only the events up to the spike
    np.testing.assert_array_equal(stored[["x", "y", "p"]], events[["x", "y", "p"]])
    wrong = np.flatnonzero(stored["t"] != events["t"])
    assert stats["events_time_repaired"] == wrong.shape[0] >= 1 and stats["time_discontinuities"] == 0
    assert np.all(np.diff(stored["t"]) >= 0)


def test_a_lost_wrap_word_shifts_the_rest_instead_of_dropping_it(tmp_path, rng):
    events = random_events(rng, 20_000, span_us=200_000)
    words = np.frombuffer(synth_stream(events), "<u2")
    wraps = np.flatnonzero(words >> 12 == 7)
    damaged = np.delete(words, wraps[2])  # the 3rd wrap word is lost: the time after it is 32.768 ms short
    with pytest.warns(UserWarning, match="time jumps"):
        reader = _decode_and_write(tmp_path / "s.h5", damaged.tobytes())
    with reader:
        stored = reader.events()
        offsets = reader.stats["writer"]["time_discontinuity_offsets"]
    assert stored.shape == events.shape and np.all(np.diff(stored["t"]) >= 0)
    assert len(offsets) == 1 and offsets[0]["offset_us"] > 0


def test_months_ahead_in_odd_short_transfers_stay_small(tmp_path, rng):
    """The issue's Faults(short_transfer_bytes=999) run: every other transfer misaligned (odd bytes dropped)."""
    events = random_events(rng, 30_000, span_us=300_000)
    data = synth_stream(events)
    camera = FakeCamera([data[i : i + 999] for i in range(0, len(data), 999)])
    with pytest.warns(UserWarning):
        summary = record_session(camera, tmp_path / "s.h5", journal=False)
    with SessionReader(summary.path) as reader:
        span_ms = reader.ms_to_idx.shape[0]
        assert reader.num_events == summary.events > 0
        assert np.all(np.diff(reader.events()["t"]) >= 0)
    assert span_ms <= summary.events * (writer_module.MAX_GAP_US // 1000 + 1)


def test_ms_to_idx_is_written_in_bounded_blocks_across_a_long_gap(tmp_path, monkeypatch):
    monkeypatch.setattr(h5file, "MS_INDEX_BLOCK", 1000)
    t = np.array([0, 5, 2_000, 7_654_321, 7_654_322, 9_000_000], np.int64)
    events = make_events(t, np.arange(6), np.arange(6), np.zeros(6, int))
    path = tmp_path / "s.h5"
    with SessionWriter(path) as writer:
        writer.append_events(events[:3])  # append_events keeps forward jumps (the times are taken as continuous)
        writer.flush()
        writer.append_events(events[3:])
    with SessionReader(path) as reader:
        np.testing.assert_array_equal(reader.events()["t"], t)
        expected = np.searchsorted(t, np.arange(9_000 + 2) * 1000, side="left")
        np.testing.assert_array_equal(reader.ms_to_idx, expected)


def test_a_jump_bridged_by_frames_is_kept(tmp_path, rng):
    from tests.helpers.session_data import random_frame

    before = random_events(rng, 100, t0_us=0, span_us=100_000)
    after = random_events(rng, 100, t0_us=3_000_000, span_us=100_000)
    frames = [random_frame(rng, t) for t in range(200_000, 3_000_000, 500_000)]  # a quiet scene, frames only
    path = tmp_path / "s.h5"
    with SessionWriter(path) as writer:
        writer.append(Chunk(before))
        writer.append(Chunk(np.zeros(0, before.dtype), frames=frames))
        writer.append(Chunk(after))
    with SessionReader(path) as reader:
        np.testing.assert_array_equal(reader.events()["t"], np.concatenate([before["t"], after["t"]]))
        assert reader.stats["writer"]["time_discontinuities"] == 0


def test_an_unbridged_jump_is_shortened_and_the_device_time_stays_recoverable(tmp_path, rng):
    before = random_events(rng, 100, t0_us=0, span_us=100_000)
    after = random_events(rng, 100, t0_us=50_000_000, span_us=100_000)
    special = np.array([(int(after["t"][50]), 2)], dtype=[("t", "<i8"), ("type", "u1")])
    path = tmp_path / "s.h5"
    with SessionWriter(path) as writer, pytest.warns(UserWarning, match="time jumps"):
        writer.append(Chunk(before))
        writer.append(Chunk(after, specials=special))
    with SessionReader(path) as reader:
        stored = reader.events()
        (entry,) = reader.stats["writer"]["time_discontinuity_offsets"]
        stored_special = reader.specials()
    assert stored["t"][100] == before["t"][-1] + 1
    np.testing.assert_array_equal(stored["t"][100:] - entry["offset_us"], after["t"])
    assert stored_special["t"][0] - entry["offset_us"] == special["t"][0]  # specials follow the events' offset


def test_times_whose_repair_leaves_int64_are_a_format_error_naming_the_file(tmp_path):
    from davis_rig.errors import FormatError

    far = -9_200_000_000_000_000_000  # garbage of a damaged import: time going back by ~2**63 µs, twice
    t = [1000, 2000, 3000, far, far + 1, 5000, 5001, far, far + 1, 9000]
    events = make_events(t, [1] * len(t), [1] * len(t), [1] * len(t))
    path = tmp_path / "s.h5"
    with SessionWriter(path) as writer:
        with pytest.raises(FormatError, match=r"s\.h5: event times out of range"):
            writer.append_events(events)
