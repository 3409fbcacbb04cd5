"""Benchmark: the live view of ``davis-record --view`` beside a recording at the DAVIS346 peak — does it slow it?

Run: ``python benchmarks/view_live.py [--rate 12e6] [--seconds 3] [--threads N] [--fps 25] [--aps-fps 25]
[--queue-mib 8] [--int8] [--runs N]`` (``--int8``: the bundled detector's int8 graph, as ``davis-record --view
--int8``; ``--runs``: the pair of recordings N times, then how many runs met each goal)

The real ``Davis346`` driver reads the virtual DAVIS346, paced in device real time at ``--rate`` events/s (a
person-sized blob walking across the sensor, 20 % uniform noise, full APS frames at ``--aps-fps``), through its
ring of asynchronous transfers and a reader queue of ``--queue-mib`` (far less than the scene, so falling behind
shows as dropped transfers), into ``record_session`` (decoder + writer + journal) — twice, from the same encoded
transfers: without the view, then with what ``davis-record --view`` adds: the tap and its feeder thread in the
recording process, and the view process (:class:`LiveViewProcess`: frames, the bundled RVT-T on ``--threads``
onnxruntime threads, the web server), with one HTTP client fetching every new frame as the page does.

Prints per run: dropped transfers, events recorded, the streaming phase's real-time factor (data s / wall s, first
to last chunk written) and the recording process's CPU-s per data-s. With the view: the view process's CPU, frames
the client received per second during the streaming (display fps), detector latency (the recording read the chunk
that completed a window → its boxes ready; median / p95 / max), how far the boxes shown lag the events shown
(newest event − the boxes' window end, device time, at every rendered frame; median / p95 / max), windows scored
and skipped, display chunks dropped, and the detector latency's parts (median; ``LiveView.stages_ms``: to the
window's histogram, waiting for a step in progress, the RVT step, post-processing). The goals: 0 dropped
transfers, display ≥ 20 fps, boxes ≤ 150 ms behind the events (median).

On a shared machine, run it with the process group at a higher CPU share than the other load, e.g. ``setsid sh -c
'echo -15 > /proc/self/autogroup && exec python benchmarks/view_live.py'`` (Linux autogroups: nice values only
order threads inside one session), and say so with the figures.
"""

from __future__ import annotations

import argparse
import http.client
import json
import multiprocessing
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from _common import metadata_line

from davis_rig.types import DAVIS346_HW, make_events
from davis_rig.usb.sources import DataSource
from davis_rig.viewer.live import default_detector_threads

DEFAULT_QUEUE_MIB = 8.0  # as benchmarks/io.py: ~0.17 s of this stream at 12 M ev/s


def scene(rate_hz: float, seconds: float, aps_fps: float, seed: int = 0):
    """Events (EVENT_DTYPE, time-sorted) and APS frames of a 60x150 px blob crossing the sensor, 20 % noise."""
    from davis_rig.protocol.frames import ApsFrame

    rng = np.random.default_rng(seed)
    n = int(rate_hz * seconds)
    t = np.sort(rng.integers(0, int(seconds * 1e6), n))
    height, width = DAVIS346_HW
    left = (40 + (width - 140) * t / (seconds * 1e6)).astype(np.int64)
    blob = rng.random(n) < 0.8
    x = np.where(blob, left + rng.integers(0, 60, n), rng.integers(0, width, n))
    y = np.where(blob, rng.integers(50, 200, n), rng.integers(0, height, n))
    events = make_events(t, x, y, rng.integers(0, 2, n))
    frames = []
    if aps_fps > 0:
        period = int(1e6 / aps_fps)
        for start in range(5_000, int(seconds * 1e6) - period, period):
            pixels = np.full(DAVIS346_HW, 300 << 6, np.uint16)
            x0 = 40 + int((width - 140) * start / (seconds * 1e6))
            pixels[50:200, x0:x0 + 60] = 900 << 6
            frames.append(ApsFrame(pixels, 0, 0, start, start + 100, start + 4100, start + 6000))
    return events, frames


class Transfers(DataSource):
    """A fresh paced source over already encoded ``(release µs, transfer)`` pairs (one per run)."""

    def __init__(self, items):
        super().__init__()
        for release_us, data in items:
            self._push(release_us, data)


def encode(events, frames) -> tuple[list, int]:
    """Encode the scene once: ``([(release µs, transfer bytes)], total bytes)``."""
    from davis_rig.protocol.layout import SensorLayout
    from davis_rig.usb.sources import EncodedSource

    source = EncodedSource(events, frames, layout=SensorLayout.davis346(), paced=True)
    items = []
    while (release := source.peek_release_us()) is not None:
        items.append((release, source.pop()))
    return items, source.total_bytes


def cpu_s() -> float:
    """User + system CPU s of this process (every thread)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def children_cpu_s() -> float:
    """User + system CPU s of the child processes that ended (the view process, the page client)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


class Timed:
    """The camera as ``record_session`` sees it, marking when chunks were written and stopping after the last byte.

    A chunk counts as written when the next one is asked for (``record_session`` appends before it reads again).
    """

    def __init__(self, camera, total_bytes: int, stop: threading.Event):
        self.camera, self.total_bytes, self._stop = camera, total_bytes, stop
        self.first = self.last = None  # (wall s, last event t µs) of the first / latest written chunk with events
        self.cpu_first = 0.0
        self._handed = None

    def __getattr__(self, name):
        return getattr(self.camera, name)

    def read(self, timeout_s=None):
        now = time.perf_counter()
        if self._handed is not None:
            self.last = (now, self._handed)
            if self.first is None:
                self.first, self.cpu_first = self.last, cpu_s()
            self._handed = None
        chunk = self.camera.read(timeout_s)
        if chunk is not None and len(chunk.events):
            self._handed = int(chunk.events["t"][-1])
        elif chunk is None:
            stats = self.camera.stats
            if stats.bytes + stats.dropped_bytes >= self.total_bytes:
                self._stop.set()
        return chunk


def page_client(port: int, ready, stop, conn) -> None:
    """Fetch every new frame like the page does (long poll with the last sequence number), in a process of its own
    (a browser is not in the recording's interpreter either); sets ``ready`` at the first frame, sends
    ``[(arrival s, bytes)]`` when ``stop`` is set."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    seq, received = -1, []
    while not stop.is_set():
        ready.set()
        connection.request("GET", f"/api/live/frame?after={seq}")
        response = connection.getresponse()
        body = response.read()
        if response.status == 200:
            seq = int(response.getheader("X-Frame-Seq"))
            received.append((time.perf_counter(), len(body)))
    connection.close()
    conn.send(received)


def run(items, total_bytes: int, span_s: float, queue_bytes: int, view_options: dict | None) -> dict:
    """One recording of the encoded scene, with the live view when ``view_options`` is given."""
    from davis_rig.device.camera import Davis346
    from davis_rig.session.record import record_session
    from davis_rig.usb.async_bulk import DEFAULT_TRANSFER_BYTES
    from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

    stop = threading.Event()
    device = VirtualDavis346(source=Transfers(items))
    out = {}
    with tempfile.TemporaryDirectory() as tmp, \
            Davis346.open(backend=VirtualDavis346Backend(device),
                          queue_transfers=max(1, queue_bytes // DEFAULT_TRANSFER_BYTES)) as camera:
        timed = Timed(camera, total_bytes, stop)
        cpu0 = cpu_s()
        if view_options is None:
            summary = record_session(timed, Path(tmp) / "plain.h5", stop_event=stop, duration_s=span_s * 5 + 10)
        else:
            from davis_rig.viewer.live import TappedCamera
            from davis_rig.viewer.live_process import LiveViewProcess

            children0 = children_cpu_s()  # the children of earlier runs (--runs) ended before this one
            context = multiprocessing.get_context("spawn")
            client_stop = context.Event()
            receiver, sender = context.Pipe(duplex=False)
            with LiveViewProcess(stats=lambda: camera.stats, **view_options) as view:
                port = int(view.url.rsplit(":", 1)[1].split("/")[0])
                client_ready = context.Event()
                client = context.Process(target=page_client, args=(port, client_ready, client_stop, sender),
                                         daemon=True)
                client.start()
                client_ready.wait(60)  # the client's start is not part of the recording
                cpu0 = cpu_s()  # the view process's start (spawn, model load) is not the recording's
                summary = record_session(TappedCamera(timed, view.tap), Path(tmp) / "viewed.h5", stop_event=stop,
                                         duration_s=span_s * 5 + 10)
                time.sleep(0.5)  # the last windows reach the detector
                client_stop.set()
                received = receiver.recv()  # time.perf_counter is system-wide (CLOCK_MONOTONIC) on Linux
                client.join()
                connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
                connection.request("GET", "/api/live/stats")
                out["view"] = json.loads(connection.getresponse().read())
                connection.close()
            out["view_process_cpu_s"] = children_cpu_s() - children0  # the view process and the page client
            t_first, t_last = timed.first[0], timed.last[0]
            shown = [t for t, _ in received if t_first <= t <= t_last]
            out["display_fps"] = len(shown) / (t_last - t_first)
            out["kb_per_frame"] = np.mean([size for _, size in received]) / 1024 if received else 0.0
        cpu_end = cpu_s()
        stats = camera.stats
    data_s = (timed.last[1] - timed.first[1]) / 1e6
    wall_s = timed.last[0] - timed.first[0]
    out.update(events=summary.events, dropped=stats.dropped_transfers, transfers=stats.transfers,
               realtime=data_s / wall_s, lag_ms=(wall_s - data_s) * 1e3, wall_s=wall_s, data_s=data_s,
               cpu_per_data_s=(cpu_end - timed.cpu_first) / data_s if data_s > 0 else float("nan"),
               cpu_total_s=cpu_end - cpu0)
    return out


def detector_step_ms(detector: Path, threads: int, repeats: int = 10):
    """How long one RVT step (histogram of a 12 M ev/s window + the ONNX step) takes here, on a quiet recording
    path: the yardstick for the latency figures (``_common.Timing``)."""
    from _common import time_ms

    from davis_rig.events.histogram import WINDOW_US, stacked_histogram
    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner
    from davis_rig.types import RVT_HW

    rng = np.random.default_rng(1)
    n = 600_000
    x, y = rng.integers(0, RVT_HW[1], n), rng.integers(0, RVT_HW[0], n)
    t, p = np.sort(rng.integers(0, WINDOW_US, n)), rng.integers(0, 2, n)
    runner = RVTOnnxRunner(detector, intra_op_threads=threads)
    return time_ms(lambda: runner.step(stacked_histogram(x, y, t, p)[None]), warmup=3, repeats=repeats)


def one_run(items, total_bytes: int, n_events: int, queue_bytes: int, detector, args) -> tuple[dict, float | None]:
    """The scene recorded without, then with the view; prints the figures and returns ``({goal: met}, median ms
    the boxes shown were behind the events shown, or None)``."""
    results = {"without view": run(items, total_bytes, args.seconds, queue_bytes, None),
               "with view": run(items, total_bytes, args.seconds, queue_bytes,
                                {"detector": detector, "threads": args.threads, "fps": args.fps})}
    for name, r in results.items():
        print(f"{name:13s} dropped transfers {r['dropped']}/{r['transfers'] + r['dropped']}, recorded "
              f"{r['events']}/{n_events} events, real-time factor {r['realtime']:.3f} (lag at the end "
              f"{r['lag_ms']:.0f} ms), {r['cpu_per_data_s']:.2f} CPU-s per data-s")
    r = results["with view"]
    view, det = r["view"], r["view"]["detector"]
    print(f"view process + page client: {r['view_process_cpu_s']:.1f} CPU-s in all (start and model load included); display "
          f"{r['display_fps']:.1f} fps received by the page client ({r['kb_per_frame']:.0f} KiB JPEG), "
          f"{view['frames_rendered']} frames rendered; display chunks dropped {view['view_dropped_chunks']}")
    if view.get("thread_cpu_s"):
        print("view process CPU-s by thread (start and model load included): "
              + ", ".join(f"{name} {cpu:.2f}" for name, cpu in sorted(view["thread_cpu_s"].items())))
    if detector is not None:
        print(f"detector ({args.threads} threads): latency (chunk completing the window read -> boxes) median "
              f"{det['latency_ms_median']:.0f} ms, p95 {det['latency_ms_p95']:.0f} ms, max {det['latency_ms_max']:.0f}"
              f" ms; windows scored {det['windows_scored']}, skipped {det['windows_skipped']}")
        if det.get("stages_ms_median"):
            print("detector latency in parts (median ms): "
                  + ", ".join(f"{name} {ms:.1f}" for name, ms in det["stages_ms_median"].items()))
        print(f"boxes behind the events shown: median {det['behind_ms_median']:.0f} ms, p95 "
              f"{det['behind_ms_p95']:.0f} ms, max {det['behind_ms_max']:.0f} ms")
    base = results["without view"]
    print(f"ratio with/without view: CPU-s per data-s {r['cpu_per_data_s'] / base['cpu_per_data_s']:.2f}, "
          f"real-time factor {r['realtime'] / base['realtime']:.3f}")
    goals = [("0 dropped transfers", r["dropped"] == 0), ("display >= 20 fps", r["display_fps"] >= 20)]
    if detector is not None:
        goals.append(("boxes <= 150 ms behind (median)",
                      det["behind_ms_median"] is not None and det["behind_ms_median"] <= 150))
    print("goals: " + ", ".join(f"{goal}: {'met' if ok else 'NOT met'}" for goal, ok in goals))
    return dict(goals), det["behind_ms_median"] if detector is not None else None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=12e6, help="event rate of the virtual camera, ev/s")
    parser.add_argument("--seconds", type=float, default=3.0, help="length of the scene, s")
    parser.add_argument("--threads", type=int, default=default_detector_threads(),
                        help="onnxruntime threads of the detector (default: davis-record --view's on this machine)")
    parser.add_argument("--fps", type=float, default=25.0, help="display frames rendered per second")
    parser.add_argument("--aps-fps", type=float, default=25.0, help="APS frames per second in the scene (0: none)")
    parser.add_argument("--queue-mib", type=float, default=DEFAULT_QUEUE_MIB,
                        help="nominal capacity of the driver's reader queue, MiB")
    parser.add_argument("--no-detector", action="store_true", help="the view without RVT")
    parser.add_argument("--int8", action="store_true", help="the bundled detector's int8 graph")
    parser.add_argument("--runs", type=int, default=1,
                        help="record the scene this many times (each without, then with the view) and count the "
                             "runs that meet each goal (default 1)")
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error(f"argument --runs: expected >= 1, got {args.runs}")
    from davis_rig.models import default_detector_path

    detector = None if args.no_detector else default_detector_path(int8=args.int8)
    print(metadata_line(("numpy", "onnxruntime", "h5py", "opencv-contrib-python-headless"),
                        detector_threads=args.threads, display_fps_target=args.fps))
    events, frames = scene(args.rate, args.seconds, args.aps_fps)
    items, total_bytes = encode(events, frames)
    n_events = len(events)
    del events, frames
    print(f"scene: {n_events / 1e6:.1f} M events at {args.rate / 1e6:.1f} M ev/s for {args.seconds:g} s, APS at "
          f"{args.aps_fps:g} fps, {total_bytes / 1e6:.0f} MB in {len(items)} transfers; reader queue "
          f"{args.queue_mib:g} MiB; detector {detector.name if detector else 'none'}")
    if detector is not None:
        print(f"RVT-T step alone in this process now ({args.threads} threads, after 3 warm-up steps): "
              f"{detector_step_ms(detector, args.threads)}")
    queue_bytes = int(args.queue_mib * 2**20)
    goals, behind = [], []
    for k in range(args.runs):
        if args.runs > 1:
            print(f"--- run {k + 1} of {args.runs}")
        run_goals, run_behind = one_run(items, total_bytes, n_events, queue_bytes, detector, args)
        goals.append(run_goals)
        behind.append(run_behind)
    if args.runs > 1:
        print(f"over {args.runs} runs: " + ", ".join(
            f"{goal}: met in {sum(run_goals[goal] for run_goals in goals)} of {args.runs}" for goal in goals[0]))
        if detector is not None:
            print("boxes behind the events shown, median per run (ms): "
                  + ", ".join("-" if ms is None else f"{ms:.0f}" for ms in behind))
    return 0


if __name__ == "__main__":
    sys.exit(main())
