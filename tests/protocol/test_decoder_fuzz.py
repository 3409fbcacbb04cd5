"""Fuzz the decoder with random and control-heavy garbage: no exception, counters grow, outputs stay well-formed."""

from __future__ import annotations

import gc
import tracemalloc

import numpy as np
import pytest

from davis_rig.protocol import SensorLayout, StreamDecoder

pytestmark = pytest.mark.usefixtures("each_decoder_kernel")


def control_heavy_words(rng: np.random.Generator, n: int) -> np.ndarray:
    """Words biased towards specials (sub-codes 0-20), ADC samples, misc8/misc10, wraps and small timestamps."""
    kind = rng.integers(0, 8, n)
    data = np.select(
        [kind == 0, kind == 1, kind == 5, kind == 7],
        [rng.integers(0, 21, n), rng.integers(0, 300, n), rng.integers(0, 0x500, n), rng.integers(0, 4096, n)],
        rng.integers(0, 4096, n),
    )
    words = (kind << 12) | data
    ts = rng.random(n) < 0.1
    words[ts] = 0x8000 | rng.integers(0, 0x8000, int(ts.sum()))
    return words.astype("<u2")


def check_chunk(chunk, layout: SensorLayout) -> None:
    events = chunk.events
    if len(events):
        assert int(events["x"].max()) < layout.dvs_width
        assert int(events["y"].max()) < layout.dvs_height
        assert int(events["p"].max()) <= 1
        assert int(events["t"].min()) >= 0
    for frame in chunk.frames:
        assert 1 <= frame.width and frame.position_x + frame.width <= layout.aps_width
        assert 1 <= frame.height and frame.position_y + frame.height <= layout.aps_height
        assert not np.any(frame.pixels & 0x3F)
    assert np.all(np.isfinite(chunk.imu[["accel_x_g", "gyro_z_dps", "temperature_c"]].tolist()))


@pytest.mark.parametrize("aps_orientation", [0, 7])
def test_random_garbage_many_seeds(aps_orientation):
    d = SensorLayout.davis346().to_dict()
    if aps_orientation & 4:
        d.update(aps_size_columns=260, aps_size_rows=346)
    layout = SensorLayout.from_mapping({**d, "aps_orientation_info": aps_orientation})
    total_words = 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        decoder = StreamDecoder(layout, reassemble_odd_bytes=bool(seed % 2))
        fed = 0
        for _ in range(6):
            if rng.random() < 0.5:
                data = rng.integers(0, 256, int(rng.integers(0, 3000)), dtype=np.uint8).tobytes()
            else:
                data = control_heavy_words(rng, int(rng.integers(0, 1500))).tobytes()
                if rng.random() < 0.3:
                    data = data[:-1]
            fed += len(data)
            check_chunk(decoder.feed(data), layout)
        stats = decoder.stats
        assert stats.words == (fed - stats.odd_bytes_dropped) // 2
        total_words += stats.words
        if stats.words > 1000:
            assert stats.unknown_words > 0
            assert stats.dvs_out_of_range > 0
    assert total_words > 100_000


def test_long_garbage_stream_keeps_memory_bounded():
    layout = SensorLayout.davis346()
    decoder = StreamDecoder(layout)
    rng = np.random.default_rng(99)
    transfers = [control_heavy_words(rng, 4096).tobytes() for _ in range(8)]
    for data in transfers:  # warm-up: internal index buffers reach their final size
        decoder.feed(data)
    gc.collect()
    tracemalloc.start()
    try:
        baseline = tracemalloc.get_traced_memory()[0]
        for _ in range(4):
            for data in transfers:
                decoder.feed(data)
        gc.collect()
        retained = tracemalloc.get_traced_memory()[0] - baseline
    finally:
        tracemalloc.stop()
    assert retained < 1_000_000  # bytes: no growth with the amount of data fed
    assert decoder.stats.words == 5 * 8 * 4096


def test_frame_that_never_ends_keeps_memory_bounded():
    """ADC samples queued for a frame without frame end are written out before they pile up."""
    layout = SensorLayout.davis346()
    decoder = StreamDecoder(layout)
    column = np.array([0x000B, *([0x4000 | 900] * 260), 0x000D], dtype="<u2")
    start = np.array([0x0008, 0x5100, 0x5200, 0x5100, 0x5200, 0x5101, 0x5259, 0x5101, 0x5203], dtype="<u2")
    decoder.feed(start.tobytes())
    transfer = np.tile(column, 31).tobytes()  # ~16 KiB of reset columns (beyond 346 columns they are dropped)
    gc.collect()
    tracemalloc.start()
    try:
        baseline = tracemalloc.get_traced_memory()[0]
        for _ in range(400):  # 3.3 M words
            decoder.feed(transfer)
        gc.collect()
        retained = tracemalloc.get_traced_memory()[0] - baseline
    finally:
        tracemalloc.stop()
    assert retained < 4_000_000  # bytes; the whole stream's samples would be > 13 MB
    assert decoder.stats.aps_samples_dropped > 3_000_000
