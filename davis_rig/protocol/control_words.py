"""The decoder's control-word pass: specials, misc8/misc10 words, big wraps and ADC samples, in stream order.

Both decoder kernels hand each block's control words (with the stream time right after each) to
:meth:`ControlPass.run`: specials become :data:`~davis_rig.protocol.decoded.SPECIAL_DTYPE` records and drive the APS
frame and the IMU sample in progress (:class:`~davis_rig.protocol.aps_assembly.ApsAssembler`,
:class:`~davis_rig.protocol.imu_assembly.ImuAssembler`), misc8 words carry IMU and ROI bytes, and the ADC samples
between two control words are queued as one column segment. Runs of whole APS columns (column start, the expected
rows of samples, column end, ...) are recognised with numpy and applied in bulk instead of word by word.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from davis_rig.protocol.aps_assembly import READOUT_RESET, READOUT_SIGNAL, ApsAssembler
from davis_rig.protocol.decoded import IMU6_DTYPE, SPECIAL_DTYPE, DecodedChunk, DecoderStats
from davis_rig.protocol.imu_assembly import ImuAssembler
from davis_rig.protocol.layout import SensorLayout
from davis_rig.protocol.words import (
    CODE_ADC_SAMPLE,
    CODE_MISC10,
    CODE_MISC8,
    CODE_SPECIAL,
    CODE_SHIFT,
    DATA_MASK,
    MISC8_BYTE_MASK,
    MISC8_SUB_SHIFT,
    MISC10_SUB_SHIFT,
    Misc8,
    Special,
    SpecialType,
)

__all__ = ["ControlPass"]

# Plain ints of the APS column sub-codes: the per-control-word loop avoids enum attribute lookups.
_RESET_COLUMN: Final = int(Special.APS_RESET_COLUMN_START)
_SIGNAL_COLUMN: Final = int(Special.APS_SIGNAL_COLUMN_START)
#: ROI values arrive as big-endian byte pairs (misc8 payloads).
_BYTE_BITS: Final = MISC8_BYTE_MASK.bit_length()

_SPECIAL_TYPE_OF_WIRE: Final = {
    Special.EXT_INPUT_FALLING: SpecialType.EXTERNAL_INPUT_FALLING_EDGE,
    Special.EXT_INPUT_RISING: SpecialType.EXTERNAL_INPUT_RISING_EDGE,
    Special.EXT_INPUT_PULSE: SpecialType.EXTERNAL_INPUT_PULSE,
    Special.EXT_GENERATOR_FALLING: SpecialType.EXTERNAL_GENERATOR_FALLING_EDGE,
    Special.EXT_GENERATOR_RISING: SpecialType.EXTERNAL_GENERATOR_RISING_EDGE,
}


class _ControlBlock:
    """State of one block's control-word pass: the ADC samples' cursor and the specials and IMU rows found.

    Args:
        aps: the APS assembler (receives the queued column segments).
        ctrl_words: uint16 [C] the control words in stream order.
        cut_array: int64 [C] number of the block's ADC samples before each control word.
        n_adc: ADC samples in the block.
        store_base: index of the block's first ADC sample in the APS sample store.
    """

    __slots__ = ("aps", "ctrl_words", "cut_array", "cuts", "n_adc", "store_base", "adc_done", "specials", "imu_rows")

    def __init__(self, aps: ApsAssembler, ctrl_words: np.ndarray, cut_array: np.ndarray, n_adc: int,
                 store_base: int):
        self.aps = aps
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
        self.aps.queue(self.store_base + start, k)


class ControlPass:
    """The control-word state machine of one stream: APS frame and IMU sample assembly, specials, loss counters.

    Args:
        layout: the device's geometry and orientation.
        stats: the decoder's counters (``unknown_words``, ``timestamp_resets``, ``big_wraps`` and the APS/IMU drops).
    """

    def __init__(self, layout: SensorLayout, stats: DecoderStats):
        self.stats = stats
        self.aps = ApsAssembler(layout, stats)
        self.imu = ImuAssembler(layout, stats)

    def run(self, w: np.ndarray, codes: np.ndarray, ctrl_pos: np.ndarray, times: np.ndarray,
            chunk: DecodedChunk) -> None:
        """Run the control words of a block in stream order (specials, misc8/misc10, big wraps, ADC segments).

        Args:
            w: uint16 [n] the block's words; codes: ``w >> CODE_SHIFT``.
            ctrl_pos: int64 [C] positions of the control words; times: int64 [C] stream time right after each, µs.
            chunk: receives the specials, IMU samples and frames.
        """
        block = self._start_block(w, codes, ctrl_pos)
        aps = self.aps
        words_list = block.ctrl_words.tolist()
        times_list = times.tolist()
        n_ctrl = len(words_list)
        i = -1
        while i + 1 < n_ctrl:
            i += 1
            word = words_list[i]
            cut = block.cuts[i]
            if (word == _RESET_COLUMN or word == _SIGNAL_COLUMN) and aps.column_run_starts(words_list, block.cuts, i):
                # a run of whole columns (start, expected_y samples, end, start, ...): handled in bulk
                pairs = aps.column_run(block.ctrl_words, block.cut_array, i)
                if pairs >= 2:
                    block.take_samples(cut)
                    block.adc_done = aps.bulk_columns(word, pairs, block.cut_array, i, block.store_base)
                    i += 2 * pairs - 1
                    continue
            code = word >> CODE_SHIFT
            if code == CODE_SPECIAL:
                self._special(block, word & DATA_MASK, times_list[i], cut, chunk)
            elif code == CODE_MISC8:
                self._misc8(block, word & DATA_MASK, cut)
            elif code == CODE_MISC10:
                if (word & DATA_MASK) >> MISC10_SUB_SHIFT:
                    self.stats.unknown_words += 1
                # sub-code 0 = exposure value parts, only used by libcaer's auto-exposure: consumed.
            else:  # big wrap (code 7)
                self._big_wrap(block, times_list[i], cut)
        self._finish_block(block, chunk)

    def _start_block(self, w: np.ndarray, codes: np.ndarray, ctrl_pos: np.ndarray) -> _ControlBlock:
        """Start a block's control pass: its ADC samples go to the APS sample store, cut at each control word."""
        adc_pos = np.flatnonzero(codes == CODE_ADC_SAMPLE)
        if adc_pos.shape[0]:
            adc_vals = (w[adc_pos] & DATA_MASK).astype(np.int32)
            cut_array = np.searchsorted(adc_pos, ctrl_pos)
        else:
            adc_vals = np.empty(0, np.int32)
            cut_array = np.zeros(ctrl_pos.shape[0], np.int64)
        store_base = self.aps.store_samples(adc_vals)  # block ADC index i is store index store_base + i
        return _ControlBlock(self.aps, w[ctrl_pos], cut_array, adc_vals.shape[0], store_base)

    def _finish_block(self, block: _ControlBlock, chunk: DecodedChunk) -> None:
        """Queue the block's trailing ADC samples, bound the sample store, and attach specials and IMU rows."""
        block.take_samples(block.n_adc)
        self.aps.release_store()
        if block.specials:
            chunk.specials = np.array(block.specials, dtype=SPECIAL_DTYPE)
        if block.imu_rows:
            chunk.imu = np.array(block.imu_rows, dtype=IMU6_DTYPE)

    def _special(self, block: _ControlBlock, sub: int, t: int, cut: int, chunk: DecodedChunk) -> None:
        """One special word (code 0, PROTOCOL.md §8.1) at stream time ``t`` µs."""
        aps = self.aps
        if sub == Special.TIMESTAMP_RESET:
            block.take_samples(cut)
            aps.flush()
            self.stats.timestamp_resets += 1
            self._interrupt()
            block.specials.append((t, SpecialType.TIMESTAMP_RESET))
        elif sub in _SPECIAL_TYPE_OF_WIRE:
            block.specials.append((t, _SPECIAL_TYPE_OF_WIRE[sub]))
        elif sub == Special.IMU_START_6:
            self.imu.start()
        elif sub == Special.IMU_END:
            row = self.imu.end(t)
            if row is not None:
                block.imu_rows.append(row)
        elif sub == Special.APS_FRAME_START_GS or sub == Special.APS_FRAME_START_RS:
            block.take_samples(cut)
            aps.flush()
            aps.start_frame(t)
            block.specials.append((t, SpecialType.APS_FRAME_START))
        elif Special.APS_FRAME_END <= sub <= Special.APS_EXPOSURE_END:
            if not aps.ignore:
                self._aps_readout(block, sub, t, cut, chunk)
        else:
            self.stats.unknown_words += 1

    def _aps_readout(self, block: _ControlBlock, sub: int, t: int, cut: int, chunk: DecodedChunk) -> None:
        """APS frame end, column start/end and exposure start/end specials of a frame being read."""
        aps = self.aps
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
            aps.start_column(READOUT_RESET)
        elif sub == Special.APS_SIGNAL_COLUMN_START:
            aps.start_column(READOUT_SIGNAL)
        elif sub == Special.APS_COLUMN_END:
            aps.end_column()
        else:  # frame end
            aps.flush()
            block.specials.append((t, SpecialType.APS_FRAME_END))
            frame = aps.end_frame(t)
            if frame is not None:
                chunk.frames.append(frame)

    def _misc8(self, block: _ControlBlock, data: int, cut: int) -> None:
        """One misc 8-bit word (code 5): IMU data/scale byte or APS ROI byte."""
        aps = self.aps
        imu = self.imu
        misc = data >> MISC8_SUB_SHIFT
        byte = data & MISC8_BYTE_MASK
        if misc == Misc8.IMU_DATA:
            if not imu.ignore:
                imu.data(byte)
        elif misc == Misc8.APS_ROI_HIGH:
            aps.roi_high = byte
        elif misc == Misc8.APS_ROI_LOW:
            slot = aps.roi_counter & 3
            aps.roi_values[slot] = (aps.roi_high << _BYTE_BITS) | byte
            aps.roi_counter += 1
            if slot == 3:
                block.take_samples(cut)
                aps.flush()
                aps.set_roi()
        elif misc == Misc8.IMU_SCALE:
            if not imu.ignore:
                imu.scale(byte)
        else:
            self.stats.unknown_words += 1

    def _big_wrap(self, block: _ControlBlock, t: int, cut: int) -> None:
        """A wrap that overflowed the 31-bit timestamp: interrupt APS/IMU and emit TIMESTAMP_WRAP at ``t``."""
        block.take_samples(cut)
        self.aps.flush()
        self.stats.big_wraps += 1
        self._interrupt()
        block.specials.append((t, SpecialType.TIMESTAMP_WRAP))

    def _interrupt(self) -> None:
        """Timestamp reset or big wrap: drop the frame / IMU sample in progress and ignore until the next start."""
        self.aps.interrupt()
        self.imu.interrupt()
