"""Benchmark: session.h5 I/O — writer throughput, compression choice, and fake camera -> session.h5 in real time.

Run: ``python benchmarks/io.py [--rate 12e6] [--seconds 2] [--repeats 3]``. Prints medians (after one warm-up) and
the metadata needed to compare runs (commit, versions, threads, load average). The end-to-end part drives the real
``Davis346`` driver over the virtual USB backend, paced in device real time at ``--rate`` events/s, into
``record_session`` (decoder + writer + journal), and reports the achieved rate, lag behind real time, dropped
transfers, CPU use (``resource.getrusage``, whole process: the virtual device's serving thread included) and
file size per million events.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from _common import metadata_line

from davis_rig.types import DAVIS346_HW, make_events


def synthetic_events(n: int, rate_hz: float, seed: int = 0) -> np.ndarray:
    """Time-sorted events at ``rate_hz`` with spatially clustered coordinates (a moving person-sized blob)."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.exponential(1e6 / rate_hz, n)).astype(np.int64)
    height, width = DAVIS346_HW
    cx = width / 2 + 80 * np.sin(t / 1e6)
    x = np.clip(rng.normal(cx, 40), 0, width - 1).astype(np.uint16)
    y = np.clip(rng.normal(height / 2, 60, n), 0, height - 1).astype(np.uint16)
    return make_events(t, x, y, rng.integers(0, 2, n))


def metadata() -> str:
    """The shared header line plus the HDF5 library and Blosc thread settings."""
    import h5py

    return metadata_line(("numpy", "h5py", "hdf5plugin"), hdf5=h5py.version.hdf5_version,
                         blosc_threads=os.environ.get("BLOSC_NTHREADS", "default"))


def codec_comparison(events: np.ndarray, repeats: int) -> list[tuple[str, float, float]]:
    """Write the event columns with each candidate compression; return (name, Mev/s, bytes/event) medians."""
    import h5py
    import hdf5plugin

    candidates = {
        "none": {},
        "gzip-1 + shuffle": dict(compression="gzip", compression_opts=1, shuffle=True),
        "lzf + shuffle": dict(compression="lzf", shuffle=True),
        "blosc lz4-5 + shuffle (chosen)": dict(hdf5plugin.Blosc(cname="lz4", clevel=5,
                                                                shuffle=hdf5plugin.Blosc.SHUFFLE)),
        "blosc zstd-1 + shuffle": dict(hdf5plugin.Blosc(cname="zstd", clevel=1, shuffle=hdf5plugin.Blosc.SHUFFLE)),
    }
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, options in candidates.items():
            rates, sizes = [], []
            for repeat in range(repeats + 1):
                path = Path(tmp) / "codec.h5"
                t0 = time.perf_counter()
                with h5py.File(path, "w") as f:
                    for column in ("t", "x", "y", "p"):
                        f.create_dataset(column, data=events[column], chunks=(1 << 17,), **options)
                elapsed = time.perf_counter() - t0
                if repeat:  # the first run is the warm-up
                    rates.append(len(events) / elapsed / 1e6)
                    sizes.append(path.stat().st_size / len(events))
            results.append((name, statistics.median(rates), statistics.median(sizes)))
    return results


def writer_throughput(events: np.ndarray, repeats: int, chunk_events: int = 2048) -> tuple[float, float, float]:
    """SessionWriter.append of chunk_events-sized chunks (like 8 KiB USB transfers).

    Returns:
        (M ev per wall second, bytes per event, M ev per CPU second of this process) medians; the CPU figure is
        what the writer costs, independent of how much CPU other processes leave us.
    """
    from davis_rig.session.writer import SessionWriter

    class Chunk:
        def __init__(self, ev):
            self.events, self.frames, self.specials, self.imu = ev, [], None, None

    chunks = [Chunk(events[i : i + chunk_events]) for i in range(0, len(events), chunk_events)]
    rates, sizes, cpu_rates = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(repeats + 1):
            path = Path(tmp) / "w.h5"
            t0, c0 = time.perf_counter(), time.process_time()
            with SessionWriter(path, overwrite=True) as writer:
                for chunk in chunks:
                    writer.append(chunk)
            elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
            if repeat:
                rates.append(len(events) / elapsed / 1e6)
                cpu_rates.append(len(events) / cpu / 1e6)
                sizes.append(path.stat().st_size / len(events))
    return statistics.median(rates), statistics.median(sizes), statistics.median(cpu_rates)


def end_to_end(events: np.ndarray, transfer_bytes: int, queue_transfers: int) -> dict:
    """Paced virtual DAVIS346 -> Davis346 -> record_session; returns the measured figures."""
    from davis_rig.device.camera import Davis346
    from davis_rig.protocol.layout import SensorLayout
    from davis_rig.session.record import record_session
    from davis_rig.usb.sources import EncodedSource
    from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

    span_s = (int(events["t"][-1]) - int(events["t"][0])) / 1e6
    source = EncodedSource(events, layout=SensorLayout.davis346(), paced=True, transfer_bytes=transfer_bytes)
    device = VirtualDavis346(source=source)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "e2e.h5"
        with Davis346.open(backend=VirtualDavis346Backend(device), read_bytes=max(transfer_bytes, 8192),
                           queue_transfers=queue_transfers) as camera:
            stop = threading.Event()
            marks = {}

            def progress(p):
                now = time.perf_counter()
                if p.events and "first" not in marks:
                    marks["first"] = now - p.elapsed_s % 0.05  # data arrived within the last interval
                stats = camera.stats
                if stats.bytes + stats.dropped_bytes >= source.total_bytes and "done" not in marks:
                    marks["done"] = now
                    stop.set()

            usage0 = resource.getrusage(resource.RUSAGE_SELF)
            t0 = time.perf_counter()
            summary = record_session(camera, path, stop_event=stop, progress=progress, progress_interval_s=0.05,
                                     duration_s=span_s * 5 + 10)
            wall = time.perf_counter() - t0
            usage1 = resource.getrusage(resource.RUSAGE_SELF)
            stats = camera.stats
        size = path.stat().st_size
    cpu = (usage1.ru_utime - usage0.ru_utime) + (usage1.ru_stime - usage0.ru_stime)
    # From the first data to everything written and the file closed (the consumer may lag behind the USB reads).
    streaming_s = t0 + wall - marks.get("first", t0)
    return {
        "streaming_s": streaming_s,
        "events_in": len(events),
        "events_recorded": summary.events,
        "span_s": span_s,
        "wall_s": wall,
        "achieved_mev_s": summary.events / streaming_s / 1e6,
        "dropped_transfers": stats.dropped_transfers,
        "transfers": stats.transfers,
        "cpu_s": cpu,
        "cpu_per_wall": cpu / wall,  # whole process incl. the virtual device thread
        "mib_per_mev": size / 2**20 / (max(summary.events, 1) / 1e6),
        "bytes_per_event": size / max(summary.events, 1),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=12e6, help="event rate of the fake camera, ev/s")
    parser.add_argument("--seconds", type=float, default=2.0, help="length of the fake scene, s")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (after one warm-up)")
    parser.add_argument("--skip-e2e", action="store_true")
    args = parser.parse_args(argv)

    print(metadata())
    codec_events = synthetic_events(4_000_000, args.rate, seed=1)
    print(f"\n== compression of the event columns ({len(codec_events) / 1e6:.0f} M events, median of "
          f"{args.repeats}) ==")
    table = codec_comparison(codec_events, args.repeats)
    base = dict((name, rate) for name, rate, _ in table)["blosc lz4-5 + shuffle (chosen)"]
    for name, rate, size in table:
        print(f"{name:34s} {rate:7.1f} M ev/s  {size:5.2f} B/ev  (x{rate / base:4.2f} of chosen)  "
              f"{rate * 1e6 / args.rate:5.1f}x the {args.rate / 1e6:.0f} M ev/s peak")

    rate, size, cpu_rate = writer_throughput(codec_events, args.repeats)
    print(f"\n== SessionWriter.append alone (2048-event chunks) ==\n{rate:7.1f} M ev/s wall, {cpu_rate:.1f} M ev per "
          f"CPU-second ({args.rate / 1e6 / cpu_rate:.2f} cores at the peak rate), {size:5.2f} B/ev")

    if not args.skip_e2e:
        events = synthetic_events(int(args.rate * args.seconds), args.rate, seed=2)
        print(f"\n== end to end: paced virtual DAVIS346 at {args.rate / 1e6:.1f} M ev/s for {args.seconds} s -> "
              "Davis346 -> record_session (decoder + writer + journal) ==")
        for transfer_bytes in (8192, 131072):
            result = end_to_end(events, transfer_bytes, queue_transfers=max(512, int(64 * 2**20 / transfer_bytes)))
            realtime = result["span_s"] / result["streaming_s"]
            print(f"transfers of {transfer_bytes // 1024:3d} KiB: achieved {result['achieved_mev_s']:.2f} M ev/s "
                  f"({realtime:.2f}x real time: first data to file closed {result['streaming_s']:.2f} s for a "
                  f"{result['span_s']:.2f} s scene; {result['wall_s']:.2f} s with camera start), "
                  f"recorded {result['events_recorded']}/{result['events_in']} events, dropped transfers "
                  f"{result['dropped_transfers']}/{result['transfers'] + result['dropped_transfers']}, "
                  f"CPU {result['cpu_s']:.2f} s ({result['cpu_s'] / result['span_s']:.2f} CPU-s per s of data, "
                  f"virtual device included), "
                  f"{result['mib_per_mev']:.2f} MiB per M events ({result['bytes_per_event']:.2f} B/ev)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
