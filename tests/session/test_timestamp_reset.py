"""Timestamp resets: the writer keeps every item and one monotonic recording time (offsets in the stats)."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.protocol.words import SpecialType
from davis_rig.session import SessionReader, SessionWriter
from davis_rig.session.record import record_session

from tests.helpers.session_data import SPECIAL_DTYPE, Chunk, FakeCamera, cut, random_events, random_frame, synth_stream

RESET = int(SpecialType.TIMESTAMP_RESET)
RISING = int(SpecialType.EXTERNAL_INPUT_RISING_EDGE)
IMU_DTYPE = np.dtype([("t", "<i8"), ("accel_x_g", "<f4")])


def _imu(times):
    table = np.zeros(len(times), IMU_DTYPE)
    table["t"] = times
    return table


@pytest.mark.filterwarnings("ignore:.*timestamp was reset")
def test_reset_inside_a_chunk_keeps_everything_in_order(tmp_path, rng):
    before = random_events(rng, 3000, t0_us=1_000, span_us=600_000)   # device epoch 0
    after = random_events(rng, 2000, t0_us=0, span_us=300_000)        # device clock restarted at 0
    t_before = 700_000  # latest pre-reset time: the last pre-reset frame ends there
    frame_before = random_frame(rng, t_before - 4100)
    frame_after = random_frame(rng, 50_000)
    specials_b = np.array([(650_000, RISING), (0, RESET), (100_000, RISING)], dtype=SPECIAL_DTYPE)
    chunks = [
        Chunk(before[:1000]),
        Chunk(np.concatenate([before[1000:], after[:500]]), frames=[frame_before, frame_after],
              specials=specials_b, imu=_imu([690_000, 10, 20])),
        Chunk(after[500:], imu=_imu([250_000])),
    ]
    originals = [c.events.copy() for c in chunks]
    path = tmp_path / "s.h5"
    with SessionWriter(path, flush_interval_s=0.0) as writer:
        for chunk in chunks:
            writer.append(chunk)
    for chunk, original in zip(chunks, originals):  # the caller's arrays are not modified
        np.testing.assert_array_equal(chunk.events, original)

    offset = t_before + 1
    with SessionReader(path) as reader:
        events = reader.events()
        assert len(events) == len(before) + len(after)
        assert np.all(np.diff(events["t"]) >= 0)
        np.testing.assert_array_equal(events["t"][: len(before)], before["t"])
        np.testing.assert_array_equal(events["t"][len(before):], after["t"] + offset)
        np.testing.assert_array_equal(events[["x", "y", "p"]], np.concatenate([before, after])[["x", "y", "p"]])
        np.testing.assert_array_equal(reader.specials(), np.array(
            [(650_000, RISING), (offset, RESET), (100_000 + offset, RISING)], dtype=SPECIAL_DTYPE))
        np.testing.assert_array_equal(reader.imu()["t"], [690_000, 10 + offset, 20 + offset, 250_000 + offset])
        np.testing.assert_array_equal(reader.frames.times_us("t_end_of_frame_us"),
                                      [t_before, frame_after.t_end_of_frame_us + offset])
        writer_stats = reader.stats["writer"]
        assert writer_stats["events_time_repaired"] == writer_stats["time_discontinuities"] == 0
        assert writer_stats["timestamp_resets"] == 1
        assert writer_stats["timestamp_reset_offsets"] == [{"t_us": offset, "offset_us": offset}]


@pytest.mark.filterwarnings("ignore:.*timestamp was reset")
def test_two_resets_in_one_chunk_and_one_at_a_chunk_edge(tmp_path, rng):
    a = random_events(rng, 500, t0_us=10_000, span_us=100_000)
    b = random_events(rng, 500, t0_us=0, span_us=50_000)
    c = random_events(rng, 500, t0_us=0, span_us=80_000)
    d = random_events(rng, 500, t0_us=0, span_us=20_000)
    resets = np.array([(0, RESET), (0, RESET)], dtype=SPECIAL_DTYPE)
    chunks = [Chunk(np.concatenate([a, b, c]), specials=resets),
              Chunk(np.zeros(0, a.dtype), specials=resets[:1]),  # reset with nothing after it in its chunk
              Chunk(d)]
    path = tmp_path / "s.h5"
    with SessionWriter(path, flush_interval_s=0.0) as writer:
        for chunk in chunks:
            writer.append(chunk)
    o1 = int(a["t"][-1]) + 1
    o2 = o1 + int(b["t"][-1]) + 1
    o3 = o2 + int(c["t"][-1]) + 1
    with SessionReader(path) as reader:
        np.testing.assert_array_equal(
            reader.events()["t"], np.concatenate([a["t"], b["t"] + o1, c["t"] + o2, d["t"] + o3]))
        np.testing.assert_array_equal(reader.specials()["t"], [o1, o2, o3])
        assert reader.stats["writer"]["timestamp_reset_offsets"] == [
            {"t_us": o, "offset_us": o} for o in (o1, o2, o3)]


@pytest.mark.filterwarnings("ignore:.*timestamp was reset")
def test_record_session_survives_a_device_timestamp_reset(tmp_path, rng):
    from davis_rig.protocol.words import Special

    before = random_events(rng, 20_000, t0_us=100, span_us=1_500_000)
    after = random_events(rng, 20_000, t0_us=0, span_us=1_000_000)
    reset_word = np.array([Special.TIMESTAMP_RESET], dtype="<u2").tobytes()
    camera = FakeCamera(cut(synth_stream(before) + reset_word + synth_stream(after), 4000))
    summary = record_session(camera, tmp_path / "s.h5")
    assert summary.events == len(before) + len(after)
    assert camera.decoder.stats.timestamp_resets == 1
    offset = int(before["t"][-1]) + 1
    with SessionReader(tmp_path / "s.h5") as reader:
        events = reader.events()
        np.testing.assert_array_equal(events["t"], np.concatenate([before["t"], after["t"] + offset]))
        assert reader.specials().tolist() == [(offset, RESET)]
        assert reader.stats["writer"]["events_time_repaired"] == reader.stats["writer"]["time_discontinuities"] == 0
        assert reader.stats["writer"]["timestamp_reset_offsets"] == [{"t_us": offset, "offset_us": offset}]
