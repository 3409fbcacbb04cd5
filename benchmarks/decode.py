"""Throughput of the DAVIS346 stream decoder (both kernels) against libcaer's C translator, and of the encoder.

Run: ``python benchmarks/decode.py [--repeats 7] [--seconds 2.0] [--libcaer-src DIR]``

Streams:

* **DVS**: word mix of a busy DVS stream — per timestamp word 1.2 X words on average (1 + Bernoulli(0.2)), a Y word
  before them with probability 0.6 (so one Y is shared by ~2 X), 1 µs per timestamp word, wrap words every 32768 µs.
* **APS-heavy**: full 346×260 global-shutter frames at 50 fps (encoded by :class:`StreamEncoder`) plus 1 M DVS
  events/s.

The DVS stream is decoded in one interleaved run (each repeat runs every contender once, in turn, so that load
drift hits them alike): libcaer's translator (``davisCommonEventTranslator``, built by ``_libcaer.py`` from the
checkout given as ``--libcaer-src``; one call per 8 KiB transfer, the packet containers drained after each, as a
``caerDeviceDataGet`` consumer would), and each decoder kernel (compiled and numpy) fed 8 KiB transfers one by one
(``feed``, libcaer's transfer size, as the camera delivers them), 8 at a time (``feed_many``) and 1 MiB at a time.
Each run is timed as wall-clock (``perf_counter``) and CPU time of the thread (``thread_time``, robust when other
processes share the cores); figures are medians over ``--repeats`` runs after one warm-up run, and the ratios
decoder/libcaer are ratios of medians of the same run. Without ``--libcaer-src`` the ratios use the fixed reference
figure :data:`LIBCAER_REFERENCE_MWORDS`. The DAVIS346 peaks at about 12 M events/s, i.e. about 28 M words/s with
this word mix.
"""

from __future__ import annotations

from _common import limit_blas_threads, load_average, metadata_line, time_ms

limit_blas_threads(1)  # before numpy is imported: the decoder figures are single-threaded

import argparse  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Mapping  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _libcaer import LibcaerTranslator, build_translator, libcaer_version  # noqa: E402

from davis_rig.protocol import ApsFrame, SensorLayout, StreamDecoder, StreamEncoder, split_transfers  # noqa: E402
from davis_rig.protocol.decoder import compiled_kernel_available  # noqa: E402
from davis_rig.types import make_events  # noqa: E402

#: libcaer's translator on this DVS stream in 8 KiB transfers, M words/s, when no checkout is given: libcaer 3.3's
#: translator built with -O3, measured wall-clock on a quiet 2-core machine of this type (2026-11-26).
LIBCAER_REFERENCE_MWORDS = 198.0
#: libcaer's USB transfer size (and the decoder's feed size in the comparison), bytes.
TRANSFER_BYTES = 8192

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


def available_kernels() -> list[str]:
    """The decoder kernels to time: compiled (where built) and numpy."""
    return ["compiled", "numpy"] if compiled_kernel_available() else ["numpy"]


def decode_runner(data: bytes, mode: str, kernel: str | None = None) -> Callable[[], None]:
    """One decode of ``data`` with a fresh decoder: ``8KiB`` feeds, ``feed_many`` of 8 × 8 KiB, or ``1MiB`` feeds."""
    transfers = split_transfers(data, TRANSFER_BYTES if mode != "1MiB" else 1 << 20)
    batches = [transfers[i : i + 8] for i in range(0, len(transfers), 8)]

    def run():
        decoder = StreamDecoder(LAYOUT, kernel=kernel)
        if mode == "feed_many":
            for batch in batches:
                decoder.feed_many(batch)
        else:
            for transfer in transfers:
                decoder.feed(transfer)

    return run


def time_cpu_and_wall(fns: Mapping[str, Callable[[], object]], repeats: int) -> dict[str, tuple[float, float]]:
    """Median (CPU s, wall s) of each function over ``repeats`` interleaved runs after one interleaved warm-up run."""
    for fn in fns.values():
        fn()
    samples: dict[str, list[tuple[float, float]]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            cpu, wall = time.thread_time(), time.perf_counter()
            fn()
            samples[name].append((time.thread_time() - cpu, time.perf_counter() - wall))
    return {name: (statistics.median(c for c, _ in runs), statistics.median(w for _, w in runs))
            for name, runs in samples.items()}


def first_use_ms() -> float:
    """Milliseconds to load the compiled kernel's shared library in a fresh interpreter: its first-use cost."""
    from davis_rig.protocol import decoder

    code = ("import importlib.util, sys, time; t = time.perf_counter(); "
            "spec = importlib.util.spec_from_file_location('_decode_kernel', sys.argv[1]); "
            "spec.loader.exec_module(importlib.util.module_from_spec(spec)); print((time.perf_counter() - t) * 1e3)")
    command = [sys.executable, "-c", code, decoder._decode_kernel.__file__]
    return float(subprocess.run(command, capture_output=True, text=True, check=True).stdout)


def per_call_us(kernel: str, transfer: bytes, calls: int = 20_000) -> float:
    """CPU µs per ``feed`` of ``transfer`` (median of 5 batches of ``calls``) on a warm decoder."""
    decoder = StreamDecoder(LAYOUT, kernel=kernel)
    decoder.feed(transfer)
    runs = []
    for _ in range(5):
        start = time.thread_time()
        for _ in range(calls):
            decoder.feed(transfer)
        runs.append((time.thread_time() - start) / calls * 1e6)
    return statistics.median(runs)


def compare_with_libcaer(data: bytes, n_events: int, repeats: int, libcaer_src: Path | None) -> dict[str, float]:
    """The interleaved run of the DVS stream; prints the table and the ratios; returns CPU M words/s per contender."""
    n_words = len(data) // 2
    n_transfers = len(split_transfers(data, TRANSFER_BYTES))
    kernels = available_kernels()
    fns: dict[str, Callable[[], object]] = {}
    with tempfile.TemporaryDirectory(prefix="libcaer_translator_") as build_dir:
        if libcaer_src is not None:
            translator = LibcaerTranslator(build_translator(libcaer_src, Path(build_dir)))
            check = translator.run(data, TRANSFER_BYTES)
            if check.polarity_events != n_events:
                raise RuntimeError(f"libcaer decoded {check.polarity_events} events, the stream has {n_events}")
            fns["libcaer translator, 8 KiB"] = lambda: translator.run(data, TRANSFER_BYTES)
        for kernel in kernels:
            fns[f"{kernel}, 8 KiB feed()"] = decode_runner(data, "8KiB", kernel)
            fns[f"{kernel}, 8 x 8 KiB feed_many()"] = decode_runner(data, "feed_many", kernel)
            fns[f"{kernel}, 1 MiB feed()"] = decode_runner(data, "1MiB", kernel)
        medians = time_cpu_and_wall(fns, repeats)
    rates = {name: n_words / cpu / 1e6 for name, (cpu, _) in medians.items()}
    wall_rates = {name: n_words / wall / 1e6 for name, (_, wall) in medians.items()}
    print(f"  {'contender':34s} {'CPU M words/s':>13s} {'µs / 8 KiB':>10s} {'wall M words/s':>14s}")
    for name, (cpu, _) in medians.items():
        print(f"  {name:34s} {rates[name]:13.1f} {cpu / n_transfers * 1e6:10.1f} {wall_rates[name]:14.1f}")
    if libcaer_src is not None:
        reference, wall_reference = rates["libcaer translator, 8 KiB"], wall_rates["libcaer translator, 8 KiB"]
        source = f"libcaer {libcaer_version(libcaer_src)} translator measured above"
    else:
        reference = wall_reference = LIBCAER_REFERENCE_MWORDS
        source = f"fixed reference {LIBCAER_REFERENCE_MWORDS:g} M words/s (a quiet 2-core measurement; no --libcaer-src given)"
    print(f"  ratio decoder / libcaer ({source}):")
    for kernel in kernels:
        print(f"    {kernel:8s} kernel: 8 KiB feed() {rates[f'{kernel}, 8 KiB feed()'] / reference:5.2f} "
              f"(wall {wall_rates[f'{kernel}, 8 KiB feed()'] / wall_reference:4.2f}), "
              f"feed_many() {rates[f'{kernel}, 8 x 8 KiB feed_many()'] / reference:5.2f} "
              f"(wall {wall_rates[f'{kernel}, 8 x 8 KiB feed_many()'] / wall_reference:4.2f})")
    return rates


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--seconds", type=float, default=2.0, help="device seconds of DVS stream")
    parser.add_argument("--libcaer-src", type=Path, default=None,
                        help="libcaer source checkout: build its DAVIS translator as the reference")
    args = parser.parse_args(argv)
    kernel = "compiled" if compiled_kernel_available() else "numpy (compiled kernel not built)"
    print(metadata_line(("numpy",), threads="1 (numpy ufuncs are single-threaded)",
                        repeats=f"{args.repeats} (+1 warm-up)", decoder_kernel=kernel))

    data, n_events = dvs_stream(args.seconds)
    n_words = len(data) // 2
    print(f"\nDVS stream: {n_words / 1e6:.2f} M words, {n_events / 1e6:.2f} M events "
          f"({n_events / (len(data) // 2):.3f} events/word), {TRANSFER_BYTES} B transfers; interleaved run:")
    rates = compare_with_libcaer(data, n_events, args.repeats, args.libcaer_src)
    default = "compiled" if compiled_kernel_available() else "numpy"
    if compiled_kernel_available():
        print(f"  first use of the compiled kernel: loading its library {first_use_ms():.2f} ms in a fresh "
              "interpreter (a C extension: no JIT compile)")
    one_word = np.array([0x8001], "<u2").tobytes()
    overhead = {k: per_call_us(k, one_word) for k in available_kernels()}
    print("  per-call cost of feed() (one-word transfer, CPU): "
          + ", ".join(f"{k} {v:.2f} µs" for k, v in overhead.items()))
    print(f"  load average after the run: {load_average()}")

    sample = np.frombuffer(data, "<u2")[:200_000]
    sample_list = sample.tolist()
    loop_time = time_ms(lambda: per_word_loop_decode(sample_list), 1, max(1, args.repeats // 3)).median_ms / 1e3
    loop_rate = sample.shape[0] / loop_time / 1e6
    assert len(per_word_loop_decode(sample_list)) == len(StreamDecoder(LAYOUT).feed(sample.tobytes()).events)
    print(f"  {'baseline: per-word Python loop (200k words)':38s} {loop_rate:7.2f} M words/s (wall)")
    print(f"  ratio {default} 1 MiB feeds (CPU) / per-word loop: {rates[f'{default}, 1 MiB feed()'] / loop_rate:.0f}x; "
          f"real-time margin at 12 M events/s (8 KiB feed): {rates[f'{default}, 8 KiB feed()'] / 28.0:.2f}x")

    aps_seconds = min(args.seconds, 1.0)
    events, frames = aps_scene(aps_seconds)
    encoder = time_ms(lambda: StreamEncoder(LAYOUT).encode(events, frames), 1, args.repeats)
    encoder_time = encoder.median_ms / 1e3
    aps_data = StreamEncoder(LAYOUT).encode(events, frames)
    n_aps_words = len(aps_data) // 2
    print(f"\nAPS-heavy stream: {len(frames)} full frames + {len(events) / 1e6:.2f} M events = "
          f"{n_aps_words / 1e6:.2f} M words ({aps_seconds:g} s of device time), {default} kernel, wall-clock")
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
