"""Differential test: the vectorised decoder against a word-by-word reference written straight from PROTOCOL.md.

The reference keeps libcaer's own state variables (int32 ``wrapAdd``/``current`` and an ``overflow`` counter,
§9) and last-Y logic (§10), one Python loop iteration per word, so it shares no code or formulation with the
vectorised decoder (which works on a 64-bit cumulative wrap base and forward-filled keys).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.protocol import DecodedChunk, SensorLayout, StreamDecoder

pytestmark = pytest.mark.usefixtures("each_decoder_kernel")

INT32_MAX = 2**31 - 1
EDGE_TYPES = {2: 3, 3: 2, 4: 4, 16: 13, 17: 12}  # wire sub-code -> libcaer special type
TIMING_SPECIALS = {0, 1, 2, 3, 4, 12, 13}  # special types the reference models


def reference_decode(words, rows: int, cols: int, invert_xy: bool):
    """Per-word libcaer-style decoding of DVS events and timing/external specials (per-event overflow)."""
    wrap_add = overflow = current = last_y = 0
    events, specials = [], []
    for word in words:
        if word & 0x8000:
            current = wrap_add + (word & 0x7FFF)
            continue
        code, data = word >> 12, word & 0x0FFF
        if code == 0:
            if data == 1:
                wrap_add = overflow = current = 0
                specials.append((0, 1))  # our convention: time right after the reset
            elif data in EDGE_TYPES:
                specials.append(((overflow << 31) | current, EDGE_TYPES[data]))
        elif code == 1:
            if data < rows:
                last_y = data
        elif code in (2, 3):
            if data < cols:
                x, y = (last_y, data) if invert_xy else (data, last_y)
                events.append(((overflow << 31) | current, x, y, code & 1))
        elif code == 7:
            total = wrap_add + data * 0x8000
            if total <= INT32_MAX:
                wrap_add = current = total
            else:
                wrap_add = current = total - 2**31
                overflow += 1
                specials.append(((overflow << 31) | current, 0))
    return events, specials


def random_stream(rng: np.random.Generator, n: int) -> np.ndarray:
    """Words mixing timestamps, rows/columns (some out of range), big and small wraps, resets and other codes."""
    choice = rng.choice(8, size=n, p=[0.30, 0.15, 0.30, 0.08, 0.02, 0.0005, 0.05, 0.0995])
    words = np.empty(n, np.int64)
    words[choice == 0] = 0x8000 | rng.integers(0, 0x8000, int((choice == 0).sum()))
    words[choice == 1] = 0x1000 | rng.integers(0, 280, int((choice == 1).sum()))
    k = int((choice == 2).sum())
    words[choice == 2] = (rng.integers(2, 4, k) << 12) | rng.integers(0, 360, k)
    words[choice == 3] = 0x7000 | rng.choice([1, 2, 4095], int((choice == 3).sum()))
    words[choice == 4] = rng.choice([2, 3, 4, 16, 17, 0, 6, 18], int((choice == 4).sum()))
    words[choice == 5] = 0x0001
    k = int((choice == 6).sum())
    others = [0x4000, 0x5000, 0x6000, 0x000B, 0x000D, 0x0008, 0x000A, 0x0005]
    words[choice == 6] = rng.choice(others, k) | rng.integers(0, 64, k)
    k = int((choice == 7).sum())
    words[choice == 7] = (rng.integers(1, 4, k) << 12) | rng.integers(0, 64, k)
    return words.astype("<u2")


def decode_in_transfers(layout: SensorLayout, words: np.ndarray, rng: np.random.Generator) -> DecodedChunk:
    data = words.tobytes()
    cuts = np.sort(rng.integers(0, len(data) // 2 + 1, 8)) * 2
    decoder = StreamDecoder(layout)
    return DecodedChunk.concatenate([decoder.feed(data[a:b]) for a, b in zip([0, *cuts], [*cuts, len(data)])])


@pytest.mark.parametrize("invert", [False, True])
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 6000))
def test_vectorised_decoder_matches_word_by_word_reference(invert, seed, n):
    d = SensorLayout.davis346().to_dict()
    if invert:
        d.update(dvs_size_columns=260, dvs_size_rows=346, dvs_orientation_info=4)
    layout = SensorLayout.from_mapping(d)
    rng = np.random.default_rng(seed)
    words = random_stream(rng, n)
    expected_events, expected_specials = reference_decode(
        words.tolist(), layout.dvs_size_rows, layout.dvs_size_columns, invert
    )
    chunk = decode_in_transfers(layout, words, rng)
    assert chunk.events.tolist() == expected_events
    timing = chunk.specials[np.isin(chunk.specials["type"], list(TIMING_SPECIALS))]
    assert timing.tolist() == expected_specials


def test_reference_stream_reaches_several_overflows():
    """The generator above really exercises big wraps: 4095-unit wraps dominate the wrap words."""
    rng = np.random.default_rng(0)
    words = random_stream(rng, 6000)
    _, specials = reference_decode(words.tolist(), 260, 346, False)
    assert sum(1 for t, kind in specials if kind == 0) >= 3
    assert sum(1 for t, kind in specials if kind == 1) >= 1
