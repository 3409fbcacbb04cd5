"""Vectorised DAVIS (logic 18) stream decoder: USB bytes → DVS events, APS frames, IMU6 samples, specials.

Semantics follow libcaer 3.x (PROTOCOL.md §8-§13) with two deliberate differences, both documented on
:class:`StreamDecoder`: the 64-bit overflow is computed per event (the intended value of vector V19, not libcaer's
stale per-packet value), and TIMESTAMP_RESET / TIMESTAMP_WRAP specials carry the stream time at which they happen
instead of libcaer's ``INT32_MAX`` marker.

Implementation: the DVS/timestamp path has no per-word Python loop. Two kernels give bit-identical output: the
compiled one (``_decode_kernel.c``, an optional C extension built by ``pip install``; one pass over the words that
writes the events and lists the control words with their times) and the numpy one (the reference and the fallback
where no C compiler was present). In the numpy kernel, per block of words, the timestamp base is a cumulative sum
of wrap increments segmented at resets, the 15-bit timestamp and the last row address are forward-filled with
``np.maximum.accumulate`` over ``(index << k) | value`` keys, and events are selected with masks. With either
kernel, control words (specials, misc8, misc10, big wraps) run through a compact Python loop
(:mod:`davis_rig.protocol.control_words`), except runs of whole APS columns (column start, expected rows of samples,
column end, ...), which are recognised with numpy and applied in bulk. APS ADC samples are never looped over: they
are queued as column segments (their values kept in a bounded store across transfers) and written into the frame
buffers once per frame (:mod:`davis_rig.protocol.aps_assembly`) — runs of whole columns as one rectangular slice,
anything irregular with one vectorised scatter per group of same-type segments. IMU samples:
:mod:`davis_rig.protocol.imu_assembly`; the output types: :mod:`davis_rig.protocol.decoded`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Final, NamedTuple

import numpy as np

from davis_rig.errors import ConfigError, MissingDependencyError, ProtocolError
from davis_rig.protocol.control_words import ControlPass
from davis_rig.protocol.decoded import IMU6_DTYPE, SPECIAL_DTYPE, DecodedChunk, DecoderStats
from davis_rig.protocol.layout import SensorLayout
from davis_rig.protocol.words import (
    CODE_ADC_SAMPLE,
    CODE_MISC10,
    CODE_MISC8,
    CODE_SPECIAL,
    CODE_TS_WRAP,
    CODE_Y_ADDR,
    CODE_SHIFT,
    DATA_MASK,
    OVERFLOW_SHIFT,
    TIMESTAMP_FLAG,
    TIMESTAMP_MASK,
    Code,
    Special,
)
from davis_rig.types import EVENT_DTYPE

try:  # the compiled DVS/timestamp pass (_decode_kernel.c), built by `pip install` where a C compiler is present
    from davis_rig.protocol import _decode_kernel
except ImportError:  # not built: the numpy path decodes (same output)
    _decode_kernel = None

_log = logging.getLogger(__name__)

__all__ = [
    "SPECIAL_DTYPE",
    "IMU6_DTYPE",
    "DecoderStats",
    "DecodedChunk",
    "KERNELS",
    "KERNEL_ENV",
    "StreamDecoder",
    "compiled_kernel_available",
]

#: Words decoded per vectorised block; bounds temporary memory (about 40 bytes per word) and keeps it in cache.
_BLOCK_WORDS: Final = 1 << 15
#: Words per call of the compiled kernel: it needs no temporaries (its event buffer, 13 bytes per word, is shrunk to
#: the events found), so only the control pass's ADC sample store (4 bytes per sample) scales with it.
_KERNEL_BLOCK_WORDS: Final = 1 << 20
#: Forward-fill keys are ``(index + 1) << shift | value``: the shift is the bit width of the filled value.
_TS_KEY_SHIFT: Final = TIMESTAMP_MASK.bit_length()
_Y_KEY_SHIFT: Final = DATA_MASK.bit_length()
#: A wrap increment is ``multiplier << _TS_KEY_SHIFT`` µs (one unit = WRAP_TICKS_US = 2**15 µs).
_WRAP_UNIT_SHIFT: Final = TIMESTAMP_MASK.bit_length()
#: X-address words are codes 2 (OFF) and 3 (ON): bits 15-13 == 0b001; the polarity is code bit 0.
_X_ADDR_SHIFT: Final = CODE_SHIFT + 1
_X_ADDR_KEY: Final = int(Code.X_ADDR_OFF) >> 1
_POLARITY_SHIFT: Final = CODE_SHIFT
#: Y-address words minus this are the row (0..4095); any other word minus it is >= 0x1000 or wraps around.
_Y_WORD_BASE: Final = np.uint16(int(Code.Y_ADDR) << CODE_SHIFT)
#: Largest 16-bit word value.
_WORD_MAX: Final = 0xFFFF

#: The timestamp-reset word as a plain int (the codes' plain ints: protocol.words).
_TS_RESET_WORD: Final = int(Special.TIMESTAMP_RESET)  # the whole word: code 0, sub-code 1

#: Decoder kernels: the compiled DVS/timestamp pass, or the vectorised numpy path (the reference and fallback).
KERNELS: Final = ("compiled", "numpy")
#: Environment variable naming the kernel when :class:`StreamDecoder` is given none (default: compiled if built).
KERNEL_ENV: Final = "DAVIS_RIG_DECODER_KERNEL"

# int64 state buffer of the compiled kernel (ST_* in _decode_kernel.c): clock, last row, last event, geometry.
_ST_BASE, _ST_OFFSET, _ST_LAST_Y, _ST_LAST_T, _ST_HAS_LAST_T, _ST_ROWS, _ST_COLUMNS, _ST_INVERT_XY = range(8)
_ST_LEN: Final = 8

_LOSS_COUNTERS: Final = (
    "odd_bytes_dropped",
    "unknown_words",
    "dvs_out_of_range",
    "aps_frames_dropped",
    "aps_samples_dropped",
    "imu_samples_dropped",
    "non_monotonic_timestamps",
)

def compiled_kernel_available() -> bool:
    """Whether the compiled decoder kernel was built (``pip install`` with a C compiler) and imports."""
    return _decode_kernel is not None


def _resolve_kernel(kernel: str | None) -> str:
    """The kernel a decoder uses: ``kernel``, else :data:`KERNEL_ENV`, else ``compiled`` when built."""
    source = "kernel"
    if kernel is None:
        kernel = os.environ.get(KERNEL_ENV) or None
        source = KERNEL_ENV
    if kernel is None:
        return "compiled" if _decode_kernel is not None else "numpy"
    if kernel not in KERNELS:
        raise ConfigError(source, f"expected one of {', '.join(KERNELS)}, got {kernel!r}")
    if kernel == "compiled" and _decode_kernel is None:
        raise MissingDependencyError(
            f"{source}=compiled: the compiled decoder kernel davis_rig.protocol._decode_kernel is not built; reinstall "
            "with a C compiler present (pip install -e .), or use the numpy kernel (same output, slower)"
        )
    return kernel


class _WordKinds(NamedTuple):
    """Counts and masks of one block's word kinds that decide which decoding steps run.

    Attributes:
        n_rare: specials, ADC samples, misc8 and misc10 words (the control-word path).
        is_wrap: bool [n] wrap words (code 7), ``None`` when the block has no code 4-7 word.
        n_wrap: number of wrap words.
        is_reset: bool [n] TIMESTAMP_RESET words, ``None`` when the block has no special word.
        n_reset: number of TIMESTAMP_RESET words.
    """

    n_rare: int
    is_wrap: np.ndarray | None
    n_wrap: int
    is_reset: np.ndarray | None
    n_reset: int


def _word_kinds(w: np.ndarray, codes: np.ndarray) -> _WordKinds:
    """Classify a block's words (``codes = w >> CODE_SHIFT``; timestamp words give codes 8-15)."""
    n_special = int(np.count_nonzero(codes == CODE_SPECIAL))
    # codes 4-7 (uint16 arithmetic wraps below 4, and timestamp words give 8-15)
    n_high = int(np.count_nonzero((codes - np.uint16(CODE_ADC_SAMPLE)) <= CODE_TS_WRAP - CODE_ADC_SAMPLE))
    is_wrap, n_wrap = None, 0
    if n_high:
        is_wrap = codes == CODE_TS_WRAP
        n_wrap = int(np.count_nonzero(is_wrap))
    is_reset, n_reset = None, 0
    if n_special:
        is_reset = w == _TS_RESET_WORD
        n_reset = int(np.count_nonzero(is_reset))
    return _WordKinds(n_special + n_high - n_wrap, is_wrap, n_wrap, is_reset, n_reset)


@dataclass(slots=True)
class _WrapBase:
    """The wrap base of one block: ``(overflow << 31) + wrapAdd`` in µs, 64-bit, after each wrap/reset word.

    Attributes:
        base_prev: base carried in from the previous block, µs.
        base_end: base after the block's last word, µs.
        changes: int64 [C] positions of the wrap and reset words (``None``: the block has none).
        change_base: int64 [C] base right after each of them, µs.
        increments: int64 [C] what each added (``multiplier << 15``; 0 for a reset), µs.
        change_is_reset: bool [C] which of them are resets.
    """

    base_prev: int
    base_end: int
    changes: np.ndarray | None = None
    change_base: np.ndarray | None = None
    increments: np.ndarray | None = None
    change_is_reset: np.ndarray | None = None

    def at(self, positions: np.ndarray):
        """Wrap base in effect at (after) each word position, µs; a scalar when the block has no change."""
        if self.changes is None:
            return self.base_prev
        j = np.searchsorted(self.changes, positions, side="right") - 1
        return np.where(j >= 0, self.change_base[np.maximum(j, 0)], self.base_prev)

    def big_wrap_positions(self) -> np.ndarray | None:
        """Positions of the wraps that overflow the 31-bit timestamp (libcaer TIMESTAMP_WRAP), or ``None``."""
        if self.changes is None:
            return None
        before = self.change_base - self.increments
        crossed = (self.change_base >> OVERFLOW_SHIFT) != (before >> OVERFLOW_SHIFT)
        crossed &= ~self.change_is_reset
        return self.changes[crossed] if crossed.any() else None


def _wrap_base(w: np.ndarray, kinds: _WordKinds, base_prev: int) -> _WrapBase:
    """Cumulative wrap base of a block: a wrap adds ``multiplier << 15`` µs, a reset restarts at 0."""
    if not (kinds.n_wrap or kinds.n_reset):
        return _WrapBase(base_prev, base_prev)
    if not kinds.n_reset:
        is_change = kinds.is_wrap
    elif kinds.is_wrap is None:
        is_change = kinds.is_reset
    else:
        is_change = kinds.is_wrap | kinds.is_reset
    changes = np.flatnonzero(is_change)
    change_words = w[changes]
    increments = (change_words & DATA_MASK).astype(np.int64) << _WRAP_UNIT_SHIFT
    change_is_reset = change_words == _TS_RESET_WORD
    increments[change_is_reset] = 0
    change_base = np.cumsum(increments)
    if kinds.n_reset:
        k = np.arange(changes.shape[0])
        last_reset = np.maximum.accumulate(np.where(change_is_reset, k, -1))
        change_base += np.where(last_reset >= 0, -change_base[np.maximum(last_reset, 0)], base_prev)
    else:
        change_base += base_prev
    return _WrapBase(base_prev, int(change_base[-1]), changes, change_base, increments, change_is_reset)


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

    Two kernels decode the DVS/timestamp words with bit-identical output: a compiled C pass (``_decode_kernel.c``,
    about 6x faster per 8 KiB transfer, see benchmarks/README.md; built by ``pip install`` where a C compiler is
    present) and the vectorised numpy path described in the module docstring (the fallback). Control words
    (specials, APS, IMU) take the same Python path with either.

    Args:
        layout: the device's raw geometry/orientation read-outs.
        reassemble_odd_bytes: if True, a trailing odd byte is carried into the next transfer (its low byte first);
            if False (libcaer), it is dropped and counted in ``stats.odd_bytes_dropped``.
        kernel: ``"compiled"``, ``"numpy"``, or None: the environment variable ``DAVIS_RIG_DECODER_KERNEL`` if
            set, else ``"compiled"`` when it is built.

    Raises:
        ProtocolError: ``layout`` is not a :class:`SensorLayout`.
        ConfigError: an unknown kernel name.
        MissingDependencyError: ``"compiled"`` asked for but not built.
    """

    def __init__(self, layout: SensorLayout, *, reassemble_odd_bytes: bool = False, kernel: str | None = None):
        if not isinstance(layout, SensorLayout):
            raise ProtocolError(f"layout: expected SensorLayout, got {type(layout).__name__}")
        self.kernel = _resolve_kernel(kernel)
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
        self._control_pass = ControlPass(layout, self._stats)  # specials, APS frames, IMU samples
        # work buffers reused by every block (fresh large allocations cost page faults on each call)
        self._idx15 = np.empty(0, np.int64)
        self._idx12 = np.empty(0, np.int64)
        self._key_t = np.empty(0, np.int64)
        self._key_y = np.empty(0, np.int64)
        # the compiled kernel's state (base/offset/last row/last event live here instead of the attributes above)
        self._kernel_state = None
        if self.kernel == "compiled":
            self._kernel_state = np.zeros(_ST_LEN, np.int64)
            self._kernel_state[_ST_ROWS] = self._dvs_rows
            self._kernel_state[_ST_COLUMNS] = self._dvs_cols
            self._kernel_state[_ST_INVERT_XY] = self._dvs_invert

    # ------------------------------------------------------------------ public API
    @property
    def stats(self) -> DecoderStats:
        """Cumulative counters (a snapshot copy)."""
        return self._stats.copy()

    @property
    def current_time_us(self) -> int:
        """Stream clock after the last decoded word, µs (64-bit, overflow included)."""
        if self._kernel_state is not None:
            return int(self._kernel_state[_ST_BASE]) + int(self._kernel_state[_ST_OFFSET])
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
            if words.size and (words.dtype.kind not in "iu" or words.min() < 0 or words.max() > _WORD_MAX):
                raise ProtocolError(f"words: expected integers in 0..65535, got {words.dtype} values")
            words = words.astype(np.uint16)
        n = words.shape[0]
        if n == 0:
            self._warn_once()
            return DecodedChunk()
        self._stats.words += n
        if self._kernel_state is not None:
            words = np.ascontiguousarray(words)
            if n <= _KERNEL_BLOCK_WORDS:
                chunk = self._decode_block_compiled(words)
            else:
                chunk = DecodedChunk.concatenate(
                    self._decode_block_compiled(words[s : s + _KERNEL_BLOCK_WORDS])
                    for s in range(0, n, _KERNEL_BLOCK_WORDS)
                )
        elif n <= _BLOCK_WORDS:
            chunk = self._decode_block(words)
        else:
            # one output array for all blocks (an upper bound: every X word), filled block by block
            out = np.empty(int(np.count_nonzero((words >> _X_ADDR_SHIFT) == _X_ADDR_KEY)), EVENT_DTYPE)
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
        """Decode one block of at most :data:`_BLOCK_WORDS` words (DVS path vectorised, control words looped)."""
        n = w.shape[0]
        idx15, idx12 = self._index_keys(n)
        codes = w >> CODE_SHIFT
        kinds = _word_kinds(w, codes)
        # --- 15-bit offset: forward fill of ((index + 1) << 15 | t15) over time-setting words --------------------
        # Non-setters get key 0; positions before the block's first setter fall back to the carried offset
        # (any setter key is >= 1 << 15 > carried offset), applied with np.maximum on gathered keys only.
        key_t = np.bitwise_or(idx15, w & TIMESTAMP_MASK, out=self._key_t[:n])
        np.multiply(key_t, w >= TIMESTAMP_FLAG, out=key_t)
        offset_in = self._offset_us
        base = _wrap_base(w, kinds, self._base_us)
        if base.changes is not None:
            key_t[base.changes] = idx15[base.changes]  # wraps and resets are setters with offset 0
        np.maximum.accumulate(key_t, out=key_t)
        key_y = self._last_row_keys(w, codes, idx12)
        last_y_in = self._last_y
        xi, events = self._dvs_events(w, key_t, key_y, base, kinds, out)
        chunk = DecodedChunk(events=events)

        # --- control words: specials, misc8, misc10, big wraps; ADC samples as column segments ---------------------
        big_wrap_pos = base.big_wrap_positions()
        if kinds.n_rare or big_wrap_pos is not None:
            ctrl_pos, times = self._control_times(codes, key_t, offset_in, base, big_wrap_pos)
            self._control_pass.run(w, codes, ctrl_pos, times, chunk)
            if kinds.n_reset and xi.shape[0] and int(np.count_nonzero(kinds.is_reset[xi[-1]:])):
                self._last_event_t = None  # a reset after the block's last event

        # --- carry state -------------------------------------------------------------------------------------------
        self._base_us = base.base_end
        self._offset_us = max(int(key_t[-1]), offset_in) & TIMESTAMP_MASK
        self._last_y = max(int(key_y[-1]), last_y_in) & DATA_MASK
        return chunk

    def _decode_block_compiled(self, w: np.ndarray) -> DecodedChunk:
        """:meth:`_decode_block` with the compiled DVS/timestamp pass (same output; control words as there).

        Args:
            w: uint16 [n] C-contiguous, at most :data:`_KERNEL_BLOCK_WORDS`.
        """
        events, n_ctrl, positions, times, n_adc, out_of_range, non_monotonic = _decode_kernel.decode(
            w, self._kernel_state
        )
        chunk = DecodedChunk(events=np.frombuffer(events, EVENT_DTYPE))
        if out_of_range:
            self._stats.dvs_out_of_range += out_of_range
        if non_monotonic:
            self._stats.non_monotonic_timestamps += non_monotonic
        if n_ctrl or n_adc:
            ctrl_pos = np.frombuffer(positions, np.int64, n_ctrl) if n_ctrl else np.empty(0, np.int64)
            ctrl_times = np.frombuffer(times, np.int64, n_ctrl) if n_ctrl else np.empty(0, np.int64)
            self._control_pass.run(w, w >> CODE_SHIFT, ctrl_pos, ctrl_times, chunk)
        return chunk

    def _last_row_keys(self, w: np.ndarray, codes: np.ndarray, idx12: np.ndarray) -> np.ndarray:
        """Forward fill of ((index + 1) << 12 | y) over the in-range Y words (0 before the block's first one)."""
        n = w.shape[0]
        y_data = w - _Y_WORD_BASE  # the row for Y words; >= 0x1000 (so never "in range") for any other word
        valid_y = y_data < self._dvs_rows
        self._stats.dvs_out_of_range += int(np.count_nonzero(codes == CODE_Y_ADDR)) - int(np.count_nonzero(valid_y))
        key_y = np.bitwise_or(idx12, y_data, out=self._key_y[:n])
        np.multiply(key_y, valid_y, out=key_y)
        np.maximum.accumulate(key_y, out=key_y)
        return key_y

    def _dvs_events(self, w, key_t, key_y, base: "_WrapBase", kinds: "_WordKinds", out):
        """DVS polarity events of the block and their non-monotonic count; returns (X word positions, events)."""
        xi = np.flatnonzero((w >> _X_ADDR_SHIFT) == _X_ADDR_KEY)  # codes 2 and 3
        if xi.shape[0]:
            x_words = w[xi]
            xdata = x_words & DATA_MASK
            if int(xdata.max()) >= self._dvs_cols:
                ok = xdata < self._dvs_cols
                self._stats.dvs_out_of_range += xi.shape[0] - int(np.count_nonzero(ok))
                xi = xi[ok]
                xdata = xdata[ok]
                x_words = x_words[ok]
        if not xi.shape[0]:
            if kinds.n_reset:
                self._last_event_t = None
            return xi, np.empty(0, EVENT_DTYPE)
        t = key_t[xi]
        if t[0] < (1 << _TS_KEY_SHIFT):  # events before the block's first setter use the carried offset
            np.maximum(t, self._offset_us, out=t)
        t &= TIMESTAMP_MASK
        t += base.at(xi)
        y = key_y[xi]
        if y[0] < (1 << _Y_KEY_SHIFT):  # events before the block's first Y word use the carried row
            np.maximum(y, self._last_y, out=y)
        y &= DATA_MASK
        events = np.empty(xi.shape[0], EVENT_DTYPE) if out is None else out[: xi.shape[0]]
        events["t"] = t
        if self._dvs_invert:
            events["x"] = y
            events["y"] = xdata
        else:
            events["x"] = xdata
            events["y"] = y
        events["p"] = (x_words >> _POLARITY_SHIFT) & 1
        # non-monotonic event times (a reset between two events restarts the comparison)
        backwards = t[1:] < t[:-1]
        first_backwards = self._last_event_t is not None and int(t[0]) < self._last_event_t
        if kinds.n_reset:
            epoch = np.searchsorted(np.flatnonzero(kinds.is_reset), xi)
            backwards &= epoch[1:] == epoch[:-1]
            first_backwards = first_backwards and int(epoch[0]) == 0
        self._stats.non_monotonic_timestamps += int(np.count_nonzero(backwards)) + int(first_backwards)
        self._last_event_t = int(t[-1])
        return xi, events

    # ------------------------------------------------------------------ control-word path
    @staticmethod
    def _control_times(codes, key_t, offset_in, base: "_WrapBase", big_wrap_pos) -> tuple[np.ndarray, np.ndarray]:
        """Positions of a block's control words (codes 0, 5, 6, big wraps) and the stream time after each, µs."""
        ctrl_mask = (codes == CODE_SPECIAL) | (codes == CODE_MISC8) | (codes == CODE_MISC10)
        if big_wrap_pos is not None:
            ctrl_mask[big_wrap_pos] = True
        ctrl_pos = np.flatnonzero(ctrl_mask)
        times = np.maximum(key_t[ctrl_pos], offset_in) & TIMESTAMP_MASK
        times += base.at(ctrl_pos)
        return ctrl_pos, times
