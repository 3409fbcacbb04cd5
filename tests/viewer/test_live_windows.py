"""The live windows' histograms, built as chunks arrive, equal the batch histograms of the whole windows."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.events.crop import crop_events
from davis_rig.events.histogram import stacked_histogram, time_bins, window_indices
from davis_rig.types import make_events
from davis_rig.viewer.live_windows import WindowHistograms, bin_starts, crop_cells, join_events, later_window

ORIGIN = (21, 10)


def stream(rng, n, span_us=400_000, t0_us=3_456, on_ends=True):
    """Sorted sensor events; with ``on_ends``, some on every window end of the grid (inside the crop)."""
    t = rng.integers(t0_us, t0_us + span_us, n)
    t[0] = t0_us
    x, y = rng.integers(0, 346, n), rng.integers(0, 260, n)
    if on_ends:
        ends = t0_us // 1000 * 1000 + 50_000 * np.arange(1, span_us // 50_000 + 1)
        t = np.concatenate([t, np.repeat(ends, 3)])
        x = np.concatenate([x, np.full(3 * len(ends), 100)])
        y = np.concatenate([y, np.full(3 * len(ends), 100)])
    order = np.argsort(t, kind="stable")
    return make_events(t[order], x[order], y[order], rng.integers(0, 2, len(t)))


def batch_histograms(events, ends, origin=ORIGIN):
    """The reference: each whole window cropped, its times made non-decreasing, then the official histogram;
    ``[(histogram, events in the crop)]``."""
    starts, stops = window_indices(events["t"], ends, 50_000)
    out = []
    for a, b in zip(starts, stops):
        window = crop_events(events[a:b], origin)
        out.append((stacked_histogram(window["x"], window["y"], np.maximum.accumulate(window["t"]), window["p"]),
                    len(window)))
    return out


def push_all(histograms, parts):
    return [window for part in parts if (window := histograms.push(part)) is not None]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), pieces=st.integers(1, 40), n=st.sampled_from([300, 5_000, 60_000]),
       on_ends=st.booleans())
def test_incremental_histograms_equal_the_batch_histograms(seed, pieces, n, on_ends):
    rng = np.random.default_rng(seed)
    events = stream(rng, n, on_ends=on_ends)
    parts = np.split(events, np.sort(rng.integers(0, len(events), pieces - 1)))
    histograms = WindowHistograms(ORIGIN)
    windows = push_all(histograms, parts)
    complete = 3_000 + 50_000 * np.arange(1, (int(events["t"][-1]) - 3_001) // 50_000 + 1)  # an event after each
    # each push gives the newest window it completes; those before it in the same push are only tallied
    expected_ends = sorted({int(complete[complete < part["t"][-1]].max()) for part in parts
                            if len(part) and (complete < part["t"][-1]).any()})
    assert [w.end_us for w in windows] == expected_ends
    assert len(windows) + histograms.superseded == len(complete)
    for window, (expected, count) in zip(windows, batch_histograms(events, expected_ends)):
        np.testing.assert_array_equal(window.histogram, expected)
        assert window.events == count
    assert [w.starts_sequence for w in windows] == [True] + [False] * (len(windows) - 1)


def test_both_ways_of_binning_give_the_batch_histogram():
    """Windows whose last crop event is on the end (binned on arrival) and windows whose last is earlier
    (recounted) in one stream, with counts above the uint8 wrap and the cutoff."""
    rng = np.random.default_rng(3)
    dense = stream(rng, 40_000, span_us=200_000)
    hot = make_events(np.full(272, 60_000), np.r_[np.full(260, 50), np.full(12, 60)], np.full(272, 40),
                      np.ones(272, int))  # 260 events in one cell wrap to 4, 12 in another are clipped to 10
    events = np.sort(np.concatenate([dense, hot]), order="t", kind="stable")
    events = events[(events["t"] < 100_000) | (events["t"] > 103_000)]  # window 2 ends with no event on its end
    windows = push_all(WindowHistograms(ORIGIN), np.array_split(events, 13))
    ends = [w.end_us for w in windows]
    assert ends == [53_000, 103_000, 153_000, 203_000]
    for window, (expected, _) in zip(windows, batch_histograms(events, ends)):
        np.testing.assert_array_equal(window.histogram, expected)
    assert windows[1].histogram[11, 30, 29] < 10 and windows[1].histogram[11, 30, 39] == 10


def test_the_completing_event_is_named_and_windows_need_an_event_after_their_end():
    events = make_events([1_000, 20_000, 51_000, 51_001, 60_000, 120_000], [100] * 6, [100] * 6, [1] * 6)
    histograms = WindowHistograms(ORIGIN)
    assert histograms.push(events[:3]) is None  # 51_000 is the first window's end, not after it
    window = histograms.push(events[3:5])
    assert (window.end_us, window.completed_at, window.events, window.starts_sequence) == (51_000, 0, 3, True)
    assert histograms.push(events[:0]) is None


def test_a_push_completing_several_windows_gives_the_newest_and_a_new_sequence_stays_new():
    rng = np.random.default_rng(1)
    histograms = WindowHistograms(ORIGIN)
    old = stream(rng, 3_000, span_us=300_000, t0_us=1_000_000)
    window = histograms.push(old)
    assert (window.end_us, window.starts_sequence, histograms.superseded) == (1_250_000, True, 4)
    new = stream(rng, 3_000, span_us=120_000, t0_us=0)  # time went back: a new grid, a new sequence
    window = histograms.push(new)
    assert (window.end_us, window.starts_sequence, histograms.superseded) == (100_000, True, 5)
    np.testing.assert_array_equal(window.histogram, batch_histograms(new, [100_000])[0][0])


def test_crop_cells_are_crop_events_in_bin_0():
    events = stream(np.random.default_rng(4), 20_000)
    expected = crop_events(events, ORIGIN)
    cells, t = crop_cells(events, ORIGIN)
    x, y, p = (expected[name].astype(np.int64) for name in "xyp")
    np.testing.assert_array_equal(cells, x + 304 * y + 10 * 240 * 304 * p)
    np.testing.assert_array_equal(t, expected["t"])


@pytest.mark.parametrize("first_us, last_us", [(0, 50_000), (1_234_567, 1_284_567), (7, 49_999), (3, 3), (5, 11),
                                                (1_000, 1_000 + 2**23)])
def test_bin_starts_bin_every_time_as_the_float32_formula(first_us, last_us):
    t = np.arange(first_us, last_us + 1) if last_us - first_us < 10**6 else \
        np.unique(np.r_[np.arange(first_us, first_us + 1_000), np.random.default_rng(0).integers(first_us, last_us, 10**6),
                        last_us])
    starts = bin_starts(first_us, last_us)
    np.testing.assert_array_equal(np.searchsorted(starts, t, side="right"),
                                  time_bins(t, first_us=first_us, last_us=last_us))


@pytest.mark.parametrize("origin", [(0, 0), (42, 20)])
def test_the_crop_origin_is_honoured(origin):
    events = stream(np.random.default_rng(5), 20_000, span_us=120_000)
    windows = push_all(WindowHistograms(origin), np.array_split(events, 12))
    for window, (expected, _) in zip(windows, batch_histograms(events, [w.end_us for w in windows], origin)):
        np.testing.assert_array_equal(window.histogram, expected)


def test_join_events_is_concatenate_and_a_view_where_the_parts_follow_each_other():
    events = stream(np.random.default_rng(6), 1_000)
    adjacent = np.array_split(events, 5)
    joined = join_events(adjacent)
    np.testing.assert_array_equal(joined, events)
    assert np.shares_memory(joined, events) and join_events(adjacent[:1]) is adjacent[0]
    apart = [adjacent[0], adjacent[2]]  # one buffer, not adjacent: copied
    joined = join_events(apart)
    np.testing.assert_array_equal(joined, np.concatenate(apart))
    assert not np.shares_memory(joined, events)
    copies = [part.copy() for part in adjacent]
    np.testing.assert_array_equal(join_events(copies), events)


def test_a_window_replacing_the_start_of_a_sequence_starts_it():
    histograms = WindowHistograms(ORIGIN)
    first = histograms.push(stream(np.random.default_rng(9), 2_000, span_us=60_000))
    second = histograms.push(stream(np.random.default_rng(10), 2_000, span_us=60_000, t0_us=63_456))
    assert first.starts_sequence and not second.starts_sequence
    assert later_window(first, second).starts_sequence and later_window(first, second).end_us == second.end_us
    assert later_window(second, first) is first and later_window(second, second) is second


def test_a_jump_ahead_in_time_skips_to_the_newest_window_at_once():
    events = make_events([1_000, 2_000, 3_600_000_000_000, 3_600_000_000_001], [100] * 4, [100] * 4, [1] * 4)
    histograms = WindowHistograms(ORIGIN)
    assert histograms.push(events[:2]) is None
    window = histograms.push(events[2:])  # an hour of windows: counted, not built one by one
    assert window.end_us == 3_599_999_951_000 and window.events == 0
    assert histograms.superseded == (3_599_999_951_000 - 51_000) // 50_000
