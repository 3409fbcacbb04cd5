"""The recording-time kernels: repaired timestamps, discontinuities, the other streams' clock and shifts."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.session.timeline import advance_clock, plan_event_times, shift_for

GAP = 1_000_000


def plan(t, last=None, clock=None, gap=GAP):
    return plan_event_times(np.array(t, np.int64), last, clock, gap)


def test_a_valid_stream_is_unchanged():
    t = [5, 5, 7, 1000, 1000, 900_000]
    result = plan(t, last=5)
    np.testing.assert_array_equal(result.t_us, t)
    assert result.repaired == 0 and result.shifts == []


def test_a_run_that_alone_goes_back_gets_the_previous_time():
    result = plan([100, 200, 200, 150, 150, 300])
    np.testing.assert_array_equal(result.t_us, [100, 200, 200, 200, 200, 300])
    assert result.repaired == 2 and result.shifts == []


def test_a_run_that_alone_sticks_out_gets_the_previous_time():
    # one corrupt timestamp word 20 ms ahead: its events are repaired, the later ones kept as they are
    result = plan([100, 200, 20_200, 20_200, 300, 400])
    np.testing.assert_array_equal(result.t_us, [100, 200, 200, 200, 300, 400])
    assert result.repaired == 2 and result.shifts == []


def test_a_run_that_alone_jumps_far_ahead_gets_the_previous_time():
    result = plan([0, 10, 5_000_000, 20])
    np.testing.assert_array_equal(result.t_us, [0, 10, 10, 20])
    assert result.repaired == 1 and result.shifts == []


def test_time_that_keeps_going_back_continues_from_the_last_time():
    # a lost wrap word: the next epoch's timestamps restart low
    result = plan([30_000, 31_000, 500, 1_500, 2_500])
    np.testing.assert_array_equal(result.t_us, [30_000, 31_000, 31_000, 32_000, 33_000])
    assert result.repaired == 0 and result.shifts == [(2, 30_500)]


def test_a_sparse_stream_that_goes_back_is_a_discontinuity_not_a_spike():
    # 200 does not stick out by more than its neighbours' spacing: keep it, shift the rest
    result = plan([100, 200, 150, 180])
    np.testing.assert_array_equal(result.t_us, [100, 200, 200, 230])
    assert result.repaired == 0 and result.shifts == [(2, 50)]


def test_an_unconfirmed_forward_jump_continues_1_us_later():
    result = plan([0, 10, 10 + 5 * GAP, 20 + 5 * GAP])
    np.testing.assert_array_equal(result.t_us, [0, 10, 11, 21])
    assert result.shifts == [(2, -(5 * GAP - 1))]
    np.testing.assert_array_equal(result.seg_shift_us, [0, -(5 * GAP - 1)])


def test_a_jump_at_the_batch_start_is_measured_from_the_last_time():
    result = plan([3 * GAP, 3 * GAP + 5], last=100)
    np.testing.assert_array_equal(result.t_us, [101, 106])
    assert result.shifts == [(0, 101 - 3 * GAP)]
    result = plan([50, 150], last=100)  # the first run alone went back
    np.testing.assert_array_equal(result.t_us, [100, 150])
    assert result.repaired == 1


def test_a_jump_bridged_by_the_clock_is_kept():
    clock = advance_clock(10, np.arange(1, 6) * 800_000, GAP)  # frames every 0.8 s
    assert clock == 4_000_000
    result = plan([4_100_000], last=10, clock=clock)
    np.testing.assert_array_equal(result.t_us, [4_100_000])
    assert result.shifts == []


def test_without_max_gap_forward_jumps_are_kept():
    result = plan([0, 10**12, 10**12 + 1], gap=None)
    np.testing.assert_array_equal(result.t_us, [0, 10**12, 10**12 + 1])


def test_advance_clock_stops_at_the_first_gap_and_ignores_the_past():
    assert advance_clock(None, np.array([5, 3, 9_000_000, 1_000_003]), GAP) == 1_000_003
    assert advance_clock(100, np.array([50, 60]), GAP) == 100
    assert advance_clock(100, np.zeros(0, np.int64), GAP) == 100
    assert advance_clock(None, np.array([7, 10**12]), None) == 10**12


def test_shift_for_takes_the_nearest_stretch_and_the_later_one_on_ties():
    lo, hi, shift = np.array([0, 500]), np.array([100, 900]), np.array([0, -7])
    np.testing.assert_array_equal(shift_for(np.array([50, 120, 300, 700, 2000]), lo, hi, shift), [0, 0, -7, -7, -7])
    np.testing.assert_array_equal(shift_for(np.array([1, 2]), lo[:1], hi[:1], np.array([4])), [4, 4])


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 10**10), min_size=1, max_size=60), st.one_of(st.none(), st.integers(0, 10**10)))
def test_output_is_monotonic_bounded_and_keeps_every_event(times, last):
    t = np.array(times, np.int64)
    result = plan_event_times(t, last, None, GAP)
    out = result.t_us
    assert out.shape == t.shape
    steps = np.diff(np.concatenate([[last], out]) if last is not None else out)
    assert np.all(steps >= 0) and np.all(steps <= GAP)  # monotonic, and the span grows at most GAP per run
    for index, shift in result.shifts:
        assert out[index] == t[index] + shift


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, GAP), min_size=1, max_size=60))
def test_sorted_input_without_long_gaps_is_returned_unchanged(steps):
    t = np.cumsum(np.array(steps, np.int64))
    result = plan_event_times(t, None, None, GAP)
    np.testing.assert_array_equal(result.t_us, t)
    assert result.repaired == 0 and result.shifts == []
