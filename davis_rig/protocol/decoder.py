"""Vectorised DAVIS (logic 18) stream decoder: USB bytes → DVS events, APS frames, IMU6 samples, specials.

Semantics follow libcaer 3.x (PROTOCOL.md §8-§13) with two deliberate differences, both documented on
:class:`StreamDecoder`: the 64-bit overflow is computed per event (the intended value of vector V19, not libcaer's
stale per-packet value), and TIMESTAMP_RESET / TIMESTAMP_WRAP specials carry the stream time at which they happen
instead of libcaer's ``INT32_MAX`` marker.

Implementation: the DVS/timestamp path has no per-word Python loop. Per block of words, the timestamp base is a
cumulative sum of wrap increments segmented at resets, the 15-bit timestamp and the last row address are
forward-filled with ``np.maximum.accumulate`` over ``(index << k) | value`` keys, and events are selected with
masks. Control words (specials, misc8, misc10, big wraps) run through a compact Python loop, except runs of whole
APS columns (column start, expected rows of samples, column end, ...), which are recognised with numpy and applied in
bulk. APS ADC samples are never looped over: they are queued as column segments (their values kept in a bounded
store across transfers) and written into the frame buffers once per frame — runs of whole columns as one rectangular
slice, anything irregular with one vectorised scatter per group of same-type segments.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields
from typing import Final

import numpy as np

from davis_rig.errors import ProtocolError
from davis_rig.protocol.frames import ApsFrame
from davis_rig.protocol.layout import SensorLayout
from davis_rig.protocol.words import (
    APS_PIXEL_MAX,
    APS_PIXEL_SHIFT,
    APS_RESET_MIN,
    IMU_TOTAL_COUNT,
    Special,
    SpecialType,
)
from davis_rig.types import EVENT_DTYPE

_log = logging.getLogger(__name__)

__all__ = [
    "SPECIAL_DTYPE",
    "IMU6_DTYPE",
    "DecoderStats",
    "DecodedChunk",
    "StreamDecoder",
]

#: A special event: time (µs, int64) and libcaer special type id (see :class:`~davis_rig.protocol.words.SpecialType`).
SPECIAL_DTYPE: Final = np.dtype([("t", "<i8"), ("type", "u1")])

#: One IMU6 sample: time µs; acceleration in g; angular rate in °/s; temperature in °C.
IMU6_DTYPE: Final = np.dtype(
    [
        ("t", "<i8"),
        ("accel_x_g", "<f4"),
        ("accel_y_g", "<f4"),
        ("accel_z_g", "<f4"),
        ("gyro_x_dps", "<f4"),
        ("gyro_y_dps", "<f4"),
        ("gyro_z_dps", "<f4"),
        ("temperature_c", "<f4"),
    ]
)

#: Words decoded per vectorised block; bounds temporary memory (about 40 bytes per word) and keeps it in cache.
_BLOCK_WORDS: Final = 1 << 15
_TS_KEY_SHIFT: Final = 15
_Y_KEY_SHIFT: Final = 12
_BIG_WRAP_SHIFT: Final = 31

_LOSS_COUNTERS: Final = (
    "odd_bytes_dropped",
    "unknown_words",
    "dvs_out_of_range",
    "aps_frames_dropped",
    "aps_samples_dropped",
    "imu_samples_dropped",
    "non_monotonic_timestamps",
)

#: Queued ADC samples are written out at the latest when this many are stored (about 3 full DAVIS346 frames).
_STORE_FLUSH_SAMPLES: Final = 1 << 19

#: Whole-column runs at least this long are written as one rectangular slice; shorter ones by one scatter.
_MIN_BLOCK_COLUMNS: Final = 16

_READOUT_RESET: Final = 0
_READOUT_SIGNAL: Final = 1

_SPECIAL_TYPE_OF_WIRE: Final = {
    Special.EXT_INPUT_FALLING: SpecialType.EXTERNAL_INPUT_FALLING_EDGE,
    Special.EXT_INPUT_RISING: SpecialType.EXTERNAL_INPUT_RISING_EDGE,
    Special.EXT_INPUT_PULSE: SpecialType.EXTERNAL_INPUT_PULSE,
    Special.EXT_GENERATOR_FALLING: SpecialType.EXTERNAL_GENERATOR_FALLING_EDGE,
    Special.EXT_GENERATOR_RISING: SpecialType.EXTERNAL_GENERATOR_RISING_EDGE,
}

# IMU present-sensor bits of the misc8 scale byte (bits 7-5 → values 4/2/1).
_IMU_ACCEL: Final = 4
_IMU_GYRO: Final = 2
_IMU_TEMP: Final = 1


@dataclass
class DecoderStats:
    """Cumulative decoder counters (never reset by :meth:`StreamDecoder.feed`).

    Attributes:
        words: 16-bit words decoded.
        odd_bytes_dropped: trailing bytes of odd-length transfers that were discarded (libcaer behaviour).
        unknown_words: words with an unhandled code/sub-code (reserved special 0, IMU9 start, specials ≥ 18,
            misc8 sub-codes ≥ 4, misc10 sub-codes ≠ 0).
        dvs_out_of_range: DVS address words outside the raw sensor size (Y ignored, X event dropped).
        aps_frames_dropped: frames started but never delivered (invalid column count at frame end, interrupted by a
            new frame start, a timestamp reset or a big wrap).
        aps_samples_dropped: ADC samples discarded (APS in ignore mode, or beyond the expected column/row counts).
        imu_samples_dropped: IMU samples started but not delivered (byte count ≠ 14 at IMU end, or interrupted).
        timestamp_resets: timestamp-reset specials seen.
        big_wraps: wraps that overflowed the 31-bit timestamp (libcaer TIMESTAMP_WRAP).
        non_monotonic_timestamps: DVS events earlier than the previous DVS event (a timestamp reset between the
            two restarts the comparison); the events are delivered unchanged.
    """

    words: int = 0
    odd_bytes_dropped: int = 0
    unknown_words: int = 0
    dvs_out_of_range: int = 0
    aps_frames_dropped: int = 0
    aps_samples_dropped: int = 0
    imu_samples_dropped: int = 0
    timestamp_resets: int = 0
    big_wraps: int = 0
    non_monotonic_timestamps: int = 0

    def copy(self) -> "DecoderStats":
        """Return an independent snapshot."""
        return DecoderStats(**self.as_dict())

    def as_dict(self) -> dict[str, int]:
        """Return the counters as a plain ``dict``."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class DecodedChunk:
    """Everything decoded from one :meth:`StreamDecoder.feed` call.

    Attributes:
        events: DVS events, :data:`~davis_rig.types.EVENT_DTYPE` [N], in stream order.
        frames: completed valid APS frames, in order of their frame-end word.
        specials: :data:`SPECIAL_DTYPE` [M], in stream order.
        imu: :data:`IMU6_DTYPE` [K], in stream order.
    """

    events: np.ndarray = field(default_factory=lambda: np.empty(0, EVENT_DTYPE))
    frames: list[ApsFrame] = field(default_factory=list)
    specials: np.ndarray = field(default_factory=lambda: np.empty(0, SPECIAL_DTYPE))
    imu: np.ndarray = field(default_factory=lambda: np.empty(0, IMU6_DTYPE))

    def __len__(self) -> int:
        return int(self.events.shape[0])

    @staticmethod
    def concatenate(chunks) -> "DecodedChunk":
        """Join several chunks into one (arrays concatenated, frame lists joined)."""
        chunks = list(chunks)
        if not chunks:
            return DecodedChunk()
        return DecodedChunk(
            events=np.concatenate([c.events for c in chunks]),
            frames=[f for c in chunks for f in c.frames],
            specials=np.concatenate([c.specials for c in chunks]),
            imu=np.concatenate([c.imu for c in chunks]),
        )


class _ApsState:
    """APS frame assembly state (PROTOCOL.md §11); ADC samples arrive as queued column segments."""

    def __init__(self, layout: SensorLayout):
        self.width = layout.aps_width
        self.height = layout.aps_height
        self.invert_xy = layout.aps_invert_xy
        self.flip_x = layout.aps_flip_x
        self.flip_y = layout.aps_flip_y
        self.ignore = True
        self.in_frame = False
        self.readout = _READOUT_RESET
        self.count_x = [0, 0]
        self.count_y = [0, 0]
        self.expected_x = 0
        self.expected_y = 0
        self.size_x = 0
        self.size_y = 0
        self.position_x = 0
        self.position_y = 0
        self.roi_counter = 0
        self.roi_high = 0
        self.roi_values = [0, 0, 0, 0]
        self.t_sof = 0
        self.t_soe = 0
        self.t_eoe = 0
        npix = self.width * self.height
        self.reset_buffer = np.zeros(npix, np.int32)
        self.pixel_buffer = np.zeros(npix, np.uint16)
        # queued column segments (readout, count_x, first_row, start, stop) indexing the sample store: single
        # tuples from the per-word path, (k, 5) int64 arrays from the whole-column bulk path. The store keeps the
        # ADC values of the blocks since the last write, so a frame split over many transfers is written at once.
        self.pending: list = []
        self.store: list[np.ndarray] = []
        self.store_len = 0

    def set_roi(self) -> None:
        start_col, start_row, end_col, end_row = self.roi_values
        size_x = end_col + 1 - start_col
        size_y = end_row + 1 - start_row
        pos_x, pos_y = start_col, start_row
        if size_x <= 0 or size_x > self.width:
            size_x = self.width
        if size_y <= 0 or size_y > self.height:
            size_y = self.height
        if pos_x + size_x > self.width:
            pos_x = 0
        if pos_y + size_y > self.height:
            pos_y = 0
        self.size_x, self.size_y = size_x, size_y
        self.position_x, self.position_y = pos_x, pos_y
        if self.invert_xy:
            self.expected_x, self.expected_y = size_y, size_x
        else:
            self.expected_x, self.expected_y = size_x, size_y


class _ImuState:
    """IMU6 assembly state (PROTOCOL.md §12)."""

    def __init__(self, layout: SensorLayout):
        self.ignore = True
        self.in_sample = False
        self.count = 0
        self.present = 0
        self.high_byte = 0
        self.values = [0.0] * 7  # ax, ay, az, temp, gx, gy, gz
        self.accel_lsb_per_g = 65536.0 / (4 * 2)
        self.gyro_lsb_per_dps = 65536.0 / (500 * 2)
        if layout.imu_type == 2:
            self.temp_scale, self.temp_offset = 333.87, 21.0
        else:
            self.temp_scale, self.temp_offset = 340.0, 35.0
        self.flip = (
            -1.0 if layout.imu_flip_x else 1.0,
            -1.0 if layout.imu_flip_y else 1.0,
            -1.0 if layout.imu_flip_z else 1.0,
        )


class StreamDecoder:
    """Stateful DAVIS word-stream decoder; feed it USB bulk transfers in arrival order.

    All parser state (timestamp base and overflow, last row address, APS frame and IMU sample in progress, odd byte
    when reassembling) is kept between :meth:`feed` calls, so where a stream is cut into transfers never changes the
    output. The initial state is libcaer's right after ``dataStart``: time 0, last Y = 0, APS and IMU parsers ignoring
    data until their next start event.

    Deliberate choices (vs libcaer 3.3):

    * **Per-event overflow.** Every event's time is ``(overflow << 31) | ts32`` with the overflow *at that event*;
      libcaer attaches the overflow to whole packets, so right after a big wrap it can report the old overflow
      (test vector V19, ``dvs_libcaer_actual``).
    * **Reset/wrap specials carry real times.** ``TIMESTAMP_WRAP`` is reported with the stream time right after the
      big wrap (the new wrap base, e.g. ``2**31 + 32768``); ``TIMESTAMP_RESET`` with the time right after the reset,
      i.e. ``0``. libcaer instead stamps both with the marker ``INT32_MAX`` (2147483647). The stream-order position
      of the special (between the last event before and the first event after) is what carries the information.

    Points libcaer leaves open, decided here: the pixel buffer is zeroed at each frame start (pixels of a valid frame
    whose columns came short stay 0), the reset-read buffer is not; a frame-end word without a preceding frame start
    delivers nothing. Data loss (odd bytes, unknown words, out-of-range addresses, dropped frames/samples) is counted
    in :attr:`stats` and logged once per kind as a warning on the ``davis_rig.protocol.decoder`` logger.

    Args:
        layout: the device's raw geometry/orientation read-outs.
        reassemble_odd_bytes: if True, a trailing odd byte is carried into the next transfer (its low byte first);
            if False (libcaer), it is dropped and counted in ``stats.odd_bytes_dropped``.

    Raises:
        ProtocolError: ``layout`` is not a :class:`SensorLayout`.
    """

    def __init__(self, layout: SensorLayout, *, reassemble_odd_bytes: bool = False):
        if not isinstance(layout, SensorLayout):
            raise ProtocolError(f"layout: expected SensorLayout, got {type(layout).__name__}")
        self.layout = layout
        self.reassemble_odd_bytes = bool(reassemble_odd_bytes)
        self._stats = DecoderStats()
        self._warned: set[str] = set()
        self._dvs_cols = layout.dvs_size_columns
        self._dvs_rows = layout.dvs_size_rows
        self._dvs_invert = layout.dvs_invert_xy
        # timestamp state: current time = base + offset; base = (overflow << 31) + wrapAdd
        self._base_us = 0
        self._offset_us = 0
        self._last_y = 0
        self._last_event_t: int | None = None
        self._odd_byte: int | None = None
        self._aps = _ApsState(layout)
        self._imu = _ImuState(layout)
        # work buffers reused by every block (fresh large allocations cost page faults on each call)
        self._idx15 = np.empty(0, np.int64)
        self._idx12 = np.empty(0, np.int64)
        self._key_t = np.empty(0, np.int64)
        self._key_y = np.empty(0, np.int64)

    # ------------------------------------------------------------------ public API
    @property
    def stats(self) -> DecoderStats:
        """Cumulative counters (a snapshot copy)."""
        return self._stats.copy()

    @property
    def current_time_us(self) -> int:
        """Stream clock after the last decoded word, µs (64-bit, overflow included)."""
        return self._base_us + self._offset_us

    def feed(self, transfer) -> DecodedChunk:
        """Decode one USB bulk transfer.

        Args:
            transfer: ``bytes``, ``bytearray``, ``memoryview`` or 1-D ``uint8`` array; 16-bit little-endian words.
                Empty transfers are allowed (nothing happens).

        Returns:
            The :class:`DecodedChunk` completed by this transfer.

        Raises:
            ProtocolError: ``transfer`` is not bytes-like / not a 1-D ``uint8`` array.
        """
        data = self._as_bytes(transfer)
        if self._odd_byte is not None:
            data = bytes((self._odd_byte,)) + bytes(data)
            self._odd_byte = None
        if len(data) % 2:
            if self.reassemble_odd_bytes:
                self._odd_byte = data[-1]
            else:
                self._stats.odd_bytes_dropped += 1
            data = data[:-1]
        words = np.frombuffer(data, dtype="<u2")
        return self.decode_words(words)

    def feed_many(self, transfers) -> DecodedChunk:
        """Decode several USB transfers in one vectorised pass (less per-call overhead for small transfers).

        Output and statistics are identical to calling :meth:`feed` on each transfer in turn (odd-length transfers
        still lose, or carry, their own trailing byte).

        Args:
            transfers: iterable of transfers accepted by :meth:`feed`.

        Returns:
            One :class:`DecodedChunk` for all of them.

        Raises:
            ProtocolError: a transfer of an unsupported type.
        """
        pieces = []
        if self._odd_byte is not None:
            pieces.append(bytes((self._odd_byte,)))
            self._odd_byte = None
        for transfer in transfers:
            data = self._as_bytes(transfer)
            if not self.reassemble_odd_bytes and len(data) % 2:
                self._stats.odd_bytes_dropped += 1
                data = data[:-1]
            pieces.append(data)
        joined = b"".join(pieces)
        if len(joined) % 2:  # only possible when reassembling
            self._odd_byte = joined[-1]
            joined = joined[:-1]
        return self.decode_words(np.frombuffer(joined, dtype="<u2"))

    def decode_words(self, words: np.ndarray) -> DecodedChunk:
        """Decode already-assembled 16-bit words (same state as :meth:`feed`; bypasses odd-byte handling).

        Args:
            words: ``uint16`` [N] (any integer dtype with values 0..65535 is accepted and converted).

        Returns:
            The :class:`DecodedChunk` completed by these words.

        Raises:
            ProtocolError: not a 1-D array, or values outside 0..65535.
        """
        words = np.asarray(words)
        if words.ndim != 1:
            raise ProtocolError(f"words: expected a 1-D array, got shape {words.shape}")
        if words.dtype != np.uint16:
            if words.size and (words.dtype.kind not in "iu" or words.min() < 0 or words.max() > 0xFFFF):
                raise ProtocolError(f"words: expected integers in 0..65535, got {words.dtype} values")
            words = words.astype(np.uint16)
        n = words.shape[0]
        if n == 0:
            self._warn_once()
            return DecodedChunk()
        self._stats.words += n
        if n <= _BLOCK_WORDS:
            chunk = self._decode_block(words)
        else:
            # one output array for all blocks (an upper bound: every X word), filled block by block
            out = np.empty(int(np.count_nonzero((words >> 13) == 1)), EVENT_DTYPE)
            filled = 0
            parts = []
            for s in range(0, n, _BLOCK_WORDS):
                part = self._decode_block(words[s : s + _BLOCK_WORDS], out=out[filled:])
                filled += part.events.shape[0]
                parts.append(part)
            chunk = DecodedChunk(
                events=out[:filled],
                frames=[f for part in parts for f in part.frames],
                specials=np.concatenate([part.specials for part in parts]),
                imu=np.concatenate([part.imu for part in parts]),
            )
        self._warn_once()
        return chunk

    def _warn_once(self) -> None:
        """Log the first occurrence of each kind of data loss (the counters keep the totals)."""
        stats = self._stats
        for name in _LOSS_COUNTERS:
            if name not in self._warned and getattr(stats, name):
                self._warned.add(name)
                _log.warning("DAVIS stream decoder: %s (first occurrence; total so far %d, see decoder.stats)",
                             name.replace("_", " "), getattr(stats, name))

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _as_bytes(transfer):
        if isinstance(transfer, np.ndarray):
            if transfer.dtype != np.uint8 or transfer.ndim != 1:
                raise ProtocolError(f"transfer: expected a 1-D uint8 array, got {transfer.dtype} {transfer.shape}")
            return memoryview(np.ascontiguousarray(transfer)).cast("B")
        if isinstance(transfer, (bytes, bytearray)):
            return transfer
        if isinstance(transfer, memoryview):
            if transfer.format == "B" and transfer.ndim == 1:
                return transfer
            if not transfer.c_contiguous:
                raise ProtocolError("transfer: expected a C-contiguous memoryview")
            return transfer.cast("B")
        raise ProtocolError(f"transfer: expected bytes, bytearray, memoryview or uint8 array, got {type(transfer).__name__}")

    def _index_keys(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        if self._idx15.shape[0] < n:
            size = max(n, 1024)
            idx = np.arange(1, size + 1, dtype=np.int64)
            self._idx15 = idx << _TS_KEY_SHIFT
            self._idx12 = idx << _Y_KEY_SHIFT
            self._key_t = np.empty(size, np.int64)
            self._key_y = np.empty(size, np.int64)
        return self._idx15[:n], self._idx12[:n]

    def _decode_block(self, w: np.ndarray, out: np.ndarray | None = None) -> DecodedChunk:
        n = w.shape[0]
        idx15, idx12 = self._index_keys(n)
        codes = w >> 12
        n_special = int(np.count_nonzero(codes == 0))
        n_high = int(np.count_nonzero((codes - np.uint16(4)) <= 3))  # codes 4-7 (uint16 arithmetic wraps below 4)
        if n_high:
            is_wrap = codes == 7
            n_wrap = int(np.count_nonzero(is_wrap))
        else:
            is_wrap = None
            n_wrap = 0
        n_rare = n_special + n_high - n_wrap  # specials, ADC samples, misc8, misc10
        is_ts = w >= 0x8000
        n_reset = 0
        is_reset = None
        if n_special:
            is_reset = w == Special.TIMESTAMP_RESET
            n_reset = int(np.count_nonzero(is_reset))

        # --- 15-bit offset: forward fill of ((index + 1) << 15 | t15) over time-setting words --------------------
        # Non-setters get key 0; positions before the block's first setter fall back to the carried offset
        # (any setter key is >= 1 << 15 > carried offset), applied with np.maximum on gathered keys only.
        key_t = np.bitwise_or(idx15, w & 0x7FFF, out=self._key_t[:n])
        np.multiply(key_t, is_ts, out=key_t)
        offset_in = self._offset_us

        # --- wrap base: only changes at wrap and reset words, which are few; computed on those positions ---------
        # base = (overflow << 31) + wrapAdd, 64-bit; a wrap adds n << 15, a reset restarts at 0.
        base_prev = self._base_us
        changes = None
        if n_wrap or n_reset:
            if not n_reset:
                is_change = is_wrap
            elif is_wrap is None:
                is_change = is_reset
            else:
                is_change = is_wrap | is_reset
            changes = np.flatnonzero(is_change)
            key_t[changes] = idx15[changes]  # wraps and resets are setters with offset 0
            change_words = w[changes]
            increments = (change_words & 0x0FFF).astype(np.int64) << 15
            change_is_reset = change_words == Special.TIMESTAMP_RESET
            increments[change_is_reset] = 0
            change_base = np.cumsum(increments)
            if n_reset:
                k = np.arange(changes.shape[0])
                last_reset = np.maximum.accumulate(np.where(change_is_reset, k, -1))
                change_base += np.where(last_reset >= 0, -change_base[np.maximum(last_reset, 0)], base_prev)
            else:
                change_base += base_prev
            base_end = int(change_base[-1])
        else:
            base_end = base_prev
        np.maximum.accumulate(key_t, out=key_t)

        def base_at(positions: np.ndarray):
            """Wrap base in effect at (after) each word position; a scalar when the block has no change."""
            if changes is None:
                return base_prev
            j = np.searchsorted(changes, positions, side="right") - 1
            return np.where(j >= 0, change_base[np.maximum(j, 0)], base_prev)

        # --- last Y: forward fill of ((index + 1) << 12 | y) over in-range Y words ---------------------------------
        y_data = w - np.uint16(0x1000)  # the row for Y words; >= 0x1000 (so never "in range") for any other word
        valid_y = y_data < self._dvs_rows
        self._stats.dvs_out_of_range += int(np.count_nonzero(codes == 1)) - int(np.count_nonzero(valid_y))
        key_y = np.bitwise_or(idx12, y_data, out=self._key_y[:n])
        np.multiply(key_y, valid_y, out=key_y)
        np.maximum.accumulate(key_y, out=key_y)
        last_y_in = self._last_y

        # --- DVS events ----------------------------------------------------------------------------------------------
        xi = np.flatnonzero((w >> 13) == 1)  # codes 2 and 3
        if xi.shape[0]:
            x_words = w[xi]
            xdata = x_words & 0x0FFF
            if int(xdata.max()) >= self._dvs_cols:
                ok = xdata < self._dvs_cols
                self._stats.dvs_out_of_range += xi.shape[0] - int(np.count_nonzero(ok))
                xi = xi[ok]
                xdata = xdata[ok]
                x_words = x_words[ok]
        if xi.shape[0]:
            t = key_t[xi]
            if t[0] < (1 << _TS_KEY_SHIFT):  # events before the block's first setter use the carried offset
                np.maximum(t, offset_in, out=t)
            t &= 0x7FFF
            t += base_at(xi)
            y = key_y[xi]
            if y[0] < (1 << _Y_KEY_SHIFT):  # events before the block's first Y word use the carried row
                np.maximum(y, last_y_in, out=y)
            y &= 0x0FFF
            events = np.empty(xi.shape[0], EVENT_DTYPE) if out is None else out[: xi.shape[0]]
            events["t"] = t
            if self._dvs_invert:
                events["x"] = y
                events["y"] = xdata
            else:
                events["x"] = xdata
                events["y"] = y
            events["p"] = (x_words >> 12) & 1
            # non-monotonic event times (a reset between two events restarts the comparison)
            backwards = t[1:] < t[:-1]
            first_backwards = self._last_event_t is not None and int(t[0]) < self._last_event_t
            if n_reset:
                epoch = np.searchsorted(np.flatnonzero(is_reset), xi)
                backwards &= epoch[1:] == epoch[:-1]
                first_backwards = first_backwards and int(epoch[0]) == 0
            self._stats.non_monotonic_timestamps += int(np.count_nonzero(backwards)) + int(first_backwards)
            self._last_event_t = int(t[-1])
        else:
            events = np.empty(0, EVENT_DTYPE)
            if n_reset:
                self._last_event_t = None

        chunk = DecodedChunk(events=events)

        # --- control words: specials, misc8, misc10, big wraps; ADC samples as column segments ---------------------
        big_wrap_pos = None
        if n_wrap:
            before = change_base - increments
            crossed = (change_base >> _BIG_WRAP_SHIFT) != (before >> _BIG_WRAP_SHIFT)
            crossed &= ~change_is_reset
            if crossed.any():
                big_wrap_pos = changes[crossed]
        if n_rare or big_wrap_pos is not None:
            self._control(w, codes, key_t, offset_in, base_at, big_wrap_pos, chunk)
            if n_reset and xi.shape[0] and int(np.count_nonzero(is_reset[xi[-1]:])):
                self._last_event_t = None  # a reset after the block's last event

        # --- carry state -------------------------------------------------------------------------------------------
        self._base_us = base_end
        self._offset_us = max(int(key_t[-1]), offset_in) & 0x7FFF
        self._last_y = max(int(key_y[-1]), last_y_in) & 0x0FFF
        return chunk

    # ------------------------------------------------------------------ control-word path
    def _control(self, w, codes, key_t, offset_in, base_at, big_wrap_pos, chunk: DecodedChunk) -> None:
        aps = self._aps
        imu = self._imu
        stats = self._stats
        ctrl_mask = (codes == 0) | (codes == 5) | (codes == 6)
        if big_wrap_pos is not None:
            ctrl_mask[big_wrap_pos] = True
        ctrl_pos = np.flatnonzero(ctrl_mask)
        adc_pos = np.flatnonzero(codes == 4)
        ctrl_words = w[ctrl_pos]
        if adc_pos.shape[0]:
            adc_vals = (w[adc_pos] & 0x0FFF).astype(np.int32)
            cut_array = np.searchsorted(adc_pos, ctrl_pos)
        else:
            adc_vals = np.empty(0, np.int32)
            cut_array = np.zeros(ctrl_pos.shape[0], np.int64)
        adc_cut = cut_array.tolist()
        n_adc = adc_vals.shape[0]
        store_base = aps.store_len  # block ADC index i is store index store_base + i
        if n_adc:
            aps.store.append(adc_vals)
            aps.store_len += n_adc
        times = np.maximum(key_t[ctrl_pos], offset_in) & 0x7FFF
        times += base_at(ctrl_pos)
        specials: list[tuple[int, int]] = []
        imu_rows: list[tuple] = []
        adc_done = 0

        def take_samples(upto: int) -> None:
            nonlocal adc_done
            k = upto - adc_done
            if k <= 0:
                return
            start = adc_done
            adc_done = upto
            if aps.ignore:
                stats.aps_samples_dropped += k
                return
            r = aps.readout
            cx = aps.count_x[r]
            cy = aps.count_y[r]
            if cx >= aps.expected_x:
                stats.aps_samples_dropped += k
                return
            take = min(k, max(aps.expected_y - cy, 0))
            stats.aps_samples_dropped += k - take
            if take:
                aps.pending.append((r, cx, cy, store_base + start, store_base + start + take))
                aps.count_y[r] = cy + take

        words_list = ctrl_words.tolist()
        times_list = times.tolist()
        n_ctrl = len(words_list)
        i = -1
        while i + 1 < n_ctrl:
            i += 1
            word = words_list[i]
            t = times_list[i]
            cut = adc_cut[i]
            if (
                (word == Special.APS_RESET_COLUMN_START or word == Special.APS_SIGNAL_COLUMN_START)
                and not aps.ignore
                and i + 3 < n_ctrl
                and words_list[i + 1] == Special.APS_COLUMN_END
                and words_list[i + 2] == word
                and adc_cut[i + 1] - cut == aps.expected_y
            ):
                # a run of whole columns (start, expected_y samples, end, start, ...): handled in bulk
                pairs = self._column_run(ctrl_words, cut_array, i)
                if pairs >= 2:
                    take_samples(cut)
                    adc_done = self._bulk_columns(word, pairs, cut_array, i, store_base)
                    i += 2 * pairs - 1
                    continue
            code = word >> 12
            sub = word & 0x0FFF
            if code == 0:
                if sub == Special.TIMESTAMP_RESET:
                    take_samples(cut)
                    self._flush_aps()
                    stats.timestamp_resets += 1
                    self._interrupt(aps, imu)
                    specials.append((t, SpecialType.TIMESTAMP_RESET))
                elif sub in _SPECIAL_TYPE_OF_WIRE:
                    specials.append((t, _SPECIAL_TYPE_OF_WIRE[sub]))
                elif sub == Special.IMU_START_6:
                    if imu.in_sample and not imu.ignore:
                        stats.imu_samples_dropped += 1
                    imu.ignore = False
                    imu.in_sample = True
                    imu.count = 0
                    imu.present = 0
                    imu.values = [0.0] * 7
                elif sub == Special.IMU_END:
                    if imu.ignore:
                        continue
                    if imu.count == IMU_TOTAL_COUNT:
                        v = imu.values
                        imu_rows.append((t, v[0], v[1], v[2], v[4], v[5], v[6], v[3]))
                    else:
                        stats.imu_samples_dropped += 1
                    imu.in_sample = False
                elif sub in (Special.APS_FRAME_START_GS, Special.APS_FRAME_START_RS):
                    take_samples(cut)
                    self._flush_aps()
                    if aps.in_frame and not aps.ignore:
                        stats.aps_frames_dropped += 1
                    aps.ignore = False
                    aps.in_frame = True
                    aps.roi_counter = 0
                    aps.readout = _READOUT_RESET
                    aps.count_x = [0, 0]
                    aps.count_y = [0, 0]
                    aps.t_sof = t
                    aps.pixel_buffer.fill(0)
                    specials.append((t, SpecialType.APS_FRAME_START))
                elif Special.APS_FRAME_END <= sub <= Special.APS_EXPOSURE_END:
                    if aps.ignore:
                        continue
                    if sub == Special.APS_EXPOSURE_START:
                        aps.t_soe = t
                        specials.append((t, SpecialType.APS_EXPOSURE_START))
                    elif sub == Special.APS_EXPOSURE_END:
                        aps.t_eoe = t
                        specials.append((t, SpecialType.APS_EXPOSURE_END))
                    else:
                        take_samples(cut)
                        if sub == Special.APS_RESET_COLUMN_START:
                            aps.readout = _READOUT_RESET
                            aps.count_y[_READOUT_RESET] = 0
                        elif sub == Special.APS_SIGNAL_COLUMN_START:
                            aps.readout = _READOUT_SIGNAL
                            aps.count_y[_READOUT_SIGNAL] = 0
                        elif sub == Special.APS_COLUMN_END:
                            aps.count_x[aps.readout] += 1
                        else:  # frame end
                            self._flush_aps()
                            specials.append((t, SpecialType.APS_FRAME_END))
                            self._end_frame(t, chunk)
                else:
                    stats.unknown_words += 1
            elif code == 5:
                misc = sub >> 8
                byte = sub & 0xFF
                if misc == 0:
                    if not imu.ignore:
                        self._imu_byte(imu, byte)
                elif misc == 1:
                    aps.roi_high = byte
                elif misc == 2:
                    slot = aps.roi_counter & 3
                    aps.roi_values[slot] = (aps.roi_high << 8) | byte
                    aps.roi_counter += 1
                    if slot == 3:
                        take_samples(cut)
                        self._flush_aps()
                        aps.set_roi()
                elif misc == 3:
                    if not imu.ignore:
                        self._imu_scale(imu, byte)
                else:
                    stats.unknown_words += 1
            elif code == 6:
                if sub >> 10:
                    stats.unknown_words += 1
                # sub-code 0 = exposure value parts, only used by libcaer's auto-exposure: consumed.
            else:  # big wrap (code 7)
                take_samples(cut)
                self._flush_aps()
                stats.big_wraps += 1
                self._interrupt(aps, imu)
                specials.append((t, SpecialType.TIMESTAMP_WRAP))
        take_samples(n_adc)
        if aps.pending and aps.store_len > _STORE_FLUSH_SAMPLES:  # bound memory on streams that never end a frame
            self._flush_aps()
        if not aps.pending:  # nothing refers to the stored samples any more
            aps.store = []
            aps.store_len = 0
        if specials:
            chunk.specials = np.array(specials, dtype=SPECIAL_DTYPE)
        if imu_rows:
            chunk.imu = np.array(imu_rows, dtype=IMU6_DTYPE)

    def _column_run(self, ctrl_words: np.ndarray, cuts: np.ndarray, i: int) -> int:
        """Number of consecutive whole-column (start, end) pairs of the same readout type starting at control i."""
        expected_y = self._aps.expected_y
        pairs = min((ctrl_words.shape[0] - i) // 2, 2 * max(self._aps.expected_x, 1) + 2)
        words = ctrl_words[i : i + 2 * pairs].reshape(pairs, 2)
        starts = cuts[i : i + 2 * pairs : 2]
        ends = cuts[i + 1 : i + 2 * pairs : 2]
        ok = (words[:, 0] == words[0, 0]) & (words[:, 1] == Special.APS_COLUMN_END) & (ends - starts == expected_y)
        ok[1:] &= starts[1:] == ends[:-1]  # no samples between a column end and the next column start
        return pairs if ok.all() else int(np.argmin(ok))

    def _bulk_columns(self, start_word: int, pairs: int, cuts: np.ndarray, i: int, store_base: int) -> int:
        """Apply ``pairs`` whole columns at once (same effect as the per-word path); return the ADC index done."""
        aps = self._aps
        readout = _READOUT_RESET if start_word == Special.APS_RESET_COLUMN_START else _READOUT_SIGNAL
        aps.readout = readout
        first_col = aps.count_x[readout]
        accepted = max(0, min(pairs, aps.expected_x - first_col))
        if accepted:
            starts = cuts[i : i + 2 * accepted : 2] + store_base
            segments = np.empty((accepted, 5), np.int64)
            segments[:, 0] = readout
            segments[:, 1] = first_col + np.arange(accepted)
            segments[:, 2] = 0
            segments[:, 3] = starts
            segments[:, 4] = starts + aps.expected_y
            aps.pending.append(segments)
        self._stats.aps_samples_dropped += (pairs - accepted) * aps.expected_y
        aps.count_x[readout] = first_col + pairs
        aps.count_y[readout] = aps.expected_y if accepted == pairs else 0
        return int(cuts[i + 2 * pairs - 1])

    def _interrupt(self, aps: _ApsState, imu: _ImuState) -> None:
        """Timestamp reset or big wrap: drop the frame / IMU sample in progress and ignore until the next start."""
        if aps.in_frame and not aps.ignore:
            self._stats.aps_frames_dropped += 1
        if imu.in_sample and not imu.ignore:
            self._stats.imu_samples_dropped += 1
        aps.ignore = True
        aps.in_frame = False
        imu.ignore = True
        imu.in_sample = False

    def _end_frame(self, t_us: int, chunk: DecodedChunk) -> None:
        aps = self._aps
        if not aps.in_frame:  # a second frame end without a new frame start delivers nothing
            return
        valid = aps.count_x[_READOUT_RESET] == aps.count_x[_READOUT_SIGNAL] == aps.expected_x and aps.expected_x > 0
        if valid:
            npix = aps.size_x * aps.size_y
            pixels = aps.pixel_buffer[:npix].reshape(aps.size_y, aps.size_x).copy()
            chunk.frames.append(
                ApsFrame(
                    pixels=pixels,
                    position_x=aps.position_x,
                    position_y=aps.position_y,
                    t_start_of_frame_us=aps.t_sof,
                    t_start_exposure_us=aps.t_soe,
                    t_end_exposure_us=aps.t_eoe,
                    t_end_of_frame_us=t_us,
                )
            )
        else:
            self._stats.aps_frames_dropped += 1
        aps.in_frame = False

    def _flush_aps(self) -> None:
        """Write queued ADC column segments into the reset/pixel buffers, one vectorised write per same-type run."""
        aps = self._aps
        pending = aps.pending
        if not pending:
            return
        aps.pending = []
        if len(aps.store) > 1:
            aps.store = [np.concatenate(aps.store)]
        adc_vals = aps.store[0]
        # rows: readout, count_x, first_row, adc start, adc stop; items are single tuples or bulk (k, 5) arrays
        blocks: list[np.ndarray] = []
        singles: list[tuple] = []
        for item in pending:
            if isinstance(item, tuple):
                singles.append(item)
            else:
                if singles:
                    blocks.append(np.array(singles, dtype=np.int64))
                    singles = []
                blocks.append(item)
        if singles:
            blocks.append(np.array(singles, dtype=np.int64))
        seg = blocks[0] if len(blocks) == 1 else np.concatenate(blocks)
        seg = self._merge_split_columns(seg)
        readout = seg[:, 0]
        cuts = [0, *(np.flatnonzero(readout[1:] != readout[:-1]) + 1).tolist(), seg.shape[0]]
        expected_y = aps.expected_y
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            group = seg[lo:hi]
            # a transfer boundary can leave a partial column at either end of a run of whole columns
            head = 0 if group[0, 2] == 0 and group[0, 4] - group[0, 3] == expected_y else 1
            tail = group.shape[0] - (0 if group[-1, 2] == 0 and group[-1, 4] - group[-1, 3] == expected_y else 1)
            if tail - head >= _MIN_BLOCK_COLUMNS and self._is_full_column_run(group[head:tail]):
                self._write_segments(group[:head], adc_vals)
                self._write_column_block(group[head:tail], adc_vals)
                self._write_segments(group[tail:], adc_vals)
            else:
                self._write_segments(group, adc_vals)

    @staticmethod
    def _merge_split_columns(seg: np.ndarray) -> np.ndarray:
        """Join consecutive segments that continue the same column (a column cut by a transfer boundary)."""
        if seg.shape[0] < 2:
            return seg
        prev, cur = seg[:-1], seg[1:]
        continues = (
            (cur[:, 0] == prev[:, 0])
            & (cur[:, 1] == prev[:, 1])
            & (cur[:, 2] == prev[:, 2] + prev[:, 4] - prev[:, 3])
            & (cur[:, 3] == prev[:, 4])
        )
        if not continues.any():
            return seg
        keep = np.ones(seg.shape[0], bool)
        keep[1:] = ~continues
        merged = seg[keep]
        last_of_group = np.flatnonzero(np.append(keep[1:], True))
        merged[:, 4] = seg[last_of_group, 4]
        return merged

    def _is_full_column_run(self, group: np.ndarray) -> bool:
        """True when the segments are whole, consecutive columns of consecutive samples (the normal case)."""
        k = group.shape[0]
        expected_y = self._aps.expected_y
        steps = np.arange(k)
        return bool(
            np.all(group[:, 2] == 0)
            and np.all(group[:, 4] - group[:, 3] == expected_y)
            and np.all(group[:, 1] == group[0, 1] + steps)
            and np.all(group[:, 3] == group[0, 3] + steps * expected_y)
        )

    def _write_column_block(self, group: np.ndarray, adc_vals: np.ndarray) -> None:
        """Fast path: k whole device columns → one rectangular slice of the ROI buffers."""
        aps = self._aps
        k = group.shape[0]
        first_col = int(group[0, 1])
        start = int(group[0, 3])
        device = adc_vals[start : start + k * aps.expected_y].reshape(k, aps.expected_y)  # [column, sample]
        if aps.flip_y:
            device = device[:, ::-1]
        if aps.flip_x:
            device = device[::-1, :]
            lo = aps.expected_x - first_col - k
        else:
            lo = first_col
        npix = aps.size_x * aps.size_y
        reset2d = aps.reset_buffer[:npix].reshape(aps.size_y, aps.size_x)
        pixel2d = aps.pixel_buffer[:npix].reshape(aps.size_y, aps.size_x)
        if aps.invert_xy:  # device columns are output rows
            region = (slice(lo, lo + k), slice(None))
            values = device
        else:
            region = (slice(None), slice(lo, lo + k))
            values = device.T
        if group[0, 0] == _READOUT_RESET:
            reset2d[region] = values
        else:
            pixel2d[region] = self._cds(reset2d[region], values)

    def _write_segments(self, group: np.ndarray, adc_vals: np.ndarray) -> None:
        """General path: arbitrary (partial, repeated) segments, scattered sample by sample (vectorised)."""
        aps = self._aps
        if group.shape[0] == 0:
            return
        lengths = group[:, 4] - group[:, 3]
        total = int(lengths.sum())
        if total == 0:
            return
        first = np.cumsum(lengths) - lengths
        within = np.arange(total) - np.repeat(first, lengths)
        sample = np.repeat(group[:, 3], lengths) + within
        pos_y = np.repeat(group[:, 2], lengths) + within
        pos_x = np.repeat(group[:, 1], lengths)
        if aps.flip_x:
            pos_x = aps.expected_x - 1 - pos_x
        if aps.flip_y:
            pos_y = aps.expected_y - 1 - pos_y
        if aps.invert_xy:
            pos_x, pos_y = pos_y, pos_x
        index = pos_y * aps.size_x + pos_x
        values = adc_vals[sample]
        if group[0, 0] == _READOUT_RESET:
            aps.reset_buffer[index] = values
        else:
            aps.pixel_buffer[index] = self._cds(aps.reset_buffer[index], values)

    @staticmethod
    def _cds(reset: np.ndarray, signal: np.ndarray) -> np.ndarray:
        """libcaer CDS: clamp(reset - signal, 0, 1023), forced to 1023 if reset < 384 or signal == 0; << 6."""
        cds = reset - signal
        np.maximum(cds, 0, out=cds)
        np.minimum(cds, APS_PIXEL_MAX, out=cds)
        np.putmask(cds, (reset < APS_RESET_MIN) | (signal == 0), APS_PIXEL_MAX)
        np.left_shift(cds, APS_PIXEL_SHIFT, out=cds)
        return cds.astype(np.uint16)

    # ------------------------------------------------------------------ IMU
    @staticmethod
    def _imu_scale(imu: _ImuState, byte: int) -> None:
        imu.present = (byte >> 5) & 7
        accel_fs = (byte >> 2) & 3
        gyro_fs = byte & 3
        imu.accel_lsb_per_g = 65536.0 / (4 * (1 << accel_fs))
        imu.gyro_lsb_per_dps = 65536.0 / (500 * (1 << gyro_fs))
        if imu.present & _IMU_ACCEL:
            imu.count = 0
        elif imu.present & _IMU_TEMP:
            imu.count = 6
        elif imu.present & _IMU_GYRO:
            imu.count = 8
        else:
            imu.count = IMU_TOTAL_COUNT

    @staticmethod
    def _imu_byte(imu: _ImuState, byte: int) -> None:
        count = imu.count
        if count >= IMU_TOTAL_COUNT:
            imu.count = count + 1
            return
        if count % 2 == 0:
            imu.high_byte = byte
        else:
            raw = (imu.high_byte << 8) | byte
            if raw >= 0x8000:
                raw -= 0x10000
            slot = count // 2  # 0-2 accel, 3 temperature, 4-6 gyro
            if slot < 3:
                imu.values[slot] = imu.flip[slot] * raw / imu.accel_lsb_per_g
                if slot == 2 and not imu.present & _IMU_TEMP:
                    count += 2 if imu.present & _IMU_GYRO else 8
            elif slot == 3:
                imu.values[3] = raw / imu.temp_scale + imu.temp_offset
                if not imu.present & _IMU_GYRO:
                    count += 6
            else:
                imu.values[slot] = imu.flip[slot - 4] * raw / imu.gyro_lsb_per_dps
        imu.count = count + 1
