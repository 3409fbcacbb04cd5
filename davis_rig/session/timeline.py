"""Recording time of a corrupt-tolerant event stream: repair bad timestamps, bridge implausible jumps (pure kernels).

A DAVIS word stream can carry damaged timestamps (a flipped bit on the cable, a replay file shifted by a byte, a
bug upstream). libcaer passes them on: one bad timestamp word puts the events that share it out of order, one bad
wrap word moves every later event seconds to months ahead, a lost wrap word moves them 32.768 ms back. A session
file needs the opposite: event times that never go back (``ms_to_idx`` is a sorted index) and a time span
proportional to the data (``ms_to_idx`` has one entry per millisecond). :func:`plan_event_times` maps the event
times of one batch (in stream order) onto such a recording time, keeping every event:

* **Repaired timestamps** (the timestamp is quarantined, the event kept): a run of events sharing one time (the
  events of one timestamp word) that alone goes back, while the run after it comes back up, gets the previous
  run's time; a run that alone jumps ahead (the run after it falls back between the two) gets the previous run's
  time too, and so does a run that alone stuck out above both neighbours when the next run goes back (only if it
  stuck out by more than the spacing of its neighbours, so a sparse stream's lost wrap does not look like one).
* **Discontinuities** (the stream resynchronises, as libcaer does at its next wrap or reset): time that keeps going
  back (a lost wrap word) continues from the last time written; a forward jump of more than ``max_gap_us`` that is
  not confirmed by other data (a bad wrap word) continues 1 µs after it. The time shift from then on is returned
  so the caller can record it (device time = recording time - offset).

A jump is confirmed when the other streams (APS frames, IMU samples, special events) have items whose times bridge
it in steps of at most ``max_gap_us`` (:func:`advance_clock`), e.g. a dark, static scene that sends frames but
almost no events.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["EventTimes", "advance_clock", "plan_event_times", "shift_for"]

#: Items × segments compared at once by :func:`shift_for` (bounds its temporary memory to a few MiB).
_SHIFT_BLOCK: int = 1 << 18


@dataclass(frozen=True)
class EventTimes:
    """The recording times :func:`plan_event_times` chose for one batch of events.

    Attributes:
        t_us: int64 [N] recording time of each event, non-decreasing and >= the previous batch's last time.
        repaired: number of events whose timestamp was replaced by the previous run's time.
        shifts: ``(event index, shift µs)`` for each discontinuity: from that event on, recording time = input
            time + shift (the shift before the first entry is 0), in stream order.
        seg_lo_us, seg_hi_us, seg_shift_us: int64 [S] input-time range and shift of each stretch of events between
            discontinuities (repaired runs excluded), for mapping the other streams with :func:`shift_for`.
    """

    t_us: np.ndarray
    repaired: int = 0
    shifts: list = field(default_factory=list)
    seg_lo_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    seg_hi_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    seg_shift_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def advance_clock(clock_us: int | None, times_us: np.ndarray, max_gap_us: int | None) -> int | None:
    """Latest time reachable from ``clock_us`` through ``times_us`` in steps of at most ``max_gap_us``.

    Args:
        clock_us: the latest plausible time so far, µs (``None``: none yet; the earliest time starts the chain).
        times_us: int64 [M] times of other items, µs, any order.
        max_gap_us: largest step, µs (``None``: any step; the result is then the maximum).

    Returns:
        The new clock, µs (``clock_us`` when no item extends it).
    """
    times = np.asarray(times_us, dtype=np.int64)
    if not times.shape[0]:
        return clock_us
    if max_gap_us is None:
        top = int(times.max())
        return top if clock_us is None else max(clock_us, top)
    times = np.sort(times)
    if clock_us is not None:
        times = times[times > clock_us]
        if not times.shape[0]:
            return clock_us
        chain = np.concatenate([[clock_us], times])
    else:
        chain = times
    breaks = np.flatnonzero(np.diff(chain) > max_gap_us)
    return int(chain[breaks[0]] if breaks.shape[0] else chain[-1])


def plan_event_times(t_us: np.ndarray, last_us: int | None, clock_us: int | None,
                     max_gap_us: int | None) -> EventTimes:
    """Choose monotonic recording times for one batch of event times (module docstring: the rules).

    Args:
        t_us: int64 [N] event times in stream order, µs (device time plus the caller's current offset).
        last_us: recording time of the last event of the previous batches, µs (``None``: this is the first).
        clock_us: latest plausible time of any stream so far, µs (>= ``last_us``; ``None``: unknown); a forward
            jump is measured from ``max(previous event, clock_us)``.
        max_gap_us: largest forward jump taken as it is, µs (``None``: never bridge forward jumps).

    Returns:
        An :class:`EventTimes`; with a valid stream (non-decreasing, no jump over ``max_gap_us``) ``t_us`` equals
        the input and nothing is repaired or shifted.
    """
    t = np.asarray(t_us, dtype=np.int64)
    n = t.shape[0]
    if n == 0:
        return EventTimes(t.copy())
    first_odd = last_us is not None and (
        t[0] < last_us
        or (max_gap_us is not None and t[0] - (last_us if clock_us is None else max(last_us, clock_us)) > max_gap_us)
    )
    step = np.diff(t)
    if not first_odd and (n == 1 or (step.min() >= 0 and (max_gap_us is None or step.max() <= max_gap_us))):
        # the usual case, a valid stream: decided with two reductions
        return EventTimes(t.copy(), 0, [], t[:1].copy(), t[-1:].copy(), np.zeros(1, np.int64))
    starts = np.concatenate([[0], np.flatnonzero(step) + 1])
    g = t[starts]
    step = np.diff(g)
    odd = step < 0 if max_gap_us is None else (step < 0) | (step > max_gap_us)
    flagged = (np.flatnonzero(odd) + 1).tolist()
    if first_odd:
        flagged.insert(0, 0)
    out, repaired, shift_runs = _resolve_runs(g, flagged, last_us, clock_us, max_gap_us)
    lengths = np.diff(np.append(starts, n))
    seg_lo, seg_hi, seg_shift = _segments(g, repaired, shift_runs)
    return EventTimes(
        t_us=np.repeat(out, lengths),
        repaired=int(lengths[repaired].sum()) if repaired else 0,
        shifts=[(int(starts[j]), s) for j, s in shift_runs],
        seg_lo_us=seg_lo,
        seg_hi_us=seg_hi,
        seg_shift_us=seg_shift,
    )


def _resolve_runs(g: np.ndarray, flagged: list, last_us: int | None, clock_us: int | None,
                  max_gap_us: int | None) -> tuple[np.ndarray, list, list]:
    """Walk the flagged run boundaries in order; returns (run times, repaired run indices, (run, shift) list)."""
    runs = g.shape[0]
    out = np.empty(runs, np.int64)
    shift = 0
    repaired: list[int] = []
    shifts: list[tuple[int, int]] = []
    decided = -1  # last run whose time was decided at a flagged boundary (never revisited)
    done = 0  # runs [0, done) have their final time in out
    for j in flagged:
        out[done:j] = g[done:j] + shift
        done = j + 1
        prev = int(out[j - 1]) if j else last_us
        cand = int(g[j]) + shift
        nxt = int(g[j + 1]) + shift if j + 1 < runs else None
        if cand < prev:
            if nxt is not None and nxt >= prev:  # this run alone went back: its timestamp is bad
                out[j] = prev
                repaired.append(j)
                decided = j
                continue
            before = _before(out, j - 1, last_us)
            if (j - 1 > decided and before is not None and nxt is not None and before <= cand <= nxt
                    and prev - cand > cand - before):  # the previous run alone stuck out above both neighbours
                out[j - 1] = before
                repaired.append(j - 1)
                prev = before
            else:  # time keeps going back (a lost wrap): continue from the last time written
                shift += prev - cand
                shifts.append((j, shift))
                out[j] = prev
                decided = j
                continue
        ref = prev if clock_us is None or prev is None else max(prev, clock_us)
        if max_gap_us is not None and ref is not None and cand - ref > max_gap_us:
            if nxt is not None and prev is not None and prev <= nxt < cand:  # this run alone jumped ahead
                out[j] = prev
                repaired.append(j)
            else:  # an unconfirmed jump (a bad wrap word): continue 1 µs after the reference
                shift -= cand - ref - 1
                shifts.append((j, shift))
                out[j] = ref + 1
            decided = j
            continue
        out[j] = cand
    out[done:] = g[done:] + shift
    return out, repaired, shifts


def _before(out: np.ndarray, k: int, last_us: int | None) -> int | None:
    """Time of the run before run ``k`` (the previous batch's last time for k = 0; None before any)."""
    if k < 0:
        return None
    return int(out[k - 1]) if k else last_us


def _segments(g: np.ndarray, repaired: list, shift_runs: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Input-time range and shift of each stretch between discontinuities (repaired runs excluded)."""
    runs = g.shape[0]
    bounds = [0, *[j for j, _ in shift_runs], runs]
    values = [0, *[s for _, s in shift_runs]]
    keep = np.ones(runs, bool)
    keep[repaired] = False
    lo, hi, shift = [], [], []
    for a, b, s in zip(bounds[:-1], bounds[1:], values):
        part = g[a:b][keep[a:b]]
        if part.shape[0]:
            lo.append(int(part.min()))
            hi.append(int(part.max()))
            shift.append(s)
    if not shift:  # every run was repaired: map everything with the final shift
        return np.zeros(1, np.int64), np.zeros(1, np.int64), np.array([values[-1]], np.int64)
    return np.array(lo, np.int64), np.array(hi, np.int64), np.array(shift, np.int64)


def shift_for(times_us: np.ndarray, seg_lo_us: np.ndarray, seg_hi_us: np.ndarray,
              seg_shift_us: np.ndarray) -> np.ndarray:
    """Shift of the stretch of events nearest to each time (the later stretch on ties), µs.

    Args:
        times_us: int64 [M] input times of other items (frames, specials, IMU samples), µs.
        seg_lo_us, seg_hi_us, seg_shift_us: int64 [S] from :class:`EventTimes` (S >= 1).

    Returns:
        int64 [M] shifts to add.
    """
    times = np.asarray(times_us, dtype=np.int64)
    if seg_shift_us.shape[0] == 1:
        return np.full(times.shape[0], int(seg_shift_us[0]), np.int64)
    out = np.empty(times.shape[0], np.int64)
    step = max(1, _SHIFT_BLOCK // seg_shift_us.shape[0])
    lo, hi = seg_lo_us[::-1], seg_hi_us[::-1]  # reversed: argmin then prefers the later stretch
    for a in range(0, times.shape[0], step):
        x = times[a : a + step, None]
        distance = np.maximum(lo - x, 0) + np.maximum(x - hi, 0)
        out[a : a + step] = seg_shift_us[::-1][np.argmin(distance, axis=1)]
    return out
