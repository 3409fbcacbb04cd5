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
kernel, control words (specials, misc8, misc10, big wraps) run through a compact Python loop, except runs of whole
APS columns (column start, expected rows of samples, column end, ...), which are recognised with numpy and applied in
bulk. APS ADC samples are never looped over: they are queued as column segments (their values kept in a bounded
store across transfers) and written into the frame buffers once per frame — runs of whole columns as one rectangular
slice, anything irregular with one vectorised scatter per group of same-type segments.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, fields
from typing import Final, NamedTuple

import numpy as np

from davis_rig.errors import ConfigError, MissingDependencyError, ProtocolError
from davis_rig.protocol.frames import ApsFrame
from davis_rig.protocol.layout import SensorLayout
from davis_rig.protocol.words import (
    APS_PIXEL_MAX,
    APS_PIXEL_SHIFT,
    APS_RESET_MIN,
    CODE_SHIFT,
    DATA_MASK,
    IMU_TOTAL_COUNT,
    MISC8_BYTE_MASK,
    MISC8_SUB_SHIFT,
    MISC10_SUB_SHIFT,
    OVERFLOW_SHIFT,
    TIMESTAMP_FLAG,
    TIMESTAMP_MASK,
    Code,
    Misc8,
    Special,
    SpecialType,
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
#: ROI and IMU values arrive as big-endian byte pairs (misc8 payloads); IMU values are signed 16-bit.
_BYTE_BITS: Final = MISC8_BYTE_MASK.bit_length()
_INT16_SPAN: Final = 1 << 16

# Plain ints of the word codes: numpy compares arrays with an IntEnum member as int64 (about 10x slower than
# with a plain int), and the per-control-word loop avoids enum attribute lookups.
_SPECIAL: Final = int(Code.SPECIAL)
_Y_ADDR: Final = int(Code.Y_ADDR)
_ADC_SAMPLE: Final = int(Code.ADC_SAMPLE)
_MISC8: Final = int(Code.MISC8)
_MISC10: Final = int(Code.MISC10)
_TS_WRAP: Final = int(Code.TS_WRAP)
_TS_RESET_WORD: Final = int(Special.TIMESTAMP_RESET)  # the whole word: code 0, sub-code 1
_RESET_COLUMN: Final = int(Special.APS_RESET_COLUMN_START)
_SIGNAL_COLUMN: Final = int(Special.APS_SIGNAL_COLUMN_START)
_COLUMN_END: Final = int(Special.APS_COLUMN_END)

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
    n_special = int(np.count_nonzero(codes == _SPECIAL))
    # codes 4-7 (uint16 arithmetic wraps below 4, and timestamp words give 8-15)
    n_high = int(np.count_nonzero((codes - np.uint16(_ADC_SAMPLE)) <= _TS_WRAP - _ADC_SAMPLE))
    is_wrap, n_wrap = None, 0
    if n_high:
        is_wrap = codes == _TS_WRAP
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


class _ControlBlock:
    """State of one block's control-word pass: the ADC samples' cursor and the specials and IMU rows found.

    Args:
        aps: the decoder's APS state (receives the queued column segments).
        stats: the decoder's counters.
        ctrl_words: uint16 [C] the control words in stream order.
        cut_array: int64 [C] number of the block's ADC samples before each control word.
        n_adc: ADC samples in the block.
        store_base: index of the block's first ADC sample in the APS sample store.
    """

    __slots__ = ("aps", "stats", "ctrl_words", "cut_array", "cuts", "n_adc", "store_base", "adc_done", "specials",
                 "imu_rows")

    def __init__(self, aps: _ApsState, stats: DecoderStats, ctrl_words: np.ndarray, cut_array: np.ndarray,
                 n_adc: int, store_base: int):
        self.aps = aps
        self.stats = stats
        self.ctrl_words = ctrl_words
        self.cut_array = cut_array
        self.cuts = cut_array.tolist()
        self.n_adc = n_adc
        self.store_base = store_base
        self.adc_done = 0
        self.specials: list[tuple[int, int]] = []
        self.imu_rows: list[tuple] = []

    def take_samples(self, upto: int) -> None:
        """Queue the ADC samples before block sample ``upto`` as a column segment of the current readout."""
        k = upto - self.adc_done
        if k <= 0:
            return
        start = self.adc_done
        self.adc_done = upto
        aps = self.aps
        if aps.ignore:
            self.stats.aps_samples_dropped += k
            return
        r = aps.readout
        cx = aps.count_x[r]
        cy = aps.count_y[r]
        if cx >= aps.expected_x:
            self.stats.aps_samples_dropped += k
            return
        take = min(k, max(aps.expected_y - cy, 0))
        self.stats.aps_samples_dropped += k - take
        if take:
            aps.pending.append((r, cx, cy, self.store_base + start, self.store_base + start + take))
            aps.count_y[r] = cy + take


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
        self._aps = _ApsState(layout)
        self._imu = _ImuState(layout)
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
            self._control(w, codes, ctrl_pos, times, chunk)
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
            self._control(w, w >> CODE_SHIFT, ctrl_pos, ctrl_times, chunk)
        return chunk

    def _last_row_keys(self, w: np.ndarray, codes: np.ndarray, idx12: np.ndarray) -> np.ndarray:
        """Forward fill of ((index + 1) << 12 | y) over the in-range Y words (0 before the block's first one)."""
        n = w.shape[0]
        y_data = w - _Y_WORD_BASE  # the row for Y words; >= 0x1000 (so never "in range") for any other word
        valid_y = y_data < self._dvs_rows
        self._stats.dvs_out_of_range += int(np.count_nonzero(codes == _Y_ADDR)) - int(np.count_nonzero(valid_y))
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
        ctrl_mask = (codes == _SPECIAL) | (codes == _MISC8) | (codes == _MISC10)
        if big_wrap_pos is not None:
            ctrl_mask[big_wrap_pos] = True
        ctrl_pos = np.flatnonzero(ctrl_mask)
        times = np.maximum(key_t[ctrl_pos], offset_in) & TIMESTAMP_MASK
        times += base.at(ctrl_pos)
        return ctrl_pos, times

    def _control(self, w, codes, ctrl_pos: np.ndarray, times: np.ndarray, chunk: DecodedChunk) -> None:
        """Run the control words of a block in stream order (specials, misc8/misc10, big wraps, ADC segments).

        Args:
            w: uint16 [n] the block's words; codes: ``w >> CODE_SHIFT``.
            ctrl_pos: int64 [C] positions of the control words; times: int64 [C] stream time right after each, µs.
            chunk: receives the specials, IMU samples and frames.
        """
        block = self._control_block(w, codes, ctrl_pos)
        words_list = block.ctrl_words.tolist()
        times_list = times.tolist()
        n_ctrl = len(words_list)
        i = -1
        while i + 1 < n_ctrl:
            i += 1
            word = words_list[i]
            cut = block.cuts[i]
            if (word == _RESET_COLUMN or word == _SIGNAL_COLUMN) and self._column_run_starts(block, words_list, i):
                # a run of whole columns (start, expected_y samples, end, start, ...): handled in bulk
                pairs = self._column_run(block.ctrl_words, block.cut_array, i)
                if pairs >= 2:
                    block.take_samples(cut)
                    block.adc_done = self._bulk_columns(word, pairs, block.cut_array, i, block.store_base)
                    i += 2 * pairs - 1
                    continue
            code = word >> CODE_SHIFT
            if code == _SPECIAL:
                self._special(block, word & DATA_MASK, times_list[i], cut, chunk)
            elif code == _MISC8:
                self._misc8(block, word & DATA_MASK, cut)
            elif code == _MISC10:
                if (word & DATA_MASK) >> MISC10_SUB_SHIFT:
                    self._stats.unknown_words += 1
                # sub-code 0 = exposure value parts, only used by libcaer's auto-exposure: consumed.
            else:  # big wrap (code 7)
                self._big_wrap(block, times_list[i], cut)
        self._finish_control(block, chunk)

    def _control_block(self, w: np.ndarray, codes: np.ndarray, ctrl_pos: np.ndarray) -> _ControlBlock:
        """Start a block's control pass: its ADC samples go to the APS sample store, cut at each control word."""
        aps = self._aps
        adc_pos = np.flatnonzero(codes == _ADC_SAMPLE)
        if adc_pos.shape[0]:
            adc_vals = (w[adc_pos] & DATA_MASK).astype(np.int32)
            cut_array = np.searchsorted(adc_pos, ctrl_pos)
        else:
            adc_vals = np.empty(0, np.int32)
            cut_array = np.zeros(ctrl_pos.shape[0], np.int64)
        store_base = aps.store_len  # block ADC index i is store index store_base + i
        if adc_vals.shape[0]:
            aps.store.append(adc_vals)
            aps.store_len += adc_vals.shape[0]
        return _ControlBlock(aps, self._stats, w[ctrl_pos], cut_array, adc_vals.shape[0], store_base)

    def _column_run_starts(self, block: "_ControlBlock", words_list: list, i: int) -> bool:
        """Whether the column start at control ``i`` begins at least two whole columns (cheap scalar pre-check)."""
        aps = self._aps
        return (
            not aps.ignore
            and i + 3 < len(words_list)
            and words_list[i + 1] == _COLUMN_END
            and words_list[i + 2] == words_list[i]
            and block.cuts[i + 1] - block.cuts[i] == aps.expected_y
        )

    def _finish_control(self, block: "_ControlBlock", chunk: DecodedChunk) -> None:
        """Queue the block's trailing ADC samples, bound the sample store, and attach specials and IMU rows."""
        aps = self._aps
        block.take_samples(block.n_adc)
        if aps.pending and aps.store_len > _STORE_FLUSH_SAMPLES:  # bound memory on streams that never end a frame
            self._flush_aps()
        if not aps.pending:  # nothing refers to the stored samples any more
            aps.store = []
            aps.store_len = 0
        if block.specials:
            chunk.specials = np.array(block.specials, dtype=SPECIAL_DTYPE)
        if block.imu_rows:
            chunk.imu = np.array(block.imu_rows, dtype=IMU6_DTYPE)

    def _special(self, block: "_ControlBlock", sub: int, t: int, cut: int, chunk: DecodedChunk) -> None:
        """One special word (code 0, PROTOCOL.md §8.1) at stream time ``t`` µs."""
        aps = self._aps
        imu = self._imu
        if sub == Special.TIMESTAMP_RESET:
            block.take_samples(cut)
            self._flush_aps()
            self._stats.timestamp_resets += 1
            self._interrupt(aps, imu)
            block.specials.append((t, SpecialType.TIMESTAMP_RESET))
        elif sub in _SPECIAL_TYPE_OF_WIRE:
            block.specials.append((t, _SPECIAL_TYPE_OF_WIRE[sub]))
        elif sub == Special.IMU_START_6:
            if imu.in_sample and not imu.ignore:
                self._stats.imu_samples_dropped += 1
            imu.ignore = False
            imu.in_sample = True
            imu.count = 0
            imu.present = 0
            imu.values = [0.0] * 7
        elif sub == Special.IMU_END:
            self._imu_end(block, t)
        elif sub == Special.APS_FRAME_START_GS or sub == Special.APS_FRAME_START_RS:
            block.take_samples(cut)
            self._flush_aps()
            self._aps_frame_start(t)
            block.specials.append((t, SpecialType.APS_FRAME_START))
        elif Special.APS_FRAME_END <= sub <= Special.APS_EXPOSURE_END:
            if not aps.ignore:
                self._aps_readout(block, sub, t, cut, chunk)
        else:
            self._stats.unknown_words += 1

    def _imu_end(self, block: "_ControlBlock", t: int) -> None:
        """IMU end special: deliver the sample if exactly :data:`IMU_TOTAL_COUNT` bytes came, else count a drop."""
        imu = self._imu
        if imu.ignore:
            return
        if imu.count == IMU_TOTAL_COUNT:
            v = imu.values
            block.imu_rows.append((t, v[0], v[1], v[2], v[4], v[5], v[6], v[3]))
        else:
            self._stats.imu_samples_dropped += 1
        imu.in_sample = False

    def _aps_frame_start(self, t: int) -> None:
        """APS frame start (global or rolling shutter): a frame still in progress is dropped."""
        aps = self._aps
        if aps.in_frame and not aps.ignore:
            self._stats.aps_frames_dropped += 1
        aps.ignore = False
        aps.in_frame = True
        aps.roi_counter = 0
        aps.readout = _READOUT_RESET
        aps.count_x = [0, 0]
        aps.count_y = [0, 0]
        aps.t_sof = t
        aps.pixel_buffer.fill(0)

    def _aps_readout(self, block: "_ControlBlock", sub: int, t: int, cut: int, chunk: DecodedChunk) -> None:
        """APS frame end, column start/end and exposure start/end specials of a frame being read."""
        aps = self._aps
        if sub == Special.APS_EXPOSURE_START:
            aps.t_soe = t
            block.specials.append((t, SpecialType.APS_EXPOSURE_START))
            return
        if sub == Special.APS_EXPOSURE_END:
            aps.t_eoe = t
            block.specials.append((t, SpecialType.APS_EXPOSURE_END))
            return
        block.take_samples(cut)
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
            block.specials.append((t, SpecialType.APS_FRAME_END))
            self._end_frame(t, chunk)

    def _misc8(self, block: "_ControlBlock", data: int, cut: int) -> None:
        """One misc 8-bit word (code 5): IMU data/scale byte or APS ROI byte."""
        aps = self._aps
        imu = self._imu
        misc = data >> MISC8_SUB_SHIFT
        byte = data & MISC8_BYTE_MASK
        if misc == Misc8.IMU_DATA:
            if not imu.ignore:
                self._imu_byte(imu, byte)
        elif misc == Misc8.APS_ROI_HIGH:
            aps.roi_high = byte
        elif misc == Misc8.APS_ROI_LOW:
            slot = aps.roi_counter & 3
            aps.roi_values[slot] = (aps.roi_high << _BYTE_BITS) | byte
            aps.roi_counter += 1
            if slot == 3:
                block.take_samples(cut)
                self._flush_aps()
                aps.set_roi()
        elif misc == Misc8.IMU_SCALE:
            if not imu.ignore:
                self._imu_scale(imu, byte)
        else:
            self._stats.unknown_words += 1

    def _big_wrap(self, block: "_ControlBlock", t: int, cut: int) -> None:
        """A wrap that overflowed the 31-bit timestamp: interrupt APS/IMU and emit TIMESTAMP_WRAP at ``t``."""
        block.take_samples(cut)
        self._flush_aps()
        self._stats.big_wraps += 1
        self._interrupt(self._aps, self._imu)
        block.specials.append((t, SpecialType.TIMESTAMP_WRAP))

    def _column_run(self, ctrl_words: np.ndarray, cuts: np.ndarray, i: int) -> int:
        """Number of consecutive whole-column (start, end) pairs of the same readout type starting at control i."""
        expected_y = self._aps.expected_y
        pairs = min((ctrl_words.shape[0] - i) // 2, 2 * max(self._aps.expected_x, 1) + 2)
        words = ctrl_words[i : i + 2 * pairs].reshape(pairs, 2)
        starts = cuts[i : i + 2 * pairs : 2]
        ends = cuts[i + 1 : i + 2 * pairs : 2]
        ok = (words[:, 0] == words[0, 0]) & (words[:, 1] == _COLUMN_END) & (ends - starts == expected_y)
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
            raw = (imu.high_byte << _BYTE_BITS) | byte
            if raw >= _INT16_SPAN >> 1:  # signed 16-bit
                raw -= _INT16_SPAN
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
