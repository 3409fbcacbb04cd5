"""Throughput of the DAVIS346 stream decoder and encoder (single thread).

Run: ``python benchmarks/decode.py [--repeats 7] [--seconds 2.0]``

Streams:

* **DVS**: word mix of a busy DVS stream — per timestamp word 1.2 X words on average (1 + Bernoulli(0.2)), a Y word
  before them with probability 0.6 (so one Y is shared by ~2 X), 1 µs per timestamp word, wrap words every 32768 µs.
* **APS-heavy**: full 346×260 global-shutter frames at 50 fps (encoded by :class:`StreamEncoder`) plus 1 M DVS
  events/s.

Decoding is timed for 8 KiB transfers fed one by one (libcaer's transfer size), the same transfers 8 at a time via
``feed_many``, and 1 MiB feeds. Each figure is the median (IQR, minimum) over ``--repeats`` timed runs after one
warm-up run (``_common.time_ms``). The DAVIS346 peaks at about 12 M events/s, i.e. about 28 M words/s with this
word mix.
"""

from __future__ import annotations

from _common import limit_blas_threads, metadata_line, time_ms

limit_blas_threads(1)  # before numpy is imported: the decoder figures are single-threaded

import argparse  # noqa: E402
import sys  # noqa: E402

import numpy as np  # noqa: E402

from davis_rig.protocol import ApsFrame, SensorLayout, StreamDecoder, StreamEncoder, split_transfers  # noqa: E402
from davis_rig.types import make_events  # noqa: E402

LAYOUT = SensorLayout.davis346()


def dvs_stream(seconds: float, seed: int = 0) -> tuple[bytes, int]:
    """Word stream with the DVS mix above covering ``seconds`` of device time at 1 µs per timestamp word.

    Returns:
        (little-endian bytes, number of X words = events).
    """
    rng = np.random.default_rng(seed)
    n_ts = int(seconds * 1e6)
    t_us = np.arange(1, n_ts + 1, dtype=np.int64)
    n_x = 1 + (rng.random(n_ts) < 0.2)
    has_y = rng.random(n_ts) < 0.6
    per_ts = 1 + has_y + n_x
    wraps_before = (t_us & 0x7FFF) == 0  # the wrap word replaces the timestamp word at multiples of 32768 µs
    ends = np.cumsum(per_ts)
    out = np.empty(int(ends[-1]), np.uint16)
    start = ends - per_ts
    out[start] = np.where(wraps_before, 0x7001, 0x8000 | (t_us & 0x7FFF))
    y_at = start[has_y] + 1
    out[y_at] = 0x1000 | rng.integers(0, 260, y_at.shape[0])
    first_x = start + 1 + has_y
    x_words = lambda k: (0x2000 | (rng.integers(0, 2, k) << 12) | rng.integers(0, 346, k)).astype(np.uint16)  # noqa: E731
    out[first_x] = x_words(n_ts)
    two = np.flatnonzero(n_x == 2)
    out[first_x[two] + 1] = x_words(two.shape[0])
    return out.astype("<u2").tobytes(), int(n_x.sum())


def aps_scene(seconds: float, fps: float = 50.0, dvs_rate_hz: float = 1e6, seed: int = 1):
    """Events and full-array frames for the APS-heavy stream."""
    rng = np.random.default_rng(seed)
    duration_us = int(seconds * 1e6)
    n = int(seconds * dvs_rate_hz)
    t_us = np.sort(rng.integers(0, duration_us, n))
    events = make_events(t_us, rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n))
    period_us = int(1e6 / fps)
    frames = []
    for k in range(int(seconds * fps)):
        sof = k * period_us + 100
        pixels = (rng.integers(0, 1024, (260, 346)) << 6).astype(np.uint16)
        frames.append(ApsFrame(pixels, 0, 0, sof, sof + 2000, sof + 7000, sof + 12000))
    return events, frames


def per_word_loop_decode(words: list[int], rows: int = 260, cols: int = 346) -> list[tuple[int, int, int, int]]:
    """Baseline: libcaer's DVS/timestamp state machine as a plain per-word Python loop (for the speed ratio)."""
    wrap_add = overflow = current = last_y = 0
    events = []
    for word in words:
        if word & 0x8000:
            current = wrap_add + (word & 0x7FFF)
            continue
        code, data = word >> 12, word & 0x0FFF
        if code == 1:
            if data < rows:
                last_y = data
        elif code in (2, 3):
            if data < cols:
                events.append(((overflow << 31) | current, data, last_y, code & 1))
        elif code == 7:
            total = wrap_add + data * 0x8000
            if total < 2**31:
                wrap_add = current = total
            else:
                wrap_add = current = total - 2**31
                overflow += 1
        elif code == 0 and data == 1:
            wrap_add = overflow = current = 0
    return events


def decode_runner(data: bytes, mode: str):
    transfers = split_transfers(data, 8192 if mode != "1MiB" else 1 << 20)
    batches = [transfers[i : i + 8] for i in range(0, len(transfers), 8)]

    def run():
        decoder = StreamDecoder(LAYOUT)
        if mode == "feed_many":
            for batch in batches:
                decoder.feed_many(batch)
        else:
            for transfer in transfers:
                decoder.feed(transfer)

    return run


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--seconds", type=float, default=2.0, help="device seconds of DVS stream")
    args = parser.parse_args(argv)
    print(metadata_line(("numpy",), threads="1 (numpy ufuncs are single-threaded)",
                        repeats=f"{args.repeats} (+1 warm-up)"))

    data, n_events = dvs_stream(args.seconds)
    n_words = len(data) // 2
    print(f"\nDVS stream: {n_words / 1e6:.2f} M words, {n_events / 1e6:.2f} M events "
          f"({n_events / (len(data) // 2):.3f} events/word)")
    results = {}
    for mode in ("8KiB", "feed_many", "1MiB"):
        timing = time_ms(decode_runner(data, mode), 1, args.repeats)
        median = timing.median_ms / 1e3
        results[mode] = n_words / median / 1e6
        label = {"8KiB": "decode, 8 KiB transfers, feed()", "feed_many": "decode, 8 × 8 KiB via feed_many()",
                 "1MiB": "decode, 1 MiB feeds"}[mode]
        print(f"  {label:38s} {results[mode]:7.1f} M words/s  ({n_events / median / 1e6:6.1f} M events/s)  "
              f"{timing}, best {n_words / timing.min_ms / 1e3:.1f} M words/s")
    sample = np.frombuffer(data, "<u2")[:200_000]
    sample_list = sample.tolist()
    loop_time = time_ms(lambda: per_word_loop_decode(sample_list), 1, max(1, args.repeats // 3)).median_ms / 1e3
    loop_rate = sample.shape[0] / loop_time / 1e6
    assert len(per_word_loop_decode(sample_list)) == len(StreamDecoder(LAYOUT).feed(sample.tobytes()).events)
    print(f"  {'baseline: per-word Python loop (200k words)':38s} {loop_rate:7.2f} M words/s")
    print(f"  ratio 1 MiB vectorised / per-word loop: {results['1MiB'] / loop_rate:.0f}x")
    print(f"  ratio feed_many / feed: {results['feed_many'] / results['8KiB']:.2f}, "
          f"1 MiB / feed: {results['1MiB'] / results['8KiB']:.2f}; "
          f"real-time margin at 12 M events/s (8 KiB feed): {results['8KiB'] / 28.0:.2f}x")

    aps_seconds = min(args.seconds, 1.0)
    events, frames = aps_scene(aps_seconds)
    encoder = time_ms(lambda: StreamEncoder(LAYOUT).encode(events, frames), 1, args.repeats)
    encoder_time = encoder.median_ms / 1e3
    aps_data = StreamEncoder(LAYOUT).encode(events, frames)
    n_aps_words = len(aps_data) // 2
    print(f"\nAPS-heavy stream: {len(frames)} full frames + {len(events) / 1e6:.2f} M events = "
          f"{n_aps_words / 1e6:.2f} M words ({aps_seconds:g} s of device time)")
    for mode in ("8KiB", "1MiB"):
        timing = time_ms(decode_runner(aps_data, mode), 1, args.repeats)
        median = timing.median_ms / 1e3
        print(f"  decode, {mode:5s} feeds {n_aps_words / median / 1e6:7.1f} M words/s  "
              f"({len(frames) / median:6.0f} frames/s)  {timing}")
    print(f"  encode (events + frames) {n_aps_words / encoder_time / 1e6:7.1f} M words/s  {encoder}")

    rng = np.random.default_rng(2)
    n = int(12e6 * min(args.seconds, 1.0))
    t_us = np.sort(rng.integers(0, int(1e6 * min(args.seconds, 1.0)), n))
    dvs_events = make_events(t_us, rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n))
    timing = time_ms(lambda: StreamEncoder(LAYOUT).encode(dvs_events), 1, args.repeats)
    median = timing.median_ms / 1e3
    print(f"\nDVS encode: {n / 1e6:.1f} M events (12 M events/s for {min(args.seconds, 1.0):g} s): "
          f"{n / median / 1e6:.1f} M events/s, {timing}, real-time factor {n / median / 12e6:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
