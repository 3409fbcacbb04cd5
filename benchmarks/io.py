"""Benchmark: session.h5 I/O — writer throughput, compression choice, and fake camera -> session.h5 in real time.

Run: ``python benchmarks/io.py [--rate 12e6] [--seconds 2] [--repeats 3] [--queue-mib 8] [--reader both]
[--skip-e2e | --e2e-only]``.
Prints medians (after one warm-up) and the metadata needed to compare runs (commit, versions, threads, load
average). The end-to-end part drives the real ``Davis346`` driver over the virtual USB backend, paced in device
real time at ``--rate`` events/s, through the driver's ring of asynchronous transfers and/or its synchronous
reads (``--reader``), into ``record_session`` (decoder + writer + journal), with a reader queue of
``--queue-mib`` (far less than the scene, so falling behind shows as dropped transfers). It reports, apart: the
streaming phase (first to last chunk written) as a real-time factor (data s / wall s) with the lag behind real
time at its end and CPU-s per data-s (``resource.getrusage``, whole process: the virtual device's serving thread
included); start-up; file close (camera stop, writer close, journal removal); dropped transfers; bytes per event.
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
from davis_rig.usb.async_bulk import DEFAULT_TRANSFER_BYTES, DEFAULT_TRANSFERS


#: Default nominal reader-queue capacity of the end-to-end run, MiB: ~0.17 s of the synthetic scene's ~50 MB/s stream
#: at 12 M ev/s (4.2 B/ev), far less than any scene, so a consumer that falls behind drops transfers instead of
#: hiding in the queue. Stricter than the driver's default (``DEFAULT_QUEUE_TRANSFERS`` = 512 reads of up to
#: ``DEFAULT_READ_BYTES`` = 128 KiB: 64 MiB nominal, ~0.5 s at the peak, since a read ends at the FX3's 1 ms
#: early-packet delay with ~50 kB).
DEFAULT_QUEUE_MIB = 8.0


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


def queue_depth(queue_bytes: int, read_bytes: int) -> int:
    """Reader queue depth, in reads, whose nominal capacity (full reads) is ``queue_bytes`` (at least one read)."""
    return max(1, queue_bytes // read_bytes)


def streaming_figures(first: tuple[float, int], last: tuple[float, int]) -> tuple[float, float, float]:
    """Real-time figures of the streaming phase from two (wall s, data t µs) marks of written data.

    Args:
        first: wall-clock time (s) the first chunk with events was written, and its last event's t (µs).
        last: the same for the last chunk written before the stop.

    Returns:
        (data s, wall s, lag s): device time covered between the marks, wall time between them, and how far the
        writer ended behind the device clock (wall - data; <= 0 means it kept up). Real-time factor = data / wall.
    """
    data_s = (last[1] - first[1]) / 1e6
    wall_s = last[0] - first[0]
    return data_s, wall_s, wall_s - data_s


def _cpu_s() -> float:
    """User + system CPU time of this process so far, s (every thread)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class _TimedCamera:
    """The camera as ``record_session`` sees it, plus marks of when data was written and a stop after the last byte.

    A chunk counts as written when ``record_session`` asks for the next one (it appends each chunk before reading
    again). Once the reader has received every byte the source holds and the queue is empty, ``stop`` is set:
    what follows (camera stop, file close) is timed apart from the streaming.
    """

    def __init__(self, camera, total_bytes: int, stop: threading.Event):
        self._camera = camera
        self._total_bytes = total_bytes
        self._stop = stop
        self._handed: int | None = None  # last event t (µs) of the chunk handed out and not yet marked
        self.first: tuple[float, int] | None = None  # (wall s, t µs) of the first written chunk with events
        self.last: tuple[float, int] | None = None  # the same for the latest one
        self.cpu_first_s = 0.0  # process CPU s at the first mark
        self.stopped: tuple[float, float] | None = None  # (wall s, process CPU s) when stop was set

    def __getattr__(self, name):
        return getattr(self._camera, name)

    def read(self, timeout_s):
        """``Davis346.read``, marking the previously handed-out chunk as written."""
        now = time.perf_counter()
        if self._handed is not None:
            self.last = (now, self._handed)
            if self.first is None:
                self.first, self.cpu_first_s = self.last, _cpu_s()
            self._handed = None
        chunk = self._camera.read(timeout_s)
        if chunk is not None and len(chunk.events):
            self._handed = int(chunk.events["t"][-1])
        elif chunk is None and self.stopped is None:
            stats = self._camera.stats
            if stats.bytes + stats.dropped_bytes >= self._total_bytes:
                self.stopped = (time.perf_counter(), _cpu_s())
                self._stop.set()
        return chunk


def end_to_end(events: np.ndarray, transfer_bytes: int, queue_bytes: int, usb_transfers: int) -> dict:
    """Paced virtual DAVIS346 -> Davis346 -> record_session; returns the measured figures.

    Args:
        events: the scene, EVENT_DTYPE [N], time-sorted (t µs).
        transfer_bytes: largest device transfer, bytes. Synchronous reads ask for ``max(transfer_bytes, 8192)``
            at a time; the ring's transfers have the driver's default size.
        queue_bytes: nominal capacity of the driver's reader queue, bytes (converted to whole reads).
        usb_transfers: asynchronous transfers in flight (the driver's ring); 0 = a thread of synchronous reads.

    Returns:
        Figures (names carry units); the streaming phase runs from the first to the last chunk written, start-up
        is before it, file close after the stop (camera stop, writer close, journal removed).
    """
    from davis_rig.device.camera import Davis346
    from davis_rig.protocol.layout import SensorLayout
    from davis_rig.session.record import record_session
    from davis_rig.usb.sources import EncodedSource
    from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

    span_s = (int(events["t"][-1]) - int(events["t"][0])) / 1e6
    source = EncodedSource(events, layout=SensorLayout.davis346(), paced=True, transfer_bytes=transfer_bytes)
    read_bytes = DEFAULT_TRANSFER_BYTES if usb_transfers else max(transfer_bytes, 8192)
    queue_transfers = queue_depth(queue_bytes, read_bytes)
    device = VirtualDavis346(source=source)
    stop = threading.Event()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "e2e.h5"
        with Davis346.open(backend=VirtualDavis346Backend(device), read_bytes=read_bytes,
                           queue_transfers=queue_transfers, usb_transfers=usb_transfers) as camera:
            timed = _TimedCamera(camera, source.total_bytes, stop)
            cpu0, t0 = _cpu_s(), time.perf_counter()
            summary = record_session(timed, path, stop_event=stop, duration_s=span_s * 5 + 10)
            t_end, cpu_end = time.perf_counter(), _cpu_s()
            stats = camera.stats
        size = path.stat().st_size
    if timed.first is None or timed.last is None or timed.stopped is None:
        raise RuntimeError(f"no complete stream recorded ({summary.events} events, stopped by {summary.stopped_by})")
    data_s, stream_wall_s, lag_s = streaming_figures(timed.first, timed.last)
    return {
        "reader": f"ring of {usb_transfers} transfers" if usb_transfers else "synchronous reads",
        "events_in": len(events),
        "events_recorded": summary.events,
        "span_s": span_s,
        "queue_transfers": queue_transfers,
        "read_bytes": read_bytes,
        "mean_read_bytes": stats.bytes / max(stats.transfers, 1),
        "data_bytes_per_s": source.total_bytes / span_s,
        "startup_s": timed.first[0] - t0,
        "stream_data_s": data_s,
        "stream_wall_s": stream_wall_s,
        "realtime_factor": data_s / stream_wall_s,
        "lag_s": lag_s,
        "close_s": t_end - timed.stopped[0],
        "wall_s": t_end - t0,
        "dropped_transfers": stats.dropped_transfers,
        "transfers": stats.transfers,
        "stream_cpu_s": timed.stopped[1] - timed.cpu_first_s,
        "cpu_s": cpu_end - cpu0,
        "bytes_per_event": size / max(summary.events, 1),
    }


def print_end_to_end(result: dict, transfer_bytes: int) -> None:
    """Print one end-to-end result as a few labelled lines."""
    queue_s = result["queue_transfers"] * min(result["read_bytes"], result["mean_read_bytes"]) / \
        result["data_bytes_per_s"]
    print(f"device transfers of {transfer_bytes // 1024:3d} KiB, {result['reader']}: queue {result['queue_transfers']} x <= "
          f"{result['read_bytes'] // 1024} KiB ({result['queue_transfers'] * result['read_bytes'] / 2**20:.1f} MiB "
          f"nominal, ~{queue_s:.3f} s of this stream at its mean read of {result['mean_read_bytes'] / 1024:.1f} KiB)")
    print(f"  streaming: real-time factor {result['realtime_factor']:.3f} ({result['stream_data_s']:.3f} s of data "
          f"in {result['stream_wall_s']:.3f} s wall), lag behind real time at the end {result['lag_s'] * 1e3:.1f} ms, "
          f"CPU {result['stream_cpu_s'] / result['stream_data_s']:.2f} CPU-s per data-s (whole process, virtual "
          "device included)")
    print(f"  dropped transfers {result['dropped_transfers']}/{result['transfers'] + result['dropped_transfers']}, "
          f"recorded {result['events_recorded']}/{result['events_in']} events")
    print(f"  start-up {result['startup_s']:.3f} s, file close {result['close_s']:.3f} s, total {result['wall_s']:.2f} "
          f"s wall and {result['cpu_s']:.2f} CPU-s for a {result['span_s']:.2f} s scene "
          f"({result['cpu_s'] / result['span_s']:.2f} CPU-s per data-s), {result['bytes_per_event']:.2f} B/ev")


def compression_and_writer(rate_hz: float, repeats: int) -> None:
    """Print the codec comparison and the SessionWriter throughput on 4 M events at ``rate_hz`` (ev/s)."""
    codec_events = synthetic_events(4_000_000, rate_hz, seed=1)
    print(f"\n== compression of the event columns ({len(codec_events) / 1e6:.0f} M events, median of "
          f"{repeats}) ==")
    table = codec_comparison(codec_events, repeats)
    base = dict((name, rate) for name, rate, _ in table)["blosc lz4-5 + shuffle (chosen)"]
    for name, rate, size in table:
        print(f"{name:34s} {rate:7.1f} M ev/s  {size:5.2f} B/ev  (x{rate / base:4.2f} of chosen)  "
              f"{rate * 1e6 / rate_hz:5.1f}x the {rate_hz / 1e6:.0f} M ev/s peak")

    rate, size, cpu_rate = writer_throughput(codec_events, repeats)
    print(f"\n== SessionWriter.append alone (2048-event chunks) ==\n{rate:7.1f} M ev/s wall, {cpu_rate:.1f} M ev per "
          f"CPU-second ({rate_hz / 1e6 / cpu_rate:.2f} cores at the peak rate), {size:5.2f} B/ev")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=12e6, help="event rate of the fake camera, ev/s")
    parser.add_argument("--seconds", type=float, default=2.0, help="length of the fake scene, s")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (after one warm-up)")
    parser.add_argument("--queue-mib", type=float, default=DEFAULT_QUEUE_MIB,
                        help="end to end: nominal capacity of the driver's reader queue, MiB (whole reads; default "
                             f"{DEFAULT_QUEUE_MIB:g} ~ 0.17 s at the 12 M ev/s peak)")
    parts = parser.add_mutually_exclusive_group()
    parts.add_argument("--skip-e2e", action="store_true", help="leave out the end-to-end capture run")
    parts.add_argument("--e2e-only", action="store_true", help="run only the end-to-end capture run")
    parser.add_argument("--reader", choices=("ring", "sync", "both"), default="both",
                        help="end to end: the driver's ring of asynchronous transfers, synchronous reads, or both")
    args = parser.parse_args(argv)
    readers = {"ring": [DEFAULT_TRANSFERS], "sync": [0], "both": [DEFAULT_TRANSFERS, 0]}[args.reader]

    print(metadata())
    if not args.e2e_only:
        compression_and_writer(args.rate, args.repeats)
    if not args.skip_e2e:
        events = synthetic_events(int(args.rate * args.seconds), args.rate, seed=2)
        print(f"\n== end to end: paced virtual DAVIS346 at {args.rate / 1e6:.1f} M ev/s for {args.seconds} s -> "
              "Davis346 -> record_session (decoder + writer + journal), one run per transfer size ==")
        for transfer_bytes in (8192, 131072):
            for usb_transfers in readers:
                result = end_to_end(events, transfer_bytes, int(args.queue_mib * 2**20), usb_transfers)
                print_end_to_end(result, transfer_bytes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
