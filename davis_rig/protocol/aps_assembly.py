"""APS frame assembly from the stream's control words and ADC samples (PROTOCOL.md §11).

A frame is a frame-start special, then per readout (reset, then signal) columns of ADC samples between
column-start and column-end specials, exposure start/end specials, and a frame-end special. The ADC samples are never
looped over one by one: the control-word pass (:mod:`davis_rig.protocol.control_words`) queues them as column
segments ``(readout, column, first row, store start, store stop)`` into a sample store that outlives the transfer,
and :meth:`ApsAssembler.flush` writes them into the reset and pixel buffers once per frame — runs of whole columns
as one rectangular slice, anything irregular with one vectorised scatter per group of same-readout segments. The
pixel value is libcaer's correlated double sampling (:meth:`ApsAssembler.cds`).
"""

from __future__ import annotations

from typing import Final

import numpy as np

from davis_rig.protocol.frames import ApsFrame
from davis_rig.protocol.layout import SensorLayout
from davis_rig.protocol.words import APS_PIXEL_MAX, APS_PIXEL_SHIFT, APS_RESET_MIN, Special

__all__ = ["READOUT_RESET", "READOUT_SIGNAL", "ApsAssembler"]

#: The two readouts of a frame, in stream order.
READOUT_RESET: Final = 0
READOUT_SIGNAL: Final = 1

#: Queued ADC samples are written out at the latest when this many are stored (about 3 full DAVIS346 frames).
_STORE_FLUSH_SAMPLES: Final = 1 << 19

#: Whole-column runs at least this long are written as one rectangular slice; shorter ones by one scatter.
_MIN_BLOCK_COLUMNS: Final = 16

_COLUMN_END: Final = int(Special.APS_COLUMN_END)


class ApsAssembler:
    """The APS frame in progress: readout counters, ROI, exposure times, queued column segments, frame buffers.

    Args:
        layout: the device's APS size and orientation.
        stats: the decoder's :class:`~davis_rig.protocol.decoded.DecoderStats` (``aps_frames_dropped`` and
            ``aps_samples_dropped`` count here).
    """

    def __init__(self, layout: SensorLayout, stats):
        self.stats = stats
        self.width = layout.aps_width
        self.height = layout.aps_height
        self.invert_xy = layout.aps_invert_xy
        self.flip_x = layout.aps_flip_x
        self.flip_y = layout.aps_flip_y
        self.ignore = True
        self.in_frame = False
        self.readout = READOUT_RESET
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

    # --- frame and readout state --------------------------------------------------------------------------------
    def set_roi(self) -> None:
        """Apply the four ROI values (start column/row, end column/row) read from misc8 bytes, as libcaer does."""
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

    def start_frame(self, t: int) -> None:
        """APS frame start (global or rolling shutter) at stream time ``t`` µs: a frame in progress is dropped."""
        if self.in_frame and not self.ignore:
            self.stats.aps_frames_dropped += 1
        self.ignore = False
        self.in_frame = True
        self.roi_counter = 0
        self.readout = READOUT_RESET
        self.count_x = [0, 0]
        self.count_y = [0, 0]
        self.t_sof = t
        self.pixel_buffer.fill(0)

    def start_column(self, readout: int) -> None:
        """Column start of the reset or the signal readout."""
        self.readout = readout
        self.count_y[readout] = 0

    def end_column(self) -> None:
        """Column end of the current readout."""
        self.count_x[self.readout] += 1

    def interrupt(self) -> None:
        """Timestamp reset or big wrap: drop the frame in progress and ignore samples until the next frame start."""
        if self.in_frame and not self.ignore:
            self.stats.aps_frames_dropped += 1
        self.ignore = True
        self.in_frame = False

    def end_frame(self, t_us: int) -> ApsFrame | None:
        """Frame end at stream time ``t_us``: the frame when both readouts have every expected column (call
        :meth:`flush` first), else ``None`` with a drop counted; ``None`` also without a frame in progress."""
        if not self.in_frame:  # a second frame end without a new frame start delivers nothing
            return None
        frame = None
        valid = self.count_x[READOUT_RESET] == self.count_x[READOUT_SIGNAL] == self.expected_x and self.expected_x > 0
        if valid:
            npix = self.size_x * self.size_y
            pixels = self.pixel_buffer[:npix].reshape(self.size_y, self.size_x).copy()
            frame = ApsFrame(
                pixels=pixels,
                position_x=self.position_x,
                position_y=self.position_y,
                t_start_of_frame_us=self.t_sof,
                t_start_exposure_us=self.t_soe,
                t_end_exposure_us=self.t_eoe,
                t_end_of_frame_us=t_us,
            )
        else:
            self.stats.aps_frames_dropped += 1
        self.in_frame = False
        return frame

    # --- the ADC sample store and the queued segments -----------------------------------------------------------
    def store_samples(self, adc_vals: np.ndarray) -> int:
        """Keep one block's ADC values (int32 [k]); returns the store index of its first sample."""
        store_base = self.store_len
        if adc_vals.shape[0]:
            self.store.append(adc_vals)
            self.store_len += adc_vals.shape[0]
        return store_base

    def release_store(self) -> None:
        """After a block: bound the store (write the queue out once it holds :data:`_STORE_FLUSH_SAMPLES`, for
        streams that never end a frame) and empty it when no queued segment refers to it any more."""
        if self.pending and self.store_len > _STORE_FLUSH_SAMPLES:
            self.flush()
        if not self.pending:
            self.store = []
            self.store_len = 0

    def queue(self, store_start: int, count: int) -> None:
        """Queue ``count`` consecutive stored samples from ``store_start`` as a segment of the current column;
        samples in ignore mode or beyond the expected columns/rows are dropped (and counted)."""
        if self.ignore:
            self.stats.aps_samples_dropped += count
            return
        r = self.readout
        cx = self.count_x[r]
        cy = self.count_y[r]
        if cx >= self.expected_x:
            self.stats.aps_samples_dropped += count
            return
        take = min(count, max(self.expected_y - cy, 0))
        self.stats.aps_samples_dropped += count - take
        if take:
            self.pending.append((r, cx, cy, store_start, store_start + take))
            self.count_y[r] = cy + take

    # --- whole columns in bulk ----------------------------------------------------------------------------------
    def column_run_starts(self, words: list, cuts: list, i: int) -> bool:
        """Whether the column start at control word ``i`` begins at least two whole columns (a cheap scalar
        pre-check; ``words``: the block's control words, ``cuts``: its ADC sample count before each)."""
        return (
            not self.ignore
            and i + 3 < len(words)
            and words[i + 1] == _COLUMN_END
            and words[i + 2] == words[i]
            and cuts[i + 1] - cuts[i] == self.expected_y
        )

    def column_run(self, ctrl_words: np.ndarray, cuts: np.ndarray, i: int) -> int:
        """Number of consecutive whole-column (start, end) pairs of the same readout type starting at control i."""
        expected_y = self.expected_y
        pairs = min((ctrl_words.shape[0] - i) // 2, 2 * max(self.expected_x, 1) + 2)
        words = ctrl_words[i : i + 2 * pairs].reshape(pairs, 2)
        starts = cuts[i : i + 2 * pairs : 2]
        ends = cuts[i + 1 : i + 2 * pairs : 2]
        ok = (words[:, 0] == words[0, 0]) & (words[:, 1] == _COLUMN_END) & (ends - starts == expected_y)
        ok[1:] &= starts[1:] == ends[:-1]  # no samples between a column end and the next column start
        return pairs if ok.all() else int(np.argmin(ok))

    def bulk_columns(self, start_word: int, pairs: int, cuts: np.ndarray, i: int, store_base: int) -> int:
        """Apply ``pairs`` whole columns at once (same effect as the per-word path); return the ADC index done."""
        readout = READOUT_RESET if start_word == Special.APS_RESET_COLUMN_START else READOUT_SIGNAL
        self.readout = readout
        first_col = self.count_x[readout]
        accepted = max(0, min(pairs, self.expected_x - first_col))
        if accepted:
            starts = cuts[i : i + 2 * accepted : 2] + store_base
            segments = np.empty((accepted, 5), np.int64)
            segments[:, 0] = readout
            segments[:, 1] = first_col + np.arange(accepted)
            segments[:, 2] = 0
            segments[:, 3] = starts
            segments[:, 4] = starts + self.expected_y
            self.pending.append(segments)
        self.stats.aps_samples_dropped += (pairs - accepted) * self.expected_y
        self.count_x[readout] = first_col + pairs
        self.count_y[readout] = self.expected_y if accepted == pairs else 0
        return int(cuts[i + 2 * pairs - 1])

    # --- writing the queue into the frame buffers ---------------------------------------------------------------
    def flush(self) -> None:
        """Write queued ADC column segments into the reset/pixel buffers, one vectorised write per same-type run."""
        pending = self.pending
        if not pending:
            return
        self.pending = []
        if len(self.store) > 1:
            self.store = [np.concatenate(self.store)]
        adc_vals = self.store[0]
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
        expected_y = self.expected_y
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
        expected_y = self.expected_y
        steps = np.arange(k)
        return bool(
            np.all(group[:, 2] == 0)
            and np.all(group[:, 4] - group[:, 3] == expected_y)
            and np.all(group[:, 1] == group[0, 1] + steps)
            and np.all(group[:, 3] == group[0, 3] + steps * expected_y)
        )

    def _write_column_block(self, group: np.ndarray, adc_vals: np.ndarray) -> None:
        """Fast path: k whole device columns → one rectangular slice of the ROI buffers."""
        k = group.shape[0]
        first_col = int(group[0, 1])
        start = int(group[0, 3])
        device = adc_vals[start : start + k * self.expected_y].reshape(k, self.expected_y)  # [column, sample]
        if self.flip_y:
            device = device[:, ::-1]
        if self.flip_x:
            device = device[::-1, :]
            lo = self.expected_x - first_col - k
        else:
            lo = first_col
        npix = self.size_x * self.size_y
        reset2d = self.reset_buffer[:npix].reshape(self.size_y, self.size_x)
        pixel2d = self.pixel_buffer[:npix].reshape(self.size_y, self.size_x)
        if self.invert_xy:  # device columns are output rows
            region = (slice(lo, lo + k), slice(None))
            values = device
        else:
            region = (slice(None), slice(lo, lo + k))
            values = device.T
        if group[0, 0] == READOUT_RESET:
            reset2d[region] = values
        else:
            pixel2d[region] = self.cds(reset2d[region], values)

    def _write_segments(self, group: np.ndarray, adc_vals: np.ndarray) -> None:
        """General path: arbitrary (partial, repeated) segments, scattered sample by sample (vectorised)."""
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
        if self.flip_x:
            pos_x = self.expected_x - 1 - pos_x
        if self.flip_y:
            pos_y = self.expected_y - 1 - pos_y
        if self.invert_xy:
            pos_x, pos_y = pos_y, pos_x
        index = pos_y * self.size_x + pos_x
        values = adc_vals[sample]
        if group[0, 0] == READOUT_RESET:
            self.reset_buffer[index] = values
        else:
            self.pixel_buffer[index] = self.cds(self.reset_buffer[index], values)

    @staticmethod
    def cds(reset: np.ndarray, signal: np.ndarray) -> np.ndarray:
        """libcaer CDS: clamp(reset - signal, 0, 1023), forced to 1023 if reset < 384 or signal == 0; << 6."""
        cds = reset - signal
        np.maximum(cds, 0, out=cds)
        np.minimum(cds, APS_PIXEL_MAX, out=cds)
        np.putmask(cds, (reset < APS_RESET_MIN) | (signal == 0), APS_PIXEL_MAX)
        np.left_shift(cds, APS_PIXEL_SHIFT, out=cds)
        return cds.astype(np.uint16)
