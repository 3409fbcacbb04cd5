"""The live windows' histograms, built as chunks arrive, equal the batch histograms of the whole windows."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.events.crop import crop_events
from davis_rig.events.histogram import stacked_histogram, window_indices
from davis_rig.types import make_events
from davis_rig.viewer.live_windows import WindowHistograms, crop_parts

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
    return [window for part in parts for window in histograms.push(part)]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), pieces=st.integers(1, 40), n=st.sampled_from([300, 5_000, 60_000]),
       on_ends=st.booleans())
def test_incremental_histograms_equal_the_batch_histograms(seed, pieces, n, on_ends):
    rng = np.random.default_rng(seed)
    events = stream(rng, n, on_ends=on_ends)
    cuts = np.sort(rng.integers(0, len(events), pieces - 1))
    windows = push_all(WindowHistograms(ORIGIN), np.split(events, cuts))
    ends = 3_000 + 50_000 * np.arange(1, len(windows) + 1)
    assert [w.end_us for w in windows] == ends.tolist()
    assert ends[-1] < events["t"][-1] <= ends[-1] + 50_000  # every window an event has passed, no more
    for window, (expected, count) in zip(windows, batch_histograms(events, ends)):
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
    events = make_events([1_000, 20_000, 51_000, 51_001, 120_000], [100] * 5, [100] * 5, [1] * 5)
    histograms = WindowHistograms(ORIGIN)
    assert histograms.push(events[:3]) == []  # 51_000 is the first window's end, not after it
    done = histograms.push(events[3:])
    assert [(w.end_us, w.completed_at, w.events) for w in done] == [(51_000, 0, 3), (101_000, 1, 2)]
    assert histograms.push(events[:0]) == []


def test_time_going_back_restarts_the_grid_and_the_sequence():
    rng = np.random.default_rng(1)
    histograms = WindowHistograms(ORIGIN)
    assert len(histograms.push(stream(rng, 3_000, span_us=300_000, t0_us=1_000_000))) == 5
    after = histograms.push(stream(rng, 3_000, span_us=120_000, t0_us=0))
    assert [(w.end_us, w.starts_sequence) for w in after] == [(50_000, True), (100_000, False)]


def test_crop_parts_are_crop_events():
    events = stream(np.random.default_rng(4), 20_000)
    expected = crop_events(events, ORIGIN)
    for got, name in zip(crop_parts(events, ORIGIN), "xytp"):
        np.testing.assert_array_equal(got, expected[name])


@pytest.mark.parametrize("origin", [(0, 0), (42, 20)])
def test_the_crop_origin_is_honoured(origin):
    events = stream(np.random.default_rng(5), 20_000, span_us=120_000)
    windows = push_all(WindowHistograms(origin), np.array_split(events, 4))
    for window, (expected, _) in zip(windows, batch_histograms(events, [w.end_us for w in windows], origin)):
        np.testing.assert_array_equal(window.histogram, expected)
