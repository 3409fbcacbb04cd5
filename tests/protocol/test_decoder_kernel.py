"""The compiled decoder kernel against the numpy kernel (the reference and fallback): bit-identical on every stream.

Each stream is decoded by two decoders, one per kernel, fed the same way; events, specials, IMU samples, frames,
every counter and the stream clock must be identical. Streams: random 16-bit words (every code), control-heavy
words, the benchmark's DVS word mix, big-wrap and reset streams, out-of-range and inverted layouts, encoded
APS/IMU scenes, every test vector, and hypothesis-made word lists; fed as 8 KiB transfers, random odd splits,
``feed_many`` batches and single large ``decode_words`` calls across the kernel's block size.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.protocol import ApsFrame, DecodedChunk, SensorLayout, StreamDecoder, StreamEncoder, decoder
from davis_rig.types import EVENT_DTYPE, make_events

pytestmark = pytest.mark.usefixtures("compiled_kernel")


def layout_with(**overrides) -> SensorLayout:
    return SensorLayout.from_mapping({**SensorLayout.davis346().to_dict(), **overrides})


INVERTED = {"dvs_size_columns": 260, "dvs_size_rows": 346, "dvs_orientation_info": 4}


def decode(layout: SensorLayout, kernel: str, pieces, how: str = "feed", **kwargs):
    """Decode ``pieces`` (bytes transfers, or a uint16 array for ``decode_words``) with one kernel."""
    dec = StreamDecoder(layout, kernel=kernel, **kwargs)
    if how == "feed":
        chunk = DecodedChunk.concatenate([dec.feed(p) for p in pieces])
    elif how == "feed_many":
        chunk = DecodedChunk.concatenate([dec.feed_many(pieces[i : i + 8]) for i in range(0, len(pieces), 8)])
    else:
        chunk = dec.decode_words(pieces)
    return chunk, dec


def assert_same_decode(layout: SensorLayout, pieces, how: str = "feed", **kwargs) -> DecodedChunk:
    """Decode with both kernels and assert every output and counter is identical; return the compiled chunk."""
    (got, got_dec), (ref, ref_dec) = (decode(layout, k, pieces, how, **kwargs) for k in ("compiled", "numpy"))
    assert got_dec.kernel == "compiled" and ref_dec.kernel == "numpy"
    assert got.events.dtype == EVENT_DTYPE and got.events.flags.writeable
    assert got.events.tobytes() == ref.events.tobytes()
    assert got.specials.tobytes() == ref.specials.tobytes()
    assert got.imu.tobytes() == ref.imu.tobytes()
    assert len(got.frames) == len(ref.frames)
    assert got.frames == ref.frames  # ApsFrame equality: position, the four times and every pixel
    assert got_dec.stats == ref_dec.stats
    assert got_dec.current_time_us == ref_dec.current_time_us
    return got


def transfers(data: bytes, size: int = 8192) -> list[bytes]:
    return [data[i : i + size] for i in range(0, len(data), size)]


def random_cuts(data: bytes, rng: np.random.Generator, k: int = 12) -> list[bytes]:
    """``data`` cut at ``k`` random byte offsets (odd ones included)."""
    cuts = np.sort(rng.integers(0, len(data) + 1, k)).tolist()
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)])]


def dvs_mix(rng: np.random.Generator, n_ts: int) -> np.ndarray:
    """The benchmark's word mix: per 1 µs timestamp a Y word (p 0.6) and 1-2 X words; wraps every 32768 µs."""
    t_us = np.arange(1, n_ts + 1)
    has_y = rng.random(n_ts) < 0.6
    n_x = 1 + (rng.random(n_ts) < 0.2)
    groups = []
    for t, y, nx in zip(t_us.tolist(), has_y.tolist(), n_x.tolist()):
        groups.append(0x7001 if t % 0x8000 == 0 else 0x8000 | (t & 0x7FFF))
        if y:
            groups.append(0x1000 | int(rng.integers(0, 260)))
        groups += [0x2000 | int(rng.integers(0, 2)) << 12 | int(rng.integers(0, 346)) for _ in range(nx)]
    return np.array(groups, "<u2")


def control_heavy(rng: np.random.Generator, n: int) -> np.ndarray:
    """Specials of every sub-code, ADC samples, misc8/misc10, wraps, DVS words and timestamps, mixed."""
    kind = rng.integers(0, 8, n)
    data = np.select(
        [kind == 0, kind == 4, kind == 5, kind == 7],
        [rng.integers(0, 21, n), rng.integers(0, 1024, n), rng.integers(0, 0x500, n), rng.integers(0, 4096, n)],
        rng.integers(0, 400, n),
    )
    words = (kind << 12) | data
    ts = rng.random(n) < 0.2
    words[ts] = 0x8000 | rng.integers(0, 0x8000, int(ts.sum()))
    return words.astype("<u2")


def big_wraps(rng: np.random.Generator, n: int) -> np.ndarray:
    """DVS words with frequent 4095-unit wraps (several 31-bit overflows per transfer), resets and timestamps."""
    words = np.where(rng.random(n) < 0.5, 0x8000 | rng.integers(0, 0x8000, n),
                     (rng.integers(1, 4, n) << 12) | rng.integers(0, 360, n))
    words[rng.random(n) < 0.03] = 0x7FFF
    words[rng.random(n) < 0.002] = 0x0001
    return words.astype("<u2")


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("invert", [False, True])
def test_random_words_every_code(seed, invert):
    rng = np.random.default_rng(seed)
    data = rng.integers(0, 1 << 16, 30_000).astype("<u2").tobytes()
    layout = layout_with(**INVERTED) if invert else SensorLayout.davis346()
    assert_same_decode(layout, transfers(data))
    assert_same_decode(layout, random_cuts(data, rng), reassemble_odd_bytes=bool(seed % 2))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("aps_orientation", [0, 7])
def test_control_heavy_words(seed, aps_orientation):
    overrides = {"aps_orientation_info": aps_orientation}
    if aps_orientation & 4:
        overrides.update(aps_size_columns=260, aps_size_rows=346)
    layout = layout_with(**overrides)
    rng = np.random.default_rng(100 + seed)
    data = control_heavy(rng, 20_000).tobytes()
    chunk = assert_same_decode(layout, random_cuts(data, rng))
    assert len(chunk.specials) > 100
    assert_same_decode(layout, transfers(data, 4096), how="feed_many")


def test_benchmark_word_mix_in_8k_transfers_and_batches():
    rng = np.random.default_rng(7)
    words = dvs_mix(rng, 70_000)  # two 32768 µs wraps
    chunk = assert_same_decode(SensorLayout.davis346(), transfers(words.tobytes()))
    assert len(chunk.events) > 80_000
    assert_same_decode(SensorLayout.davis346(), transfers(words.tobytes()), how="feed_many")


@pytest.mark.parametrize("seed", range(4))
def test_big_wraps_resets_and_out_of_range(seed):
    rng = np.random.default_rng(200 + seed)
    data = big_wraps(rng, 40_000).tobytes()
    chunk = assert_same_decode(SensorLayout.davis346(), random_cuts(data, rng))
    assert int(chunk.events["t"].max()) >= 2**31  # overflowed past 31 bits
    assert len(chunk.specials) > 10  # big wraps and resets


def test_decode_words_across_the_kernel_block_size(monkeypatch):
    """One decode_words call longer than a kernel block (shrunk here) equals the numpy path's blocks."""
    monkeypatch.setattr(decoder, "_KERNEL_BLOCK_WORDS", 5_000)
    rng = np.random.default_rng(11)
    words = np.concatenate([big_wraps(rng, 20_000), control_heavy(rng, 20_000), dvs_mix(rng, 20_000)])
    assert_same_decode(SensorLayout.davis346(), words, how="words")
    assert_same_decode(SensorLayout.davis346(), words[1::2], how="words")  # non-contiguous input


def test_encoded_frames_imu_free_scene():
    """Full global-shutter frames and DVS events made by the encoder (the bulk column path)."""
    rng = np.random.default_rng(5)
    n = 20_000
    events = make_events(np.sort(rng.integers(0, 60_000, n)), rng.integers(0, 346, n), rng.integers(0, 260, n),
                         rng.integers(0, 2, n))
    frames = [ApsFrame((rng.integers(0, 1024, (260, 346)) << 6).astype(np.uint16), 0, 0, s, s + 500, s + 3000,
                       s + 6000) for s in (1_000, 25_000)]
    data = StreamEncoder(SensorLayout.davis346()).encode(events, frames)
    chunk = assert_same_decode(SensorLayout.davis346(), transfers(data))
    assert len(chunk.frames) == 2
    assert_same_decode(SensorLayout.davis346(), random_cuts(data, rng, 40))


def test_every_vector_in_two_byte_and_whole_transfers(vector, proto):
    layout = proto.layout(vector)
    data = b"".join(proto.transfers(vector))
    assert_same_decode(layout, proto.transfers(vector))
    assert_same_decode(layout, transfers(data, 2))
    assert_same_decode(layout, [data], reassemble_odd_bytes=True)


_WORD_KINDS = st.one_of(
    st.integers(0x8000, 0xFFFF),  # timestamps
    st.integers(0x1000, 0x1FFF),  # Y (some out of range)
    st.integers(0x2000, 0x3FFF),  # X (some out of range)
    st.sampled_from([0x0001, 0x7000, 0x7001, 0x7FFF, 0x0008, 0x000A, 0x000B, 0x000C, 0x000D, 0x0005, 0x0007]),
    st.integers(0, 0xFFFF),
)


@settings(max_examples=150, deadline=None)
@given(words=st.lists(_WORD_KINDS, max_size=400), cut=st.integers(0, 800), invert=st.booleans())
def test_hypothesis_word_lists(words, cut, invert):
    data = np.array(words, "<u2").tobytes()
    layout = layout_with(**INVERTED) if invert else SensorLayout.davis346()
    assert_same_decode(layout, [data[:cut], data[cut:]])


def test_kernel_rejects_bad_buffers():
    state = np.zeros(8, np.int64)
    with pytest.raises(ValueError, match="odd word buffer"):
        decoder._decode_kernel.decode(b"\x00\x80\x01", state)
    with pytest.raises(ValueError, match="state size"):
        decoder._decode_kernel.decode(b"\x00\x80", np.zeros(3, np.int64))
    with pytest.raises(BufferError):
        decoder._decode_kernel.decode(b"\x00\x80", bytes(64))  # state must be writable
