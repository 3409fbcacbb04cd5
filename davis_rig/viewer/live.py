"""The live view: frames and RVT boxes of an event stream as it arrives, for the page of ``davis-record --view``.

``davis-record --view`` runs a :class:`LiveView` in a process of its own, fed through shared memory
(:mod:`davis_rig.viewer.live_process`), so that none of this competes with the recording for the GIL. Inside
the view (threads, and what each does):

- chunks arrive through :meth:`LiveTap.offer` (a ``deque.append`` of a reference per reader: no copy, no lock,
  never blocks; :class:`TappedCamera` offers every chunk a camera's ``read`` returns);
- with a detector, ``davis-view-windows`` takes the chunks every 2 ms and counts their events into the open
  50 ms window's stacked histogram of the 304x240 crop (:class:`~davis_rig.viewer.live_windows.WindowHistograms`),
  so that a window's end only clips its counts; it leaves each complete window in a one-slot :class:`Mailbox`
  (a window not taken yet is replaced by the newer one: skipped, counted; so is a window that the same look at
  the tap completed together with a newer one, left uncounted);
- ``davis-view-detector`` runs one RVT step on the window in the mailbox (onnxruntime, ``threads`` intra-op
  threads) and post-processes it (:class:`WindowDetector`: the LSTM states are carried over skipped windows and
  reset where the stream's time restarts);
- ``davis-view-live`` takes the chunks too (its own queue: the detector's windows never hold up the display),
  accumulates the events of the current display frame (ON/OFF counts on the sensor), keeps the latest APS frame,
  and every ``1 / fps`` s renders a frame (:func:`~davis_rig.viewer.render.render_view`) and encodes it as JPEG;
- the web server's threads hand out the latest encoded frame (a page that is slower gets fewer frames).

On Linux the view's threads run at nice +10 (onnxruntime's worker threads inherit it from the detector thread,
which creates the session), so the scheduler serves the capture first on a busy CPU. The tap holds at most ``max_pending_chunks`` chunks: when the view falls behind,
the oldest are dropped — display data, never recorded data — and counted (``view_dropped_chunks``).
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from davis_rig.errors import DavisRigError
from davis_rig.events.histogram import WINDOW_US
from davis_rig.types import DAVIS346_HW, RVT_HW, RVT_NMS_IOU
from davis_rig.viewer.live_windows import WindowHistograms, join_events, later_window
from davis_rig.viewer.render import LAYERS, ImageFormat, ViewContent, add_event_counts, encode_image, render_view
from davis_rig.viewer.server import RequestError, Response, int_param, json_response

__all__ = ["LiveApp", "LiveTap", "LiveView", "Mailbox", "TappedCamera", "WindowDetector", "default_detector_threads",
           "lower_priority"]

def default_detector_threads(cpu_count: int | None = None) -> int:
    """onnxruntime threads of the live detector when none are given: 2, but 1 on a machine of 2 cores or fewer.

    The recording keeps a core to itself: beside a 12 M ev/s recording on 2 cores, the boxes came 122 ms (median)
    after their window with 1 thread against 164 ms with 2 (``benchmarks/view_live.py``, benchmarks/README.md).

    Args:
        cpu_count: cores of the machine (default ``os.cpu_count()``).
    """
    cores = cpu_count if cpu_count is not None else (os.cpu_count() or 1)
    return 1 if cores <= 2 else 2


#: nice increment of the view's threads (Linux), so the capture threads get the CPU first.
VIEW_NICE = 10
#: How often the windows thread looks for new chunks, s.
POLL_S = 0.002


def lower_priority(increment: int = VIEW_NICE) -> None:
    """Raise the calling thread's nice value by ``increment`` (Linux only: elsewhere ``setpriority`` on a
    thread id is not per thread, so nothing is done)."""
    if sys.platform.startswith("linux"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                           os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + increment)
        except OSError:
            pass  # not permitted here (a container's seccomp policy): the view runs at normal priority


class LiveTap:
    """Non-blocking hand-off of decoded chunks from the recording loop to the live view's readers.

    Every reader gets every chunk, in its own queue, so that a reader that falls behind (the detector's windows)
    does not hold up another (the display).

    Args:
        max_chunks: chunks kept for each reader; beyond, its oldest are dropped (counted in
            :attr:`dropped_chunks`).
        readers: how many readers take chunks (numbered from 0).
    """

    def __init__(self, max_chunks: int = 256, readers: int = 1):
        self._queues = [deque(maxlen=int(max_chunks)) for _ in range(int(readers))]
        self._taken = [0] * int(readers)
        self.offered_chunks = 0
        self.offered_events = 0

    def offer(self, chunk, t_offer_s: float | None = None) -> None:
        """Hand over one decoded chunk (called by the recording loop; O(readers), never blocks, never copies).

        Args:
            chunk: has ``events`` (EVENT_DTYPE) and/or ``frames`` (APS frames).
            t_offer_s: when the recording read it, ``time.monotonic()`` s (default: now).
        """
        item = (time.monotonic() if t_offer_s is None else t_offer_s, chunk)
        for queue in self._queues:
            queue.append(item)
        events = getattr(chunk, "events", None)
        self.offered_chunks += 1
        self.offered_events += 0 if events is None else len(events)

    def take(self, reader: int = 0) -> list:
        """All chunks offered since ``reader``'s last call, oldest first, as ``(offer time s (monotonic), chunk)``."""
        queue, out = self._queues[reader], []
        while True:
            try:
                out.append(queue.popleft())
            except IndexError:
                break
        self._taken[reader] += len(out)
        return out

    @property
    def dropped_chunks(self) -> int:
        """Chunks a reader never saw because it fell behind (the most over the readers)."""
        return max(self.offered_chunks - taken - len(queue) for taken, queue in zip(self._taken, self._queues))


class TappedCamera:
    """A camera as :func:`~davis_rig.session.record.record_session` sees it, whose reads also go to a tap.

    Every attribute but ``read`` is the camera's own.
    """

    def __init__(self, camera, tap: LiveTap):
        self._camera = camera
        self._tap = tap

    def __getattr__(self, name):
        return getattr(self._camera, name)

    def read(self, timeout_s: float | None = None):
        """The camera's ``read``; a chunk is also offered to the tap."""
        chunk = self._camera.read(timeout_s)
        if chunk is not None:
            self._tap.offer(chunk)
        return chunk


class Mailbox:
    """One slot between two threads: :meth:`put` replaces an item not taken yet (counted in :attr:`replaced`), so
    the taker always gets the newest and never more than one waits."""

    def __init__(self):
        self._item = None
        self._cond = threading.Condition()
        self.replaced = 0

    def put(self, item, merge=None) -> None:
        """Leave ``item`` (not ``None``) in the slot, replacing what is there (``merge(replaced, item)`` instead of
        ``item`` when given: what the replaced item carried that must not be lost)."""
        with self._cond:
            if self._item is not None:
                self.replaced += 1
                if merge is not None:
                    item = merge(self._item, item)
            self._item = item
            self._cond.notify()

    def get(self, timeout_s: float):
        """Take the item in the slot, waiting up to ``timeout_s`` for one; ``None`` when none came."""
        with self._cond:
            self._cond.wait_for(lambda: self._item is not None, timeout_s)
            item, self._item = self._item, None
            return item


class WindowDetector:
    """RVT over the live windows handed to it, one recurrent step each.

    The LSTM states of a step are the previous step's, also when windows were skipped between them (a detector
    slower than the windows): the states then span the gap, as for a camera at a lower window rate, instead of
    starting over at every step, which would leave RVT without its memory whenever it cannot keep up. They are
    reset at a window that starts a sequence (the stream began or its time went back).

    Args:
        runner: an :class:`~davis_rig.models.rvt.ort_runner.RVTOnnxRunner` (``step(hist, states)``).
        threshold: confidence threshold (obj · class).
        nms_threshold: IoU of the non-maximum suppression.
    """

    def __init__(self, runner, threshold: float, nms_threshold: float = RVT_NMS_IOU):
        self.runner = runner
        self.threshold = float(threshold)
        self.nms_threshold = float(nms_threshold)
        self.states = None

    def step(self, histogram: np.ndarray, starts_sequence: bool):
        """One RVT step on a window's histogram (uint8 [20, 240, 304]); returns the raw decoded output."""
        if starts_sequence:
            self.states = None
        decoded, self.states = self.runner.step(histogram[None], self.states)
        return decoded

    def boxes(self, decoded) -> np.ndarray:
        """The step's detections after threshold and NMS: float32 [K, 7] rows ``(x1, y1, x2, y2, obj, class_conf,
        class_pred)``, crop px."""
        from davis_rig.models.rvt.postprocess import postprocess

        rows = postprocess(decoded, self.threshold, self.nms_threshold)[0]
        return np.zeros((0, 7), np.float32) if rows is None else rows


def _percentile(values, q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


#: The parts of the detector's latency (``LiveView.stages``), in order: the chunk completing a window read by the
#: recording -> the window's histogram ready (ring, feed, counting, clip); -> taken by the detector (waiting for a
#: step in progress); -> RVT step done; -> boxes ready (threshold, NMS).
STAGES = ("to_window", "wait", "step", "post")


class LiveView:
    """Frames and RVT boxes of a running recording (see the module docstring); a context manager.

    Args:
        detector: RVT step ONNX, or ``None`` for no boxes.
        threshold: detector confidence threshold (obj · class).
        threads: onnxruntime intra-op threads of the detector (default :func:`default_detector_threads`).
        fps: display frames rendered per second.
        crop_origin_xy: the 304x240 crop, px (default centred).
        window_us: detector window, µs.
        stats: called about twice a second for the camera's counters (``dropped_transfers`` is shown; an optional
            ``view_dropped_chunks`` counts display chunks dropped before this view's tap), or ``None``.
        max_pending_chunks: chunks the tap keeps for a view that falls behind.
        jpeg_quality: 0..100.

    Raises (on entering):
        ModelFormatError / MissingDependencyError: the detector cannot be loaded (the recording has not started).
    """

    def __init__(self, *, detector: Path | None = None, threshold: float = 0.1, threads: int | None = None,
                 fps: float = 25.0, crop_origin_xy: tuple[int, int] | None = None, window_us: int = WINDOW_US,
                 stats=None, max_pending_chunks: int = 256, jpeg_quality: int = 80,
                 nms_threshold: float = RVT_NMS_IOU):
        from davis_rig.events.crop import center_crop_origin

        self.detector = None if detector is None else Path(detector)
        self.threshold = float(threshold)
        self.threads = int(threads) if threads is not None else default_detector_threads()
        self.period_s = 1.0 / float(fps)
        self.crop_origin_xy = tuple(crop_origin_xy) if crop_origin_xy is not None else center_crop_origin()
        self.window_us = int(window_us)
        self.stats_source = stats
        self.jpeg_quality = int(jpeg_quality)
        self.nms_threshold = float(nms_threshold)
        self.tap = LiveTap(max_pending_chunks, readers=1 if self.detector is None else 2)  # display, windows
        self._mailbox = Mailbox()
        self._windows = None  # the detector's WindowHistograms (made by the windows thread)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._frame_cond = threading.Condition()
        self._frame: tuple[int, bytes] | None = None
        self._boxes: tuple[int, np.ndarray] | None = None  # (window end µs, float32 [K, 7]) of the latest step
        self._detector_ready = threading.Event()
        self._detector_error: DavisRigError | None = None
        #: detector latency of the last 1000 windows scored, ms: the chunk that completed the window was read by the
        #: recording -> its boxes ready
        self.latency_ms: deque = deque(maxlen=1000)
        #: the same windows' latency in parts (:data:`STAGES`), ms: one tuple per window
        self.stages_ms: deque = deque(maxlen=1000)
        #: at the last 1000 frames drawn with boxes: newest event − the boxes' window end, ms of device time
        self.behind_ms: deque = deque(maxlen=1000)
        self._render_times: deque = deque(maxlen=200)
        self._served_times: deque = deque(maxlen=200)
        self._camera_stats: dict = {}
        self._newest_t: int | None = None
        self._t_first_chunk: float | None = None
        self._rate: tuple[float, int] = (time.monotonic(), 0)
        self._rate_hz = 0.0
        self.windows_scored = 0
        self.frames_rendered = 0

    # --- life cycle ---------------------------------------------------------------------------
    def __enter__(self) -> "LiveView":
        if self.detector is not None:
            self._start(self._detector_loop, "davis-view-detector")
            self._detector_ready.wait()
            if self._detector_error is not None:
                self.__exit__(None, None, None)
                raise self._detector_error
            self._start(self._windows_loop, "davis-view-windows")
        self._start(self._view_loop, "davis-view-live")
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join()
        self._threads = []

    def _start(self, target, name: str) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    # --- the windows thread -------------------------------------------------------------------
    def _windows_loop(self) -> None:
        """Count the chunks' events into the detector's windows; mail the windows that complete."""
        lower_priority()
        self._windows = windows = WindowHistograms(self.crop_origin_xy, self.window_us)
        while not self._stop.is_set():
            parts = [(t_offer, events) for t_offer, chunk in self.tap.take(1)
                     if (events := getattr(chunk, "events", None)) is not None and len(events)]
            if parts:  # one push for what came since the last look: a window completed and superseded is skipped
                events = join_events([events for _, events in parts])
                if (window := windows.push(events)) is not None:
                    ends = np.cumsum([len(events) for _, events in parts])  # which chunk completed it, read when
                    t_offer = parts[int(np.searchsorted(ends, window.completed_at, side="right"))][0]
                    self._mailbox.put((window, t_offer, time.monotonic()),
                                      lambda replaced, item: (later_window(replaced[0], item[0]), *item[1:]))
            self._stop.wait(POLL_S)

    def _windows_skipped(self) -> int:
        """Complete windows the detector did not score: superseded in a push, or replaced in the mailbox."""
        return self._mailbox.replaced + (self._windows.superseded if self._windows is not None else 0)

    # --- the view thread ----------------------------------------------------------------------
    def _view_loop(self) -> None:
        lower_priority()
        counts = np.zeros((2, *DAVIS346_HW), np.int32)  # the events of the frame being drawn, counted as they come
        aps = None
        next_render = next_stats = time.monotonic()
        while not self._stop.is_set():
            taken = self.tap.take(0)
            if taken:
                if self._t_first_chunk is None:
                    self._t_first_chunk = taken[0][0]
                aps = self._latest_aps(taken) or aps
                parts = [events for _, chunk in taken
                         if (events := getattr(chunk, "events", None)) is not None and len(events)]
                if parts:
                    events = join_events(parts)
                    add_event_counts(counts, events["x"], events["y"], events["p"])
                    self._newest_t = int(events["t"][-1])
            now = time.monotonic()
            if now >= next_stats:
                self._update_stats(now)
                next_stats = now + 0.5
            if now >= next_render:
                self._render(counts, aps)
                counts[...] = 0
                next_render = max(next_render + self.period_s, now)
            self._stop.wait(min(0.005, max(next_render - time.monotonic(), 0.0)))

    @staticmethod
    def _latest_aps(taken: list):
        """``(pixels, (x0, y0))`` of the newest APS frame among the chunks taken, or ``None``."""
        for _, chunk in reversed(taken):
            frames = getattr(chunk, "frames", None)
            if frames:
                return np.asarray(frames[-1].pixels), (int(frames[-1].position_x), int(frames[-1].position_y))
        return None

    def _update_stats(self, now: float) -> None:
        t_then, events_then = self._rate
        events = self.tap.offered_events
        if now > t_then:
            self._rate_hz = (events - events_then) / (now - t_then)
        self._rate = (now, events)
        if self.stats_source is not None:
            stats = self.stats_source()
            self._camera_stats = {"dropped_transfers": int(getattr(stats, "dropped_transfers", 0) or 0),
                                  "upstream_dropped_chunks": int(getattr(stats, "view_dropped_chunks", 0) or 0)}

    def _render(self, counts: np.ndarray, aps) -> None:
        boxes = self._boxes
        detections = np.zeros((0, 7), np.float32)
        if boxes is not None:
            end_us, detections = boxes
            if self._newest_t is not None:
                self.behind_ms.append((self._newest_t - end_us) / 1000)
        seconds = 0.0 if self._t_first_chunk is None else time.monotonic() - self._t_first_chunk
        caption = f"{seconds:7.1f} s  {self._rate_hz / 1e6:6.2f} Mev/s"
        image = render_view(ViewContent(counts=counts, aps=aps, detections=detections,
                                        crop_origin_xy=self.crop_origin_xy, layers=frozenset(LAYERS),
                                        caption=caption))
        data = encode_image(image, ImageFormat.JPG, self.jpeg_quality)
        with self._frame_cond:
            seq = self._frame[0] + 1 if self._frame is not None else 0
            self._frame = (seq, data)
            self._frame_cond.notify_all()
        self._render_times.append(time.monotonic())
        self.frames_rendered += 1

    # --- the detector thread ------------------------------------------------------------------
    def _detector_loop(self) -> None:
        lower_priority()  # before the session exists: its intra-op threads inherit the nice value
        from davis_rig.events.histogram import NUM_BINS
        from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

        try:
            runner = RVTOnnxRunner(self.detector, intra_op_threads=self.threads)
            runner.step(np.zeros((1, 2 * NUM_BINS, *RVT_HW), np.uint8))  # warm-up: the first step allocates
        except DavisRigError as exc:
            self._detector_error = exc
            return
        finally:
            self._detector_ready.set()
        detector = WindowDetector(runner, self.threshold, self.nms_threshold)
        while not self._stop.is_set():
            item = self._mailbox.get(0.1)
            if item is None:
                continue
            window, t_offer, t_ready = item
            t_start = time.monotonic()
            decoded = detector.step(window.histogram, window.starts_sequence)
            t_step = time.monotonic()
            self._boxes = (window.end_us, detector.boxes(decoded))
            t_done = time.monotonic()
            self.latency_ms.append((t_done - t_offer) * 1000)
            self.stages_ms.append(tuple(1000 * d for d in (t_ready - t_offer, t_start - t_ready, t_step - t_start,
                                                           t_done - t_step)))
            self.windows_scored += 1

    # --- what the server asks -----------------------------------------------------------------
    def latest_frame(self, after: int, timeout_s: float = 1.0) -> tuple[int, bytes] | None:
        """The newest encoded frame with a sequence number above ``after`` (waiting up to ``timeout_s``), or ``None``.

        Returns:
            ``(seq, JPEG bytes)``.
        """
        with self._frame_cond:
            self._frame_cond.wait_for(lambda: self._frame is not None and self._frame[0] > after, timeout_s)
            frame = self._frame
        if frame is None or frame[0] <= after:
            return None
        self._served_times.append(time.monotonic())
        return frame

    def thread_cpu_s(self) -> dict[str, float] | None:
        """CPU s used so far by each running thread of this process: Python threads by name, the others
        (onnxruntime's workers) summed as ``native``; ``None`` where ``/proc`` has no per-thread times (not Linux)."""
        names = {str(thread.native_id): thread.name for thread in threading.enumerate()}
        out: dict[str, float] = {}
        try:
            tasks = os.listdir("/proc/self/task")
        except OSError:
            return None
        tick = os.sysconf("SC_CLK_TCK")
        for task in tasks:
            try:
                with open(f"/proc/self/task/{task}/stat") as stat:
                    fields = stat.read().rsplit(")", 1)[1].split()
            except OSError:
                continue  # the thread ended meanwhile
            name = names.get(task, "native")
            out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick  # utime + stime
        return out

    @staticmethod
    def _fps(times: deque) -> float:
        now = time.monotonic()
        recent = [t for t in list(times) if now - t <= 1.0]
        return float(len(recent))

    def stats(self) -> dict:
        """Counters of the view (JSON-ready); ``display`` holds the same as short texts for the page."""
        latency = list(self.latency_ms)
        behind = list(self.behind_ms)
        stages = list(self.stages_ms)
        out = {
            "events": self.tap.offered_events,
            "event_rate_hz": self._rate_hz,
            "dropped_transfers": self._camera_stats.get("dropped_transfers"),
            "view_dropped_chunks": self.tap.dropped_chunks + self._camera_stats.get("upstream_dropped_chunks", 0),
            "frames_rendered": self.frames_rendered,
            "render_fps": self._fps(self._render_times),
            "served_fps": self._fps(self._served_times),
            "thread_cpu_s": self.thread_cpu_s(),
            "detector": None if self.detector is None else {
                "model": self.detector.name, "threshold": self.threshold, "windows_scored": self.windows_scored,
                "windows_skipped": self._windows_skipped(), "latency_ms_median": _percentile(latency, 50),
                "latency_ms_p95": _percentile(latency, 95), "latency_ms_max": max(latency) if latency else None,
                "latency_ms_last": latency[-1] if latency else None, "behind_ms_median": _percentile(behind, 50),
                "behind_ms_p95": _percentile(behind, 95), "behind_ms_max": max(behind) if behind else None,
                "stages_ms_median": dict(zip(STAGES, np.median(stages, axis=0).tolist())) if stages else None,
            },
        }
        display = {"event rate": f"{self._rate_hz / 1e6:.2f} Mev/s", "events": f"{self.tap.offered_events:,}",
                   "dropped transfers": str(out["dropped_transfers"]),
                   "display": f"{out['render_fps']:.0f} fps rendered, {out['served_fps']:.0f} fps served",
                   "view skipped chunks": str(out["view_dropped_chunks"])}
        if self.detector is not None:
            d = out["detector"]
            display["detector"] = (f"{d['model']} @ {self.threshold:g}: latency "
                                   + ("-" if d["latency_ms_last"] is None else f"{d['latency_ms_last']:.0f} ms")
                                   + f", {d['windows_skipped']} windows skipped")
        out["display"] = display
        return out


class LiveApp:
    """The live view's API for :class:`~davis_rig.viewer.server.ViewerServer`.

    Routes (GET, below ``/api/``): ``info``; ``live/frame?after=SEQ`` (the next JPEG frame, long-polled up to
    1 s; 204 when none came; its number in the ``X-Frame-Seq`` header); ``live/stats`` (:meth:`LiveView.stats`).
    """

    mode = "live"

    def __init__(self, view: LiveView):
        self.view = view

    def handle(self, parts: list[str], params: dict) -> Response:
        """Answer ``/api/<parts>``.

        Raises:
            RequestError: unknown route (404) or bad parameter (400).
        """
        if parts == ["info"]:
            return json_response({"mode": self.mode, "crop_origin_xy": list(self.view.crop_origin_xy),
                                  "detector": None if self.view.detector is None else self.view.detector.name})
        if parts == ["live", "frame"]:
            after = int_param(params, "after", -1, 2**62, default=-1)
            frame = self.view.latest_frame(after)
            if frame is None:
                return Response(204, b"", "image/jpeg")
            return Response(200, frame[1], "image/jpeg", (("X-Frame-Seq", str(frame[0])),))
        if parts == ["live", "stats"]:
            return json_response(self.view.stats())
        raise RequestError(404, "no such API route")
