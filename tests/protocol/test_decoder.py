"""StreamDecoder against the shared DAVIS346 test vectors and hand-made streams (PROTOCOL.md §8-§13)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from davis_rig.errors import ProtocolError
from davis_rig.protocol import DecodedChunk, SensorLayout, SpecialType, StreamDecoder
from davis_rig.protocol.words import (
    adc_word,
    misc8_word,
    special_word,
    timestamp_word,
    wrap_word,
    x_word,
    y_word,
)

from tests.helpers.davis346_vectors import assert_matches_expected

pytestmark = pytest.mark.usefixtures("each_decoder_kernel")


# ---------------------------------------------------------------------------------------------- shared vectors
def test_vector_decodes_exactly(vector, proto):
    chunk, _ = proto.decode_all(proto.layout(vector), proto.transfers(vector))
    assert_matches_expected(chunk, vector["expected"])


def test_vector_every_even_split_gives_same_output(vector, proto):
    data = b"".join(proto.transfers(vector))
    layout = proto.layout(vector)
    for cut in range(0, len(data) + 1, 2):
        chunk, decoder = proto.decode_all(layout, [data[:cut], data[cut:]])
        assert_matches_expected(chunk, vector["expected"])
        assert decoder.stats.odd_bytes_dropped == 0
    chunk, _ = proto.decode_all(layout, [data[i : i + 2] for i in range(0, len(data), 2)])
    assert_matches_expected(chunk, vector["expected"])


def test_vector_every_byte_split_with_reassembly(vector, proto):
    data = b"".join(proto.transfers(vector))
    layout = proto.layout(vector)
    for cut in range(len(data) + 1):
        chunk, decoder = proto.decode_all(layout, [data[:cut], data[cut:]], reassemble_odd_bytes=True)
        assert_matches_expected(chunk, vector["expected"])
        assert decoder.stats.odd_bytes_dropped == 0
    chunk, _ = proto.decode_all(layout, [data[i : i + 1] for i in range(len(data))], reassemble_odd_bytes=True)
    assert_matches_expected(chunk, vector["expected"])


def test_v19_per_event_overflow_differs_from_libcaer_packet_quirk(vectors, proto):
    """V19: we report the intended per-event time; libcaer's stale packet overflow is exactly 2**31 lower."""
    vector = next(v for v in vectors if v["id"].startswith("V19"))
    chunk, decoder = proto.decode_all(proto.layout(vector), proto.transfers(vector))
    ours = proto.events_as_lists(chunk.events)
    libcaer = vector["expected"]["dvs_libcaer_actual"]
    assert ours == vector["expected"]["dvs"] == [[2**31 + 33768, 6, 5, 1]]
    assert ours != libcaer
    assert [e[0] - l[0] for e, l in zip(ours, libcaer)] == [2**31]
    assert [e[1:] for e in ours] == [l[1:] for l in libcaer]
    assert decoder.stats.big_wraps == 1


def test_v05_wrap_and_reset_special_times(vectors, proto):
    vector = next(v for v in vectors if v["id"].startswith("V05"))
    chunk, decoder = proto.decode_all(proto.layout(vector), proto.transfers(vector))
    # big wrap: 16*4095 + 17 wrap units = 2**31 + 32768 µs; reset: clock restarts at 0
    assert chunk.specials.tolist() == [(2**31 + 32768, SpecialType.TIMESTAMP_WRAP), (0, SpecialType.TIMESTAMP_RESET)]
    assert decoder.stats.timestamp_resets == 1
    assert decoder.stats.big_wraps == 1
    assert decoder.current_time_us == 20


# ---------------------------------------------------------------------------------------------- odd transfers
def test_odd_byte_dropped_like_libcaer_or_reassembled(davis346, proto):
    first = proto.words(timestamp_word(100), y_word(10), x_word(20, 1)) + b"\x15"  # low byte of 0x3015
    second = b"\x30" + proto.words(timestamp_word(102), x_word(22, 1))  # 5 bytes
    chunk, decoder = proto.decode_all(davis346, [first, second])
    # libcaer: each trailing odd byte dropped; the shifted second transfer is garbage (misc10 sub 1, Y 1664)
    assert proto.events_as_lists(chunk.events) == [[100, 20, 10, 1]]
    assert decoder.stats.odd_bytes_dropped == 2
    assert decoder.stats.unknown_words == 1
    assert decoder.stats.dvs_out_of_range == 1

    chunk, decoder = proto.decode_all(davis346, [first, second], reassemble_odd_bytes=True)
    assert proto.events_as_lists(chunk.events) == [[100, 20, 10, 1], [100, 21, 10, 1], [102, 22, 10, 1]]
    assert decoder.stats.odd_bytes_dropped == 0
    assert decoder.stats.words == 6


def test_empty_and_various_input_types(davis346, proto):
    data = proto.words(timestamp_word(7), y_word(3), x_word(4, 0))
    for transfer in (data, bytearray(data), memoryview(data), np.frombuffer(data, np.uint8)):
        decoder = StreamDecoder(davis346)
        assert len(decoder.feed(b"")) == 0
        assert proto.events_as_lists(decoder.feed(transfer).events) == [[7, 4, 3, 0]]


@pytest.mark.parametrize("bad", ["abc", 12, np.zeros(4, np.uint16), np.zeros((2, 2), np.uint8)])
def test_bad_transfer_type_raises(davis346, bad):
    with pytest.raises(ProtocolError, match="transfer"):
        StreamDecoder(davis346).feed(bad)


def test_bad_layout_raises():
    with pytest.raises(ProtocolError, match="SensorLayout"):
        StreamDecoder({"dvs_size_columns": 346})


# ---------------------------------------------------------------------------------------------- timestamps
def test_wrap_words_and_two_big_wraps(davis346, proto):
    stream = [timestamp_word(5), y_word(1), x_word(1, 1)]
    stream += [wrap_word(4095)] * 32 + [wrap_word(32)]  # 32*4095*2**15 + 32*2**15 = 2**32
    stream += [timestamp_word(5), x_word(2, 0)]
    chunk, decoder = proto.decode_all(davis346, [proto.words(*stream)])
    # the row address survives wraps; the X right after the wraps gets the new timestamp word's time
    assert proto.events_as_lists(chunk.events) == [[5, 1, 1, 1], [2**32 + 5, 2, 1, 0]]
    assert decoder.stats.big_wraps == 2
    first_crossing = 17 * 4095 * 2**15  # first multiple of the wrap sum >= 2**31
    assert chunk.specials.tolist() == [(first_crossing, SpecialType.TIMESTAMP_WRAP), (2**32, SpecialType.TIMESTAMP_WRAP)]


def test_event_after_wrap_without_timestamp_uses_wrap_base(davis346, proto):
    stream = [timestamp_word(32000), y_word(2), x_word(3, 1), wrap_word(2), x_word(4, 1)]
    chunk, _ = proto.decode_all(davis346, [proto.words(*stream)])
    assert proto.events_as_lists(chunk.events) == [[32000, 3, 2, 1], [65536, 4, 2, 1]]


def test_reset_then_events_restart_at_zero_and_keep_last_y(davis346, proto):
    stream = [timestamp_word(900), y_word(7), x_word(1, 1), special_word(1), x_word(2, 0), timestamp_word(3), x_word(5, 1)]
    chunk, decoder = proto.decode_all(davis346, [proto.words(*stream)])
    assert proto.events_as_lists(chunk.events) == [[900, 1, 7, 1], [0, 2, 7, 0], [3, 5, 7, 1]]
    assert decoder.stats.timestamp_resets == 1
    assert decoder.stats.non_monotonic_timestamps == 0


def test_non_monotonic_timestamps_are_counted_not_fixed(davis346, proto):
    stream = [timestamp_word(100), y_word(1), x_word(1, 1), timestamp_word(50), x_word(2, 1), timestamp_word(60)]
    decoder = StreamDecoder(davis346)
    chunk = decoder.feed(proto.words(*stream[:3]))
    chunk2 = decoder.feed(proto.words(*stream[3:]))
    assert proto.events_as_lists(chunk.events) + proto.events_as_lists(chunk2.events) == [[100, 1, 1, 1], [50, 2, 1, 1]]
    assert decoder.stats.non_monotonic_timestamps == 1


def test_block_boundaries_do_not_change_output(davis346):
    """A feed much longer than the internal block size equals feeding it in small transfers."""
    rng = np.random.default_rng(3)
    n = 100_000
    kinds = rng.integers(0, 4, n)
    stream = np.where(
        kinds == 0,
        0x8000 | rng.integers(0, 0x8000, n),
        np.where(kinds == 1, 0x1000 | rng.integers(0, 300, n), 0x2000 | rng.integers(0, 2, n) << 12 | rng.integers(0, 400, n)),
    ).astype("<u2")
    stream[rng.integers(0, n, 50)] = 0x7001  # some wraps
    stream[rng.integers(0, n, 3)] = 0x0001  # some resets
    data = stream.tobytes()
    whole_decoder = StreamDecoder(davis346)
    whole = whole_decoder.feed(data)
    parts_decoder = StreamDecoder(davis346)
    parts = DecodedChunk.concatenate([parts_decoder.feed(data[i : i + 8192]) for i in range(0, len(data), 8192)])
    assert len(whole.events) > 10_000
    np.testing.assert_array_equal(whole.events, parts.events)
    np.testing.assert_array_equal(whole.specials, parts.specials)
    assert whole_decoder.stats == parts_decoder.stats


# ---------------------------------------------------------------------------------------------- APS frames
def roi_words(start_col: int, start_row: int, end_col: int, end_row: int) -> list[int]:
    out = []
    for value in (start_col, start_row, end_col, end_row):
        out += [misc8_word(1, value >> 8), misc8_word(2, value & 0xFF)]
    return out


def column(kind: int, samples) -> list[int]:
    return [special_word(kind)] + [adc_word(s) for s in samples] + [special_word(13)]


def frame_1x2(reset=(900, 900), signal=(400, 100), roi=True) -> list[int]:
    """A GS frame with a 1-column × 2-row ROI at (5, 6): one reset column and one signal column of 2 samples."""
    words = [special_word(8)] + (roi_words(5, 6, 5, 7) if roi else [])
    words += column(11, reset) + [special_word(14), special_word(15)] + column(12, signal) + [special_word(10)]
    return words


def test_minimal_frame_and_roi_persistence(davis346, proto):
    stream = [timestamp_word(10)] + frame_1x2() + [timestamp_word(20)] + frame_1x2(signal=(1, 899), roi=False)
    chunk, decoder = proto.decode_all(davis346, [proto.words(*stream)])
    assert len(chunk.frames) == 2
    first, second = chunk.frames
    assert (first.position_x, first.position_y, first.pixels.shape) == (5, 6, (2, 1))
    assert first.pixels_10bit.ravel().tolist() == [500, 800]
    # second frame has no ROI words: the previous ROI and expected counts persist
    assert (second.position_x, second.position_y) == (5, 6)
    assert second.pixels_10bit.ravel().tolist() == [899, 1]
    assert second.t_start_of_frame_us == 20
    assert decoder.stats.aps_frames_dropped == 0


def test_cds_clamp_rules(davis346, proto):
    # reset < 384 → 1023; signal == 0 → 1023; negative → 0; above 1023 (12-bit samples) → 1023
    stream = [special_word(8)] + roi_words(0, 0, 0, 3)
    stream += column(11, [383, 900, 500, 4095]) + column(12, [100, 0, 600, 100]) + [special_word(10)]
    chunk, _ = proto.decode_all(davis346, [proto.words(*stream)])
    assert chunk.frames[0].pixels_10bit.ravel().tolist() == [1023, 1023, 0, 1023]


def test_data_before_first_frame_start_is_ignored(davis346, proto):
    stream = column(11, [900, 900]) + column(12, [1, 1]) + [special_word(10), special_word(14)] + frame_1x2()
    chunk, decoder = proto.decode_all(davis346, [proto.words(*stream)])
    assert len(chunk.frames) == 1
    assert [int(s) for s in chunk.specials["type"]] == [14, 16, 17, 15]
    assert decoder.stats.aps_samples_dropped == 4


def test_reset_during_frame_drops_it_until_next_frame_start(davis346, proto):
    partial = frame_1x2()[:-8]  # up to the middle of the signal column
    stream = partial + [special_word(1)] + [adc_word(5), special_word(13), special_word(10)] + frame_1x2()
    chunk, decoder = proto.decode_all(davis346, [proto.words(*stream)])
    assert len(chunk.frames) == 1
    assert decoder.stats.aps_frames_dropped == 1
    assert decoder.stats.aps_samples_dropped == 1


def test_big_wrap_during_frame_drops_it(davis346, proto):
    stream = frame_1x2()[:-1] + [wrap_word(4095)] * 17 + [special_word(10)]
    chunk, decoder = proto.decode_all(davis346, [proto.words(*stream)])
    assert chunk.frames == []
    assert decoder.stats.aps_frames_dropped == 1
    assert decoder.stats.big_wraps == 1


def test_wrong_column_count_drops_frame_extra_rows_are_ignored(davis346, proto):
    missing_signal = [special_word(8)] + roi_words(5, 6, 5, 7) + column(11, [900, 900]) + [special_word(10)]
    extra_rows = frame_1x2(signal=(400, 100, 7, 7))
    chunk, decoder = proto.decode_all(davis346, [proto.words(*(missing_signal + extra_rows))])
    assert len(chunk.frames) == 1
    assert chunk.frames[0].pixels_10bit.ravel().tolist() == [500, 800]
    assert decoder.stats.aps_frames_dropped == 1
    assert decoder.stats.aps_samples_dropped == 2


def test_frame_split_at_every_word_boundary(davis346, proto):
    data = proto.words(*([timestamp_word(10)] + frame_1x2() + [y_word(3), x_word(4, 1)]))
    for cut in range(0, len(data) + 1, 2):
        chunk, _ = proto.decode_all(davis346, [data[:cut], data[cut:]])
        assert [f.pixels_10bit.ravel().tolist() for f in chunk.frames] == [[500, 800]]
        assert proto.events_as_lists(chunk.events) == [[10, 4, 3, 1]]


def test_oversized_roi_falls_back_to_full_size(proto):
    layout = SensorLayout.from_mapping({**SensorLayout.davis346().to_dict(), "aps_size_columns": 2, "aps_size_rows": 2})
    stream = [special_word(8)] + roi_words(1, 1, 9, 9)  # 9 wide > 2 → full width; position reset to 0
    stream += column(11, [900, 900]) + column(11, [900, 900]) + column(12, [1, 2]) + column(12, [3, 4])
    stream += [special_word(10)]
    chunk, _ = proto.decode_all(layout, [proto.words(*stream)])
    frame = chunk.frames[0]
    assert (frame.position_x, frame.position_y) == (0, 0)
    assert frame.pixels_10bit.tolist() == [[899, 897], [898, 896]]


# ---------------------------------------------------------------------------------------------- IMU
def imu_sample(scale: int, data: list[int]) -> list[int]:
    return [special_word(5), misc8_word(3, scale)] + [misc8_word(0, b) for b in data] + [special_word(7)]


def test_imu_flips_and_mpu9250_temperature(proto):
    layout = SensorLayout.from_mapping({**SensorLayout.davis346().to_dict(), "imu_type": 2, "imu_orientation_info": 7})
    # accel FS 0 (16384 LSB/g), gyro FS 3 (16.384 LSB/dps), all sensors present
    data = [0x40, 0x00, 0x20, 0x00, 0xC0, 0x00, 0x00, 0x00, 0x00, 0x10, 0x00, 0x00, 0xFF, 0xF0]
    chunk, _ = proto.decode_all(layout, [proto.words(timestamp_word(42), *imu_sample(0b1110_0011, data))])
    sample = chunk.imu[0]
    assert int(sample["t"]) == 42
    np.testing.assert_allclose([sample["accel_x_g"], sample["accel_y_g"], sample["accel_z_g"]], [-1.0, -0.5, 1.0])
    np.testing.assert_allclose(
        [sample["gyro_x_dps"], sample["gyro_y_dps"], sample["gyro_z_dps"]], [-16 / 16.384, 0.0, 16 / 16.384], rtol=1e-6
    )
    assert float(sample["temperature_c"]) == pytest.approx(21.0)


def test_imu_accel_only_sample_has_six_bytes(davis346, proto):
    scale = 0b1000_0100  # accel only, accel FS 1 (8192 LSB/g)
    chunk, decoder = proto.decode_all(davis346, [proto.words(*imu_sample(scale, [0x20, 0, 0, 0, 0xE0, 0]))])
    assert chunk.imu[["accel_x_g", "accel_y_g", "accel_z_g"]].tolist() == [(1.0, 0.0, -1.0)]
    assert decoder.stats.imu_samples_dropped == 0


def test_imu_interrupted_by_reset_is_dropped(davis346, proto):
    stream = imu_sample(0xE5, [0] * 14)[:-3] + [special_word(1)] + [misc8_word(0, 0)] * 2 + [special_word(7)]
    chunk, decoder = proto.decode_all(davis346, [proto.words(*stream)])
    assert len(chunk.imu) == 0
    assert decoder.stats.imu_samples_dropped == 1


def test_stats_snapshot_is_independent(davis346, proto):
    decoder = StreamDecoder(davis346)
    before = decoder.stats
    decoder.feed(proto.words(special_word(0)))
    assert before.unknown_words == 0
    assert decoder.stats.unknown_words == 1
    assert decoder.stats.as_dict()["words"] == 1


@pytest.mark.parametrize("reassemble", [False, True])
def test_feed_many_equals_feeding_one_by_one(davis346, reassemble):
    rng = np.random.default_rng(11)
    stream = np.where(
        rng.random(20_000) < 0.3,
        0x8000 | rng.integers(0, 0x8000, 20_000),
        (rng.integers(1, 4, 20_000) << 12) | rng.integers(0, 300, 20_000),
    ).astype("<u2").tobytes()
    sizes = rng.integers(0, 3000, 40)
    transfers, pos = [], 0
    for size in sizes:
        transfers.append(stream[pos : pos + int(size)])
        pos += int(size)
    one = StreamDecoder(davis346, reassemble_odd_bytes=reassemble)
    expected = DecodedChunk.concatenate([one.feed(t) for t in transfers])
    many = StreamDecoder(davis346, reassemble_odd_bytes=reassemble)
    got = DecodedChunk.concatenate([many.feed_many(transfers[:15]), many.feed_many(transfers[15:])])
    np.testing.assert_array_equal(got.events, expected.events)
    assert len(got.events) > 1000
    assert many.stats == one.stats
    assert (many.stats.odd_bytes_dropped > 0) != reassemble


def test_data_loss_is_logged_once_per_kind(davis346, proto, caplog):
    decoder = StreamDecoder(davis346)
    with caplog.at_level("WARNING", logger="davis_rig.protocol.decoder"):
        decoder.feed(b"\x01")
        decoder.feed(proto.words(special_word(0), special_word(0)) + b"\x00")
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2
    assert "odd bytes dropped" in messages[0]
    assert "unknown words" in messages[1]
    assert decoder.stats.odd_bytes_dropped == 2 and decoder.stats.unknown_words == 2


def test_decode_words_validates_values(davis346):
    decoder = StreamDecoder(davis346)
    chunk = decoder.decode_words(np.array([0x8005, 0x1002, 0x3003], np.int64))
    assert chunk.events.tolist() == [(5, 3, 2, 1)]
    for bad in (np.array([70000]), np.array([-1]), np.array([1.5]), np.zeros((2, 2), np.uint16)):
        with pytest.raises(ProtocolError, match="words"):
            decoder.decode_words(bad)


@st.composite
def column_soup(draw):
    """APS word streams made of frame starts, ROIs, (mostly regular) columns, exposure and frame-end words."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    words: list[int] = []
    for _ in range(draw(st.integers(1, 4))):
        width, height = int(rng.integers(1, 5)), int(rng.integers(1, 5))
        words += [timestamp_word(int(rng.integers(0, 30000))), special_word(8)]
        if rng.random() < 0.8:
            words += roi_words(2, 3, 2 + width - 1, 3 + height - 1)
        for kind in (11, 12):
            for _ in range(int(rng.integers(0, width + 3))):
                rows = height if rng.random() < 0.8 else int(rng.integers(0, height + 2))
                words += column(kind, rng.integers(0, 1024, rows).tolist())
                if rng.random() < 0.05:
                    words.append(special_word(int(rng.choice([1, 14, 15]))))
        if rng.random() < 0.9:
            words.append(special_word(10))
    return words


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(column_soup(), st.integers(1, 64))
def test_bulk_column_path_equals_word_by_word_path(davis346, proto, stream, transfer_words):
    data = proto.words(*stream)
    transfers = [data[i : i + 2 * transfer_words] for i in range(0, len(data), 2 * transfer_words)]
    fast, fast_decoder = proto.decode_all(davis346, transfers)
    slow_decoder = StreamDecoder(davis346)
    slow_decoder._column_run = lambda *args: 0  # disable the bulk path
    slow = DecodedChunk.concatenate([slow_decoder.feed(t) for t in transfers])
    assert fast.frames == slow.frames
    np.testing.assert_array_equal(fast.specials, slow.specials)
    assert fast_decoder.stats == slow_decoder.stats
