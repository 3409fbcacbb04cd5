"""Benchmark: USB capture path on the virtual DAVIS346 (pyusb → reader thread → decoder), vs the 12 Mev/s peak.

Run: ``python benchmarks/usb_pipeline.py [--events 1000000] [--repeats 5]``

Measures, with warm-up and the median over repeats:

1. ``transport``: raw bulk reads through pyusb + the virtual backend (``UsbTransport.read_data`` in a loop),
   i.e. the synchronous pyusb path with 128 KiB reads, in MB/s and reads/s;
2. ``camera``: the full :class:`~davis_rig.device.camera.Davis346` path (reader thread, queue, raw listener,
   :class:`~davis_rig.protocol.decoder.StreamDecoder`) draining the same transfers, in Mev/s;

and prints them as ratios of the DAVIS346 peak (12 Mev/s). The scene is 8192-byte transfers of random events at
~10 Mev/s device time (1 ms slices, like the camera's early-packet delay); like a real bulk read, one read runs
over transfers made of whole 1024-byte packets and stops after a short packet.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import metadata_line, summarize_ms

from davis_rig.device.camera import Davis346
from davis_rig.protocol.layout import SensorLayout
from davis_rig.types import make_events
from davis_rig.usb.sources import EncodedSource, TransferListSource
from davis_rig.usb.transport import UsbTransport
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

PEAK_EVENTS_PER_S = 12e6


def make_transfers(n_events: int, rate_ev_per_s: float = 10e6, seed: int = 0) -> list[bytes]:
    """Encode a random scene into 8 KiB transfers (1 ms slices)."""
    rng = np.random.default_rng(seed)
    t_end_us = int(n_events / rate_ev_per_s * 1e6)
    events = make_events(
        np.sort(rng.integers(0, t_end_us, n_events)),
        rng.integers(0, 346, n_events),
        rng.integers(0, 260, n_events),
        rng.integers(0, 2, n_events),
    )
    source = EncodedSource(events, layout=SensorLayout.davis346(), transfer_bytes=8192)
    out = []
    while source.peek_release_us() is not None:
        out.append(source.pop())
    return out


def run_transport(transfers: list[bytes]) -> tuple[float, int]:
    """Seconds to read every byte with ``UsbTransport.read_data`` (128 KiB reads), and the number of reads."""
    dev = VirtualDavis346(source=TransferListSource(transfers))
    with UsbTransport.open(backend=VirtualDavis346Backend(dev)) as t:
        for module, param in ((9, 0), (0, 0), (1, 3)):
            t.config_write(module, param, 1)
        total = sum(len(x) for x in transfers)
        t0 = time.perf_counter()
        got, reads = 0, 0
        while got < total:
            data = t.read_data(16 * 8192, 100)
            if data:
                got += len(data)
                reads += 1
        return time.perf_counter() - t0, reads


def run_camera(transfers: list[bytes]) -> tuple[float, int]:
    """Seconds for Davis346 to deliver every transfer decoded, and the number of events."""
    dev = VirtualDavis346(source=TransferListSource(transfers))
    raw_bytes = [0]
    with Davis346.open(backend=VirtualDavis346Backend(dev), sleep=lambda s: None, read_timeout_ms=20) as cam:
        cam.add_raw_listener(lambda b: raw_bytes.__setitem__(0, raw_bytes[0] + len(b)))
        n_events = 0
        t0 = time.perf_counter()
        cam.start()  # ~40 control requests; the reader starts streaming inside
        t_last = t0
        for chunk in cam.chunks(timeout_s=0.1):
            n_events += len(chunk.events)
            t_last = time.perf_counter()  # the final idle timeout is not work
        elapsed = t_last - t0
        cam.stop()
        assert cam.stats.dropped_transfers == 0
    return elapsed, n_events


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    transfers = make_transfers(args.events)
    total_bytes = sum(len(t) for t in transfers)
    print(metadata_line(packages=("numpy", "pyusb"), threads="main + 1 reader (+ FX3 debug poller)"))
    print(f"scene: {args.events} events, {len(transfers)} transfers, {total_bytes / 1e6:.2f} MB; repeats {args.repeats} + 1 warm-up")

    run_transport(transfers)  # warm-up
    runs = [run_transport(transfers) for _ in range(args.repeats)]
    t_transport = [r[0] for r in runs]
    n_reads = runs[0][1]
    run_camera(transfers)
    cam = [run_camera(transfers) for _ in range(args.repeats)]
    t_camera = [c[0] for c in cam]
    n_events = cam[0][1]

    transport = summarize_ms([t * 1e3 for t in t_transport])
    camera = summarize_ms([t * 1e3 for t in t_camera])
    med_t, med_c = transport.median_ms / 1e3, camera.median_ms / 1e3
    mbps = total_bytes / med_t / 1e6
    reads = n_reads / med_t
    mev_transport = n_events / med_t / 1e6
    mev_camera = n_events / med_c / 1e6
    print(f"transport  median {med_t * 1e3:8.1f} ms  {mbps:8.1f} MB/s  {reads:9.0f} reads/s  "
          f"{mev_transport:6.2f} Mev/s  = {mev_transport * 1e6 / PEAK_EVENTS_PER_S:5.2f} x peak")
    print(f"camera     median {med_c * 1e3:8.1f} ms  {total_bytes / med_c / 1e6:8.1f} MB/s  "
          f"{mev_camera:6.2f} Mev/s  = {mev_camera * 1e6 / PEAK_EVENTS_PER_S:5.2f} x peak")
    print(f"ratio camera/transport time: {med_c / med_t:.2f}")
    print(f"transport min {transport.min_ms:.1f} ms, IQR {transport.iqr_ms:.1f} ms | "
          f"camera min {camera.min_ms:.1f} ms, IQR {camera.iqr_ms:.1f} ms")


if __name__ == "__main__":
    main()
