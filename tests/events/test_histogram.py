"""Tests for the numpy stacked histogram: bit-exact vs the official RVT output, edge cases, windows."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.errors import FormatError, ShapeError
from davis_rig.events import (
    regular_window_ends,
    stacked_histogram,
    stacked_histograms,
    time_bins,
    window_indices,
)
from davis_rig.events.histogram import monotonic_timestamps
from davis_rig.types import make_events


def _official_torch_histogram(x, y, t_us, p, height, width, num_bins, count_cutoff):
    """Transcription of RVT's ``StackedHistogram.construct`` (fastmode=True), run with torch."""
    torch = pytest.importorskip("torch")
    x, y, time, pol = (torch.from_numpy(np.asarray(a, dtype=np.int64)) for a in (x, y, t_us, p))
    representation = torch.zeros((2, num_bins, height, width), dtype=torch.uint8)
    if x.numel() == 0:
        return representation.reshape(-1, height, width).numpy()
    t0_int = time[0]
    t1_int = time[-1]
    t_norm = time - t0_int
    t_norm = t_norm / max((t1_int - t0_int), 1)
    t_norm = t_norm * num_bins
    t_idx = torch.clamp(t_norm.floor(), max=num_bins - 1)
    indices = x.long() + width * y.long() + height * width * t_idx.long() + num_bins * height * width * pol.long()
    values = torch.ones_like(indices, dtype=torch.uint8)
    representation.put_(indices, values, accumulate=True)
    representation = torch.clamp(representation, min=0, max=count_cutoff)
    return representation.reshape(-1, height, width).numpy()


# --- golden tests against the official pre-processing ----------------------------------------------------
def test_matches_official_fixture_histograms(reference_windows):
    ref = reference_windows
    events = {k: ref[f"events_{k}"] for k in ("x", "y", "t_us", "p")}
    hist = stacked_histograms(events, ref["window_end_ts_us"])
    assert hist.dtype == np.uint8
    assert hist.shape == ref["hist_uint8_unpadded"].shape
    np.testing.assert_array_equal(hist, ref["hist_uint8_unpadded"])


def test_dense_counting_path_matches_official_fixture_histograms(reference_windows, monkeypatch):
    import davis_rig.events.histogram as histogram_module

    monkeypatch.setattr(histogram_module, "_SPARSE_FRACTION", 10**9)  # force the np.bincount path
    ref = reference_windows
    events = {k: ref[f"events_{k}"] for k in ("x", "y", "t_us", "p")}
    np.testing.assert_array_equal(stacked_histograms(events, ref["window_end_ts_us"]), ref["hist_uint8_unpadded"])


def test_structured_array_and_tuple_inputs_give_the_same_result(reference_windows):
    ref = reference_windows
    x, y, t_us, p = (ref[f"events_{k}"] for k in ("x", "y", "t_us", "p"))
    structured = make_events(t_us, x, y, p)
    ends = ref["window_end_ts_us"]
    np.testing.assert_array_equal(stacked_histograms(structured, ends), ref["hist_uint8_unpadded"])
    np.testing.assert_array_equal(stacked_histograms((x, y, t_us, p), ends), ref["hist_uint8_unpadded"])


def test_fixture_contains_the_wrap_and_clip_cases(reference_windows):
    # the fixtures have a 260-event hot cell (wraps to 4) and a 40-event cell (clipped to 10)
    hist = reference_windows["hist_uint8_unpadded"]
    assert hist.max() == 10
    assert (hist == 4).any()


# --- hand-made edge cases ----------------------------------------------------------------------------------
def test_single_event_goes_to_bin_zero_of_its_polarity():
    hist = stacked_histogram([5], [7], [123_456], [1])
    assert hist.shape == (20, 240, 304)
    assert hist[10, 7, 5] == 1
    assert int(hist.sum()) == 1


def test_all_events_with_one_timestamp_land_in_bin_zero():
    x = np.array([0, 1, 2, 3])
    hist = stacked_histogram(x, np.zeros(4, int), np.full(4, 777), np.array([0, 1, 0, 1]))
    assert hist[0, 0, 0] == 1 and hist[10, 0, 1] == 1 and hist[0, 0, 2] == 1 and hist[10, 0, 3] == 1
    assert int(hist.sum()) == 4


def test_first_and_last_event_times_define_the_bins():
    # window bounds play no role: t0 = 1000, t1 = 2000; the last event lands in bin 9, a mid event in bin 5
    hist = stacked_histogram([0, 1, 2], [0, 0, 0], [1000, 1500, 2000], [0, 0, 0])
    assert hist[0, 0, 0] == 1
    assert hist[5, 0, 1] == 1
    assert hist[9, 0, 2] == 1


def test_empty_window_is_all_zeros():
    hist = stacked_histogram(np.array([], np.int16), np.array([], np.int16), np.array([], np.int64), [])
    assert hist.shape == (20, 240, 304)
    assert hist.dtype == np.uint8
    assert not hist.any()


@pytest.mark.parametrize(("count", "expected"), [(9, 9), (10, 10), (11, 10), (255, 10), (256, 0), (260, 4)])
@pytest.mark.parametrize("dense", [False, True])
def test_uint8_wrap_happens_before_the_clip(count, expected, dense, monkeypatch):
    import davis_rig.events.histogram as histogram_module

    if dense:
        monkeypatch.setattr(histogram_module, "_SPARSE_FRACTION", 10**9)
    n = count
    hist = stacked_histogram(np.full(n, 3), np.full(n, 4), np.zeros(n, np.int64), np.ones(n, np.uint8))
    assert hist[10, 4, 3] == expected


def test_count_cutoff_and_bins_are_parameters():
    n = 7
    hist = stacked_histogram(
        np.full(n, 1), np.full(n, 1), np.arange(n), np.zeros(n, np.int64), height=3, width=2, num_bins=1, count_cutoff=5
    )
    assert hist.shape == (2, 3, 2)
    assert hist[0, 1, 1] == 5


def test_time_normalization_is_float32_like_torch():
    # span 2**24 + 1 µs: float32(8388608) / float32(16777217) * 10 floors to 5, exact arithmetic gives 4
    t_us = np.array([0, 8_388_608, 16_777_217])
    np.testing.assert_array_equal(time_bins(t_us), [0, 5, 9])
    official = _official_torch_histogram([0, 1, 2], [0, 0, 0], t_us, [0, 0, 0], 2, 4, 10, 10)
    np.testing.assert_array_equal(stacked_histogram([0, 1, 2], [0, 0, 0], t_us, [0, 0, 0], height=2, width=4), official)


def test_negative_polarity_encoding_maps_to_off():
    hist = stacked_histogram([0, 1], [0, 0], [0, 10], [-1, 1], height=1, width=2)
    assert hist[0, 0, 0] == 1
    assert hist[19, 0, 1] == 1


def test_inputs_are_not_modified():
    x = np.array([1, 2, 3], np.int16)
    y = np.array([0, 1, 2], np.int16)
    t_us = np.array([0, 5, 9], np.int64)
    p = np.array([-1, 1, 0], np.int8)
    copies = [a.copy() for a in (x, y, t_us, p)]
    stacked_histogram(x, y, t_us, p)
    for original, copy in zip((x, y, t_us, p), copies):
        np.testing.assert_array_equal(original, copy)


# --- validation ---------------------------------------------------------------------------------------------
def test_coordinates_outside_the_frame_raise_shape_error():
    with pytest.raises(ShapeError, match=r"0 <= x < 304.*got x in \[0, 345\]"):
        stacked_histogram([0, 345], [0, 0], [0, 1], [0, 0])
    with pytest.raises(ShapeError, match="0 <= y < 240"):
        stacked_histogram([0], [240], [0], [0])


def test_mismatched_columns_raise_shape_error():
    with pytest.raises(ShapeError, match=r"x: expected shape \(2,\)"):
        stacked_histogram([0, 1, 2], [0, 0], [0, 1], [0, 0])


def test_bad_polarity_time_order_and_dtype_raise_format_error():
    with pytest.raises(FormatError, match="polarity"):
        stacked_histogram([0], [0], [0], [2])
    with pytest.raises(FormatError, match="non-decreasing"):
        stacked_histogram([0, 1], [0, 0], [10, 5], [0, 0])
    with pytest.raises(FormatError, match="non-decreasing"):
        stacked_histogram([0, 1], [0, 0], np.array([10, 5], np.uint64), [0, 0])
    with pytest.raises(FormatError, match="integer"):
        stacked_histogram([0.5], [0], [0], [0])


def test_unsupported_event_container_raises_format_error():
    with pytest.raises(FormatError, match="expected a structured"):
        stacked_histograms("events", [50_000])
    with pytest.raises(FormatError, match="lacks keys"):
        stacked_histograms({"x": [0], "y": [0]}, [50_000])


# --- official timestamp correction (H5Reader._correct_time) ------------------------------------------------
def _official_correct_time(t_us):
    """Transcription of RVT's ``H5Reader._correct_time`` (in place on a copy; numba loop run as Python)."""
    time_array = np.array(t_us, dtype=np.int64)
    assert time_array[0] >= 0
    time_last = 0
    for idx, time in enumerate(time_array):
        if time < time_last:
            time_array[idx] = time_last
        else:
            time_last = time
    return time_array


def test_monotonic_timestamps_is_the_running_maximum():
    t_us = np.array([0, 10, 5, 20, 15, 15, 30, 29, 31], np.int64)
    before = t_us.copy()
    corrected = monotonic_timestamps(t_us)
    np.testing.assert_array_equal(corrected, [0, 10, 10, 20, 20, 20, 30, 30, 31])
    np.testing.assert_array_equal(corrected, _official_correct_time(t_us))
    np.testing.assert_array_equal(t_us, before)  # input untouched
    assert corrected.dtype == np.int64
    np.testing.assert_array_equal(monotonic_timestamps(np.array([3, 1, 2], np.uint32)), [3, 3, 3])
    assert monotonic_timestamps(np.zeros(0, np.int64)).shape == (0,)
    rng = np.random.default_rng(0)
    jittered = np.cumsum(rng.integers(0, 50, 2000)) + rng.integers(-200, 200, 2000)
    jittered[0] = 0
    np.testing.assert_array_equal(monotonic_timestamps(jittered), _official_correct_time(jittered))
    with pytest.raises(FormatError, match="integer"):
        monotonic_timestamps([0.5, 1.0])


def test_stacked_histograms_correct_time_applies_the_official_rule_before_windowing():
    # events 2 and 4 are out of order; corrected times: 0, 30, 30, 50, 50, 90 ms
    t_us = np.array([0, 30_000, 20_000, 50_000, 40_000, 90_000], np.int64)
    x = np.arange(6)
    y = np.zeros(6, np.int64)
    p = np.ones(6, np.int64)
    ends = [50_000, 100_000]
    with pytest.raises(FormatError, match="non-decreasing.*correct_time=True"):
        stacked_histograms((x, y, t_us, p), ends)
    before = t_us.copy()
    hist = stacked_histograms((x, y, t_us, p), ends, correct_time=True)
    np.testing.assert_array_equal(t_us, before)  # the caller's timestamps are not modified
    corrected = np.array([0, 30_000, 30_000, 50_000, 50_000, 90_000])
    np.testing.assert_array_equal(hist, stacked_histograms((x, y, corrected, p), ends))
    # window 1 (0..50 ms): event 2 shares event 1's bin 6; event 4, now at 50 ms, is the last one (bin 9)
    assert hist[0, 16, 0, 1] == 1 and hist[0, 16, 0, 2] == 1 and hist[0, 19, 0, 3] == 1 and hist[0, 19, 0, 4] == 1
    # window 2 (50..100 ms): events 3 and 4 are its first events (bin 0), event 5 its last (bin 9)
    assert hist[1, 10, 0, 3] == 1 and hist[1, 10, 0, 4] == 1 and hist[1, 19, 0, 5] == 1
    assert int(hist[0].sum()) == 5 and int(hist[1].sum()) == 3


_CORRECT_TIME_HINT = "(stacked_histograms(..., correct_time=True) applies the official running-maximum correction)"


def test_a_step_back_within_a_window_names_the_event_and_its_times():
    with pytest.raises(FormatError) as info:
        stacked_histogram([0, 1, 2], [0, 0, 0], [10, 20, 5], [0, 0, 0], height=1, width=3)
    assert str(info.value) == ("t_us: expected non-decreasing timestamps within a window, but event 2 at 5 µs comes "
                               f"after 20 µs {_CORRECT_TIME_HINT}")


def test_a_step_back_between_windows_is_detected_and_corrected_across_them():
    # event 4 steps back from 120 ms (window 3) to 70 ms: no window's own slice holds both, so checking each
    # window alone missed it (window 3 came out empty; corrected, it holds events 3 and 4)
    t_us = np.array([50_000, 50_000, 70_000, 120_000, 70_000], np.int64)
    ends = np.array([50_000, 100_000, 150_000])
    starts, stops = window_indices(t_us, ends)
    assert all(np.all(np.diff(t_us[a:b]) >= 0) for a, b in zip(starts, stops))
    x, y, p = np.arange(5), np.zeros(5, np.int64), np.ones(5, np.int64)
    with pytest.raises(FormatError) as info:
        stacked_histograms((x, y, t_us, p), ends, height=1, width=5)
    assert str(info.value) == ("t_us: expected non-decreasing timestamps in the event stream, but event 4 at 70000 "
                               f"µs comes after 120000 µs {_CORRECT_TIME_HINT}")
    # correct_time=True: the running maximum carries across the windows (event 4 -> 120 ms, into window 3)
    hist = stacked_histograms((x, y, t_us, p), ends, height=1, width=5, num_bins=2, correct_time=True)
    corrected = np.array([50_000, 50_000, 70_000, 120_000, 120_000])
    np.testing.assert_array_equal(hist, stacked_histograms((x, y, corrected, p), ends, height=1, width=5,
                                                           num_bins=2))
    np.testing.assert_array_equal(hist[:, 2:].sum(1)[:, 0], [[1, 1, 0, 0, 0], [1, 1, 1, 0, 0], [0, 0, 0, 1, 1]])
    np.testing.assert_array_equal(t_us, [50_000, 50_000, 70_000, 120_000, 70_000])  # caller's array untouched


def test_a_step_back_outside_every_window_is_detected():
    # windows [25, 50] and [125, 150] ms; the step back 160 -> 80 ms lies in neither, yet it misleads the binary
    # search: unchecked, event 3 (140 ms) landed in window 2, which is empty once the times are corrected (160 ms)
    t_us = np.array([30_000, 160_000, 80_000, 140_000])
    columns = (np.arange(4), np.zeros(4, int), t_us, np.ones(4, int))
    with pytest.raises(FormatError) as info:
        stacked_histograms(columns, [50_000, 150_000], window_us=25_000, height=1, width=4)
    assert str(info.value) == ("t_us: expected non-decreasing timestamps in the event stream, but event 2 at 80000 "
                               f"µs comes after 160000 µs {_CORRECT_TIME_HINT}")
    hist = stacked_histograms(columns, [50_000, 150_000], window_us=25_000, height=1, width=4, correct_time=True)
    assert hist.reshape(2, -1).sum(1).tolist() == [1, 0]


# --- windows ------------------------------------------------------------------------------------------------
def test_window_is_inclusive_at_both_ends():
    t_us = np.array([0, 49_999, 50_000, 50_001, 100_000, 100_001])
    assert window_indices(t_us, 50_000) == (0, 3)
    assert window_indices(t_us, 100_000) == (2, 5)
    starts, stops = window_indices(t_us, np.array([50_000, 100_000, 150_000]))
    np.testing.assert_array_equal(starts, [0, 2, 4])
    np.testing.assert_array_equal(stops, [3, 5, 6])


def test_boundary_event_is_counted_in_both_windows():
    t_us = np.array([10_000, 50_000, 90_000])
    x = np.array([1, 2, 3])
    hist = stacked_histograms((x, np.zeros(3, int), t_us, np.ones(3, int)), [50_000, 100_000])
    # window 1: events at 10 ms and 50 ms -> the boundary event is the last one (bin 9)
    assert hist[0, 19, 0, 2] == 1 and hist[0, 10, 0, 1] == 1
    # window 2: events at 50 ms and 90 ms -> the boundary event is now the first one (bin 0)
    assert hist[1, 10, 0, 2] == 1 and hist[1, 19, 0, 3] == 1
    assert int(hist[0].sum()) == 2 and int(hist[1].sum()) == 2


def test_window_without_events_is_zero_and_custom_window_length():
    t_us = np.array([0, 10, 20])
    hist = stacked_histograms((np.zeros(3, int), np.zeros(3, int), t_us, np.zeros(3, int)), [20, 500], window_us=10)
    assert int(hist[0].sum()) == 2
    assert not hist[1].any()


def test_regular_window_ends():
    np.testing.assert_array_equal(regular_window_ends(0, 150_000), [50_000, 100_000, 150_000])
    np.testing.assert_array_equal(regular_window_ends(0, 149_999), [50_000, 100_000])
    np.testing.assert_array_equal(regular_window_ends(1_000, 300_000, step_us=125_000), [51_000, 176_000])
    assert regular_window_ends(0, 49_999).shape == (0,)
    with pytest.raises(ShapeError, match="expected > 0"):
        regular_window_ends(0, 10, window_us=0)


# --- property test against a transcription of the official torch code ---------------------------------------
@settings(max_examples=40, deadline=None)
@given(
    data=st.lists(
        st.tuples(st.integers(0, 5), st.integers(0, 3), st.integers(0, 300), st.integers(0, 1)),
        min_size=0,
        max_size=400,
    ),
    num_bins=st.integers(1, 4),
    dense=st.booleans(),
)
def test_matches_official_transcription_on_random_windows(data, num_bins, dense):
    import davis_rig.events.histogram as histogram_module

    fraction = histogram_module._SPARSE_FRACTION
    histogram_module._SPARSE_FRACTION = 10**9 if dense else 0
    rows = np.array(data, dtype=np.int64).reshape(-1, 4)
    rows = rows[np.argsort(rows[:, 2], kind="stable")]
    x, y, t_us, p = rows.T
    expected = _official_torch_histogram(x, y, t_us, p, 4, 6, num_bins, 3)
    try:
        got = stacked_histogram(x, y, t_us, p, height=4, width=6, num_bins=num_bins, count_cutoff=3)
    finally:
        histogram_module._SPARSE_FRACTION = fraction
    np.testing.assert_array_equal(got, expected)
