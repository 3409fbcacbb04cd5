"""Vectorised DAVIS (logic 18) stream encoder: DVS events + APS frames → the 16-bit word stream a DAVIS346 sends.

Used by the virtual USB device and by tests to "record" synthetic scenes. The output decodes, with a fresh
:class:`~davis_rig.protocol.decoder.StreamDecoder` of the same layout, to exactly the events and frames given.

Word-stream rules (what a logic-18 FPGA does, PROTOCOL.md §8-§11):

* time: a timestamp word is emitted only when the 15-bit time changes; when the wrap base (``t - t % 32768``) has to
  advance, wrap words (code 7) with multipliers up to 4095 are emitted first. An event whose time is exactly the new
  wrap base needs no timestamp word (the decoder's clock is the wrap base after a wrap, V03).
* DVS: a row (Y) word is shared by consecutive events of the same row and timestamp; each event is one X word (code 3
  ON, 2 OFF). With DVS invertXY the output x goes into the Y word and the output y into the X word.
* APS (global shutter): frame start (special 8) → ROI as 4 × (misc8 1 high byte, misc8 2 low byte): start column,
  start row, end column, end row in output coordinates → [3 × misc10 exposure parts, only if ``adc_clock_mhz`` is
  given] → reset columns (special 11, samples, special 13) → exposure start (special 14) → exposure end (special 15)
  → signal columns (special 12, samples, special 13) → frame end (special 10). The four groups are stamped with the
  frame's SOF, SOE, EOE and EOF times and interleaved with DVS events in time order (events at the same time go
  first).
* CDS values: every pixel is read with reset = 1023 and signal = 1023 − v where ``v = pixels >> 6``; v = 1023 gives
  signal 0, which the decoder's clamp rule turns into 1023. So **every 16-bit pixel value that is a multiple of 64
  (v in 0..1023) round-trips exactly**; values with any of the low 6 bits set cannot be produced by a DAVIS and are
  rejected.
* Big wraps: when the wrap base crosses a multiple of 2**31 µs (every ~35.8 min of stream time) the decoder, like
  libcaer, drops the APS frame in progress; a frame whose SOF and EOF lie on different sides of such a boundary is
  encoded faithfully but will not decode (as with a real camera).
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

from davis_rig.errors import ProtocolError, ShapeError
from davis_rig.protocol.frames import ApsFrame
from davis_rig.protocol.layout import SensorLayout
from davis_rig.protocol.words import (
    APS_PIXEL_MAX,
    APS_PIXEL_SHIFT,
    Code,
    Misc8,
    Special,
    TIMESTAMP_FLAG,
    TIMESTAMP_MASK,
    WRAP_MAX_MULTIPLIER,
)
from davis_rig.types import EVENT_DTYPE

__all__ = ["StreamEncoder", "split_transfers"]

_WRAP_SHIFT = 15
_EVENT_BLOCK = 1 << 18  # events encoded per vectorised block (keeps temporaries in cache)
_RESET_READ = APS_PIXEL_MAX  # reset value used for every pixel (≥ 384, so the clamp rule never fires on it)


def split_transfers(data: bytes, sizes: int | Sequence[int]) -> list[bytes]:
    """Cut a byte stream into USB-transfer-sized pieces.

    Args:
        data: the byte stream.
        sizes: one size in bytes (every piece that size, the last one shorter), or a sequence of sizes used in turn
            and cycled until ``data`` is used up (0 makes an empty transfer).

    Returns:
        The pieces, in order; ``b"".join(pieces) == data``.

    Raises:
        ProtocolError: a negative size, or no positive size at all.
    """
    data = bytes(data)
    if isinstance(sizes, (int, np.integer)):
        sizes = [int(sizes)]
    sizes = [int(s) for s in sizes]
    if not sizes or min(sizes) < 0 or max(sizes) <= 0:
        raise ProtocolError(f"sizes: expected sizes >= 0 with at least one > 0, got {sizes}")
    pieces: list[bytes] = []
    pos = 0
    i = 0
    while pos < len(data):
        size = sizes[i % len(sizes)]
        pieces.append(data[pos : pos + size])
        pos += size
        i += 1
    return pieces


class StreamEncoder:
    """Stateful encoder producing the DAVIS346 word stream for events and APS frames.

    The encoder models the device clock the decoder reconstructs (wrap base and current time, both µs), and the
    last row address it sent; this state is carried across :meth:`encode` calls, so a long scene can be encoded
    piecewise and the concatenated bytes decode as if encoded at once. It starts like a decoder right after
    ``dataStart``: clock 0.

    Args:
        layout: the device's raw geometry/orientation (determines raw address ranges and APS column order).
        adc_clock_mhz: if given, each frame carries libcaer's three misc10 exposure words with
            ``round((t_end_exposure - t_start_exposure) × adc_clock_mhz)`` ADC cycles (only libcaer's
            auto-exposure reads them); if None they are omitted.

    Raises:
        ProtocolError: ``layout`` is not a :class:`SensorLayout`.
    """

    def __init__(self, layout: SensorLayout, *, adc_clock_mhz: float | None = None):
        if not isinstance(layout, SensorLayout):
            raise ProtocolError(f"layout: expected SensorLayout, got {type(layout).__name__}")
        self.layout = layout
        self.adc_clock_mhz = adc_clock_mhz
        self._base_us = 0
        self._time_us = 0
        self._last_y: int | None = None

    @property
    def current_time_us(self) -> int:
        """The decoder-visible stream clock after everything encoded so far, µs."""
        return self._time_us

    # ------------------------------------------------------------------ public API
    def encode(self, events=None, frames: Iterable[ApsFrame] = (), t_start_us: int | None = None) -> bytes:
        """Encode DVS events and APS frames into little-endian 16-bit words.

        Args:
            events: :data:`~davis_rig.types.EVENT_DTYPE` [N], sorted by ``t`` (µs), output coordinates
                (``x < layout.dvs_width``, ``y < layout.dvs_height``), ``p`` in {0, 1}; None or empty for none.
            frames: APS frames in time order, each with ``t_start_of_frame_us <= t_start_exposure_us <=
                t_end_exposure_us <= t_end_of_frame_us``, not overlapping each other, the ROI inside the APS
                array, pixels multiples of 64.
            t_start_us: if given, the stream clock is first advanced (wrap words only, like an idle FPGA) to the
                wrap base of ``t_start_us``.

        Returns:
            The encoded bytes (``2 ×`` number of words).

        Raises:
            ProtocolError: times before the current stream clock or unsorted, addresses out of range, polarity
                not in {0, 1}, frames overlapping / mis-ordered / outside the array / with low pixel bits set.
            ShapeError: ``events`` has the wrong dtype or is not 1-D.
        """
        pieces: list[np.ndarray] = []
        if t_start_us is not None:
            t_start_us = int(t_start_us)
            if t_start_us < self._time_us:
                raise ProtocolError(f"t_start_us: expected >= current stream time {self._time_us}, got {t_start_us}")
            pieces.append(self._advance(t_start_us & ~TIMESTAMP_MASK, emit_timestamp=False))
        events = self._check_events(events)
        frames = list(frames)
        anchors = self._frame_anchors(frames, events)
        if anchors:
            anchor_times = np.array([a[0] for a in anchors], dtype=np.int64)
            cuts = np.searchsorted(events["t"], anchor_times, side="right")
            start = 0
            for (t_us, words), cut in zip(anchors, cuts.tolist()):
                pieces.append(self._encode_events(events[start:cut]))
                start = cut
                pieces.append(self._advance(t_us, emit_timestamp=True))
                pieces.append(words)
            pieces.append(self._encode_events(events[start:]))
        else:
            pieces.append(self._encode_events(events))
        pieces = [p for p in pieces if p.shape[0]]
        if not pieces:
            return b""
        return np.concatenate(pieces).astype("<u2", copy=False).tobytes()

    def timestamp_reset(self) -> bytes:
        """Encode a timestamp-reset special word; the stream clock restarts at 0 (decoder APS/IMU go to ignore).

        Returns:
            2 bytes.
        """
        self._base_us = 0
        self._time_us = 0
        self._last_y = None
        return np.array([Special.TIMESTAMP_RESET], dtype="<u2").tobytes()

    # ------------------------------------------------------------------ validation
    def _check_events(self, events) -> np.ndarray:
        if events is None:
            return np.empty(0, EVENT_DTYPE)
        events = np.asarray(events)
        if events.dtype != EVENT_DTYPE or events.ndim != 1:
            raise ShapeError(f"events: expected EVENT_DTYPE [N], got {events.dtype} {events.shape}")
        n = events.shape[0]
        if n == 0:
            return events
        t = events["t"]
        if t[0] < self._time_us:
            raise ProtocolError(f"events: first t {int(t[0])} µs is before the current stream time {self._time_us} µs")
        if n > 1 and np.any(t[1:] < t[:-1]):
            bad = int(np.flatnonzero(t[1:] < t[:-1])[0])
            raise ProtocolError(f"events: expected sorted t, got t[{bad}]={int(t[bad])} > t[{bad + 1}]={int(t[bad + 1])}")
        width, height = self.layout.dvs_width, self.layout.dvs_height
        if int(events["x"].max()) >= width or int(events["y"].max()) >= height:
            raise ProtocolError(
                f"events: expected x < {width} and y < {height}, got max x {int(events['x'].max())}, "
                f"max y {int(events['y'].max())}"
            )
        if int(events["p"].max()) > 1:
            raise ProtocolError(f"events: expected p in {{0, 1}}, got max {int(events['p'].max())}")
        return events

    def _frame_anchors(self, frames: list[ApsFrame], events: np.ndarray) -> list[tuple[int, np.ndarray]]:
        anchors: list[tuple[int, np.ndarray]] = []
        previous_end = self._time_us
        for k, frame in enumerate(frames):
            if not isinstance(frame, ApsFrame):
                raise ProtocolError(f"frames[{k}]: expected ApsFrame, got {type(frame).__name__}")
            times = (frame.t_start_of_frame_us, frame.t_start_exposure_us, frame.t_end_exposure_us,
                     frame.t_end_of_frame_us)
            if list(times) != sorted(times) or times[0] < previous_end:
                raise ProtocolError(
                    f"frames[{k}]: expected {previous_end} <= SOF <= SOE <= EOE <= EOF µs, got {times}"
                )
            previous_end = times[3]
            anchors.extend(zip(times, self._frame_groups(frame, k)))
        return anchors

    # ------------------------------------------------------------------ words
    def _advance(self, t_us: int, *, emit_timestamp: bool) -> np.ndarray:
        """Words that move the stream clock to ``t_us`` (wraps, then a timestamp word if needed)."""
        words: list[int] = []
        base = t_us & ~TIMESTAMP_MASK
        jump = (base - self._base_us) >> _WRAP_SHIFT
        if jump < 0 or t_us < self._time_us:
            raise ProtocolError(f"time: expected >= current stream time {self._time_us} µs, got {t_us} µs")
        if jump:
            full, rest = divmod(jump, WRAP_MAX_MULTIPLIER)
            words.extend([(Code.TS_WRAP << 12) | WRAP_MAX_MULTIPLIER] * full)
            if rest:
                words.append((Code.TS_WRAP << 12) | rest)
            self._base_us = base
            self._time_us = base
            self._last_y = None
        if emit_timestamp and t_us != self._time_us:
            words.append(TIMESTAMP_FLAG | (t_us & TIMESTAMP_MASK))
            self._time_us = t_us
            self._last_y = None
        return np.array(words, dtype=np.uint16)

    def _encode_events(self, events: np.ndarray) -> np.ndarray:
        n = events.shape[0]
        if n <= _EVENT_BLOCK:
            return self._encode_event_block(events)
        # cache-sized blocks; the carried state makes this identical to encoding all at once
        return np.concatenate([self._encode_event_block(events[s : s + _EVENT_BLOCK]) for s in range(0, n, _EVENT_BLOCK)])

    def _encode_event_block(self, events: np.ndarray) -> np.ndarray:
        n = events.shape[0]
        if n == 0:
            return np.empty(0, np.uint16)
        t = np.ascontiguousarray(events["t"], dtype=np.int64)  # the field view is strided (13-byte records)
        if self.layout.dvs_invert_xy:
            y_raw = events["x"].astype(np.uint16)
            x_raw = events["y"].astype(np.uint16)
        else:
            y_raw = events["y"].astype(np.uint16)
            x_raw = events["x"].astype(np.uint16)
        # wrap-base jumps (in wrap units) from the previous event / the carried clock
        wrap_index = t >> _WRAP_SHIFT
        jump = np.empty(n, np.int64)
        jump[0] = wrap_index[0] - (self._base_us >> _WRAP_SHIFT)
        np.subtract(wrap_index[1:], wrap_index[:-1], out=jump[1:])
        wrapped = jump > 0
        n_wrap = wrapped.astype(np.int64)
        long_gaps = np.flatnonzero(jump > WRAP_MAX_MULTIPLIER)
        if long_gaps.shape[0]:
            n_wrap[long_gaps] = -(-jump[long_gaps] // WRAP_MAX_MULTIPLIER)
        # a timestamp word when the time changes, unless the event sits exactly on a new wrap base
        need_ts = np.empty(n, bool)
        need_ts[0] = t[0] != self._time_us
        np.not_equal(t[1:], t[:-1], out=need_ts[1:])
        on_base = (t & TIMESTAMP_MASK) == 0
        on_base &= wrapped
        need_ts &= ~on_base
        # a row word when the row or the clock changes
        need_y = np.empty(n, bool)
        need_y[0] = self._last_y is None or int(y_raw[0]) != self._last_y
        np.not_equal(y_raw[1:], y_raw[:-1], out=need_y[1:])
        need_y |= wrapped
        need_y |= need_ts

        counts = n_wrap + need_ts
        counts += need_y
        counts += 1
        ends = np.cumsum(counts)
        out = np.empty(int(ends[-1]), np.uint16)
        x_pos = ends - 1
        x_words = events["p"].astype(np.uint16) << 12
        x_words |= x_raw
        x_words |= np.uint16(Code.X_ADDR_OFF << 12)
        out[x_pos] = x_words
        y_at = np.flatnonzero(need_y)
        out[x_pos[y_at] - 1] = y_raw[y_at] | np.uint16(Code.Y_ADDR << 12)
        ts_at = np.flatnonzero(need_ts)
        out[x_pos[ts_at] - 1 - need_y[ts_at]] = (t[ts_at] & TIMESTAMP_MASK).astype(np.uint16) | np.uint16(TIMESTAMP_FLAG)
        wrap_at = np.flatnonzero(n_wrap)
        if wrap_at.shape[0]:
            reps = n_wrap[wrap_at]
            first = ends[wrap_at] - counts[wrap_at]
            total = int(reps.sum())
            within = np.arange(total) - np.repeat(np.cumsum(reps) - reps, reps)
            positions = np.repeat(first, reps) + within
            multipliers = np.full(total, WRAP_MAX_MULTIPLIER, np.int64)
            last = np.cumsum(reps) - 1
            multipliers[last] = jump[wrap_at] - WRAP_MAX_MULTIPLIER * (reps - 1)
            out[positions] = ((Code.TS_WRAP << 12) | multipliers).astype(np.uint16)

        base = t[-1:] & ~np.int64(TIMESTAMP_MASK)
        self._base_us = int(base[0])
        self._time_us = int(t[-1])
        self._last_y = int(y_raw[-1])
        return out

    def _frame_groups(self, frame: ApsFrame, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The frame's words as 4 groups stamped SOF, SOE, EOE, EOF."""
        layout = self.layout
        height, width = frame.pixels.shape
        px, py = frame.position_x, frame.position_y
        if (width < 1 or height < 1 or px < 0 or py < 0 or px + width > layout.aps_width
                or py + height > layout.aps_height):
            raise ProtocolError(
                f"frames[{k}]: ROI {width}x{height} at ({px},{py}) does not fit the APS array "
                f"{layout.aps_width}x{layout.aps_height}"
            )
        if np.any(frame.pixels & ((1 << APS_PIXEL_SHIFT) - 1)):
            raise ProtocolError(f"frames[{k}]: pixels must be multiples of 64 (10-bit CDS << 6) to be encodable")
        values = (frame.pixels >> APS_PIXEL_SHIFT).astype(np.int64)  # [height, width], 0..1023
        # device order D[column, sample]: without invertXY columns are output x, samples output y
        device = values if layout.aps_invert_xy else values.T
        if layout.aps_flip_x:
            device = device[::-1, :]
        if layout.aps_flip_y:
            device = device[:, ::-1]
        signal = _RESET_READ - device

        def columns(start_code: int, samples: np.ndarray) -> np.ndarray:
            block = np.empty((samples.shape[0], samples.shape[1] + 2), np.uint16)
            block[:, 0] = start_code
            block[:, 1:-1] = (Code.ADC_SAMPLE << 12) | samples
            block[:, -1] = Special.APS_COLUMN_END
            return block.ravel()

        head = [Special.APS_FRAME_START_GS]
        for value in (px, py, px + width - 1, py + height - 1):
            head.append((Code.MISC8 << 12) | (Misc8.APS_ROI_HIGH << 8) | (value >> 8))
            head.append((Code.MISC8 << 12) | (Misc8.APS_ROI_LOW << 8) | (value & 0xFF))
        if self.adc_clock_mhz is not None:
            cycles = int(round((frame.t_end_exposure_us - frame.t_start_exposure_us) * self.adc_clock_mhz))
            cycles = min(max(cycles, 0), (1 << 30) - 1)
            head.extend((Code.MISC10 << 12) | ((cycles >> (10 * i)) & 0x3FF) for i in range(3))
        reset = np.full(device.shape, _RESET_READ, np.int64)
        sof = np.concatenate([np.array(head, np.uint16), columns(Special.APS_RESET_COLUMN_START, reset)])
        soe = np.array([Special.APS_EXPOSURE_START], np.uint16)
        eoe = np.concatenate([np.array([Special.APS_EXPOSURE_END], np.uint16),
                              columns(Special.APS_SIGNAL_COLUMN_START, signal)])
        eof = np.array([Special.APS_FRAME_END], np.uint16)
        return sof, soe, eoe, eof
