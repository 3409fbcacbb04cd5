"""The live view: frames and RVT boxes of an event stream as it arrives, for the page of ``davis-record --view``.

``davis-record --view`` runs a :class:`LiveView` in a process of its own, fed through shared memory
(:mod:`davis_rig.viewer.live_process`), so that none of this competes with the recording for the GIL. Inside
the view (threads, and what each does):

- chunks arrive through :meth:`LiveTap.offer` (one ``deque.append`` of a reference: no copy, no lock, never
  blocks; :class:`TappedCamera` offers every chunk a camera's ``read`` returns);
- ``davis-view-live`` takes the chunks every few ms, accumulates the events of the current display frame (ON/OFF
  counts on the sensor), keeps the latest APS frame, cuts RVT's 50 ms windows (:class:`WindowCutter`, views, no
  copy), and every ``1 / fps`` s renders a frame (:func:`~davis_rig.viewer.render.render_view`) and encodes it
  as JPEG;
- ``davis-view-detector`` crops the newest complete window to 304x240, turns it into a stacked histogram, runs
  one RVT step (onnxruntime, ``threads`` intra-op threads, LSTM states carried) and post-processes it;
- the web server's threads hand out the latest encoded frame (a page that is slower gets fewer frames).

On Linux the view's threads run at nice +10 (onnxruntime's worker threads inherit it from the detector thread,
which creates the session), so the scheduler serves the capture first on a busy CPU. The tap holds at most
``max_pending_chunks`` chunks: when the view falls behind, the oldest are dropped — display data, never recorded
data — and counted (``view_dropped_chunks``). A detector slower than the windows skips to the newest complete
window (its states carried over the skipped ones) and counts them (``windows_skipped``).
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
from davis_rig.viewer.render import LAYERS, ImageFormat, ViewContent, encode_image, event_counts, render_view
from davis_rig.viewer.server import RequestError, Response, int_param, json_response

__all__ = ["LiveApp", "LiveTap", "LiveView", "TappedCamera", "WindowCutter", "crop_columns", "lower_priority"]

#: nice increment of the view's threads (Linux), so the capture threads get the CPU first.
VIEW_NICE = 10
#: Events of one display frame kept as arrays before they are folded into counts (memory bound if rendering lags).
FOLD_EVENTS = 2_000_000


def lower_priority() -> None:
    """Raise the calling thread's nice value by :data:`VIEW_NICE` (Linux only: elsewhere ``setpriority`` on a
    thread id is not per thread, so nothing is done)."""
    if sys.platform.startswith("linux"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                           os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + VIEW_NICE)
        except OSError:
            pass  # not permitted here (a container's seccomp policy): the view runs at normal priority


class LiveTap:
    """Non-blocking hand-off of decoded chunks from the recording loop to the live view.

    Args:
        max_chunks: chunks kept for the view; beyond, the oldest are dropped (counted in :attr:`dropped_chunks`).
    """

    def __init__(self, max_chunks: int = 256):
        self._queue: deque = deque(maxlen=int(max_chunks))
        self.offered_chunks = 0
        self.offered_events = 0
        self.taken_chunks = 0

    def offer(self, chunk, t_offer_s: float | None = None) -> None:
        """Hand over one decoded chunk (called by the recording loop; O(1), never blocks, never copies).

        Args:
            chunk: has ``events`` (EVENT_DTYPE) and/or ``frames`` (APS frames).
            t_offer_s: when the recording read it, ``time.monotonic()`` s (default: now).
        """
        self._queue.append((time.monotonic() if t_offer_s is None else t_offer_s, chunk))
        events = getattr(chunk, "events", None)
        self.offered_chunks += 1
        self.offered_events += 0 if events is None else len(events)

    def take(self) -> list:
        """All chunks offered since the last call, oldest first, as ``(offer time s (monotonic), chunk)``."""
        out = []
        while True:
            try:
                out.append(self._queue.popleft())
            except IndexError:
                break
        self.taken_chunks += len(out)
        return out

    @property
    def dropped_chunks(self) -> int:
        """Chunks the view never saw because it fell behind."""
        return self.offered_chunks - self.taken_chunks - len(self._queue)


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


class WindowCutter:
    """Cut a live event stream into RVT's windows: ends at ``t0 + k · window_us``, each ``end − window_us ≤ t ≤ end``.

    ``t0`` is the first event's millisecond (as a session's ``t_offset``). A window is complete once an event
    after its end has arrived. Nothing is copied or cropped here (the detector crops the windows it scores, and
    skips the others at no cost): a window is handed out as views into the arrays pushed. Time going back by more
    than a window (a device timestamp reset) restarts the grid at the new time and marks the next window as the
    start of a new sequence (RVT states reset).

    Args:
        window_us: window length, µs.
    """

    def __init__(self, window_us: int = WINDOW_US):
        self.window_us = int(window_us)
        self._end: int | None = None
        self._pending: list[np.ndarray] = []  # arrays (views) holding the current window's events, in order
        self._restart = True

    def push(self, events: np.ndarray) -> list[tuple[int, list[np.ndarray], bool]]:
        """Add time-sorted sensor events (EVENT_DTYPE); return the windows they complete.

        Returns:
            ``[(end µs, [views whose concatenation is the window's events, end − window_us ≤ t ≤ end],
            starts_sequence), ...]``, oldest first.
        """
        if not len(events):
            return []
        t_first, t_last = int(events["t"][0]), int(events["t"][-1])
        if self._end is None or t_first < self._end - 2 * self.window_us:
            self._end = t_first // 1000 * 1000 + self.window_us
            self._pending, self._restart = [], True
        self._pending.append(events)
        done = []
        while t_last > self._end:
            parts = [_between(part, self._end - self.window_us, self._end) for part in self._pending]
            done.append((self._end, [part for part in parts if len(part)], self._restart))
            self._restart = False
            self._end += self.window_us
            # keep what the next window (which starts at the old end, inclusive) may hold
            kept = [_between(part, self._end - self.window_us, None) for part in self._pending]
            self._pending = [part for part in kept if len(part)]
        return done


def _between(events: np.ndarray, t0_us: int, t1_us: int | None) -> np.ndarray:
    """The view of time-sorted ``events`` with ``t0_us <= t <= t1_us`` (no upper bound for ``None``); a binary
    search only where the bounds cut the array (a field of a structured array is strided: searching it copies)."""
    first, last = int(events["t"][0]), int(events["t"][-1])
    if first >= t0_us and (t1_us is None or last <= t1_us):
        return events
    if last < t0_us or (t1_us is not None and first > t1_us):
        return events[:0]
    t = events["t"]
    lo = 0 if first >= t0_us else int(np.searchsorted(t, t0_us, side="left"))
    hi = len(events) if t1_us is None or last <= t1_us else int(np.searchsorted(t, t1_us, side="right"))
    return events[lo:hi]


def crop_columns(parts: list[np.ndarray], origin_xy: tuple[int, int]):
    """The events of ``parts`` (EVENT_DTYPE arrays, in order) inside the 304x240 crop at ``origin_xy``, as
    columns ``(x, y, t, p)`` in crop px (a new array each; the same events as
    :func:`~davis_rig.events.crop.crop_events`)."""
    events = np.concatenate(parts) if len(parts) != 1 else parts[0]
    x0, y0 = (int(v) for v in origin_xy)
    x = events["x"].astype(np.int32) - x0
    y = events["y"].astype(np.int32) - y0
    keep = (x >= 0) & (x < RVT_HW[1]) & (y >= 0) & (y < RVT_HW[0])
    return x[keep], y[keep], events["t"][keep], events["p"][keep]


class _Mailbox:
    """One slot between two threads: :meth:`put` replaces what was not taken yet (counted)."""

    def __init__(self):
        self._item = None
        self._cond = threading.Condition()
        self.replaced = 0

    def put(self, item) -> None:
        with self._cond:
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify()

    def get(self, timeout_s: float):
        with self._cond:
            self._cond.wait_for(lambda: self._item is not None, timeout_s)
            item, self._item = self._item, None
            return item


def _percentile(values, q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


class LiveView:
    """Frames and RVT boxes of a running recording (see the module docstring); a context manager.

    Args:
        detector: RVT step ONNX, or ``None`` for no boxes.
        threshold: detector confidence threshold (obj · class).
        threads: onnxruntime intra-op threads of the detector.
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

    def __init__(self, *, detector: Path | None = None, threshold: float = 0.1, threads: int | None = 2,
                 fps: float = 25.0, crop_origin_xy: tuple[int, int] | None = None, window_us: int = WINDOW_US,
                 stats=None, max_pending_chunks: int = 256, jpeg_quality: int = 80,
                 nms_threshold: float = RVT_NMS_IOU):
        from davis_rig.events.crop import center_crop_origin

        self.detector = None if detector is None else Path(detector)
        self.threshold = float(threshold)
        self.threads = threads
        self.period_s = 1.0 / float(fps)
        self.crop_origin_xy = tuple(crop_origin_xy) if crop_origin_xy is not None else center_crop_origin()
        self.window_us = int(window_us)
        self.stats_source = stats
        self.jpeg_quality = int(jpeg_quality)
        self.nms_threshold = float(nms_threshold)
        self.tap = LiveTap(max_pending_chunks)
        self._cutter = WindowCutter(self.window_us)
        self._mailbox = _Mailbox()
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

    # --- the view thread ----------------------------------------------------------------------
    def _view_loop(self) -> None:
        lower_priority()
        shown: list[np.ndarray] = []  # the events of the frame being drawn, one array per chunk
        counts = np.zeros((2, *DAVIS346_HW), np.int64)
        aps = None
        next_render = next_stats = time.monotonic()
        while not self._stop.is_set():
            taken = self.tap.take()
            if taken:
                if self._t_first_chunk is None:
                    self._t_first_chunk = taken[0][0]
                aps = self._latest_aps(taken) or aps
                shown.extend(self._take_events(taken))
                if sum(len(part) for part in shown) > FOLD_EVENTS:  # keep memory bounded if rendering lags
                    counts += self._counts(shown)
                    shown = []
            now = time.monotonic()
            if now >= next_stats:
                self._update_stats(now)
                next_stats = now + 0.5
            if now >= next_render:
                self._render(counts + self._counts(shown), aps)
                counts[...] = 0
                shown = []
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

    def _take_events(self, taken: list) -> list[np.ndarray]:
        """The non-empty event arrays of the chunks taken (not copied); the detector's windows are cut from them."""
        out = []
        for t_offer, chunk in taken:
            events = getattr(chunk, "events", None)
            if events is None or not len(events):
                continue
            out.append(events)
            self._newest_t = int(events["t"][-1])
            for end, parts, restart in self._cutter.push(events):  # complete since this chunk was read
                self._mailbox.put((end, parts, restart, t_offer))
        return out

    @staticmethod
    def _counts(parts: list) -> np.ndarray:
        if not parts:
            return np.zeros((2, *DAVIS346_HW), np.int64)
        events = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return event_counts(events["x"], events["y"], events["p"], DAVIS346_HW)

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
        from davis_rig.events.histogram import NUM_BINS, stacked_histogram
        from davis_rig.models.rvt.ort_runner import RVTOnnxRunner
        from davis_rig.models.rvt.postprocess import postprocess

        try:
            runner = RVTOnnxRunner(self.detector, intra_op_threads=self.threads)
            runner.step(np.zeros((1, 2 * NUM_BINS, *RVT_HW), np.uint8))  # warm-up: the first step allocates
        except DavisRigError as exc:
            self._detector_error = exc
            return
        finally:
            self._detector_ready.set()
        states = None
        while not self._stop.is_set():
            item = self._mailbox.get(0.1)
            if item is None:
                continue
            end_us, parts, restart, t_offer = item
            if restart:
                states = None
            if parts:
                x, y, t, p = crop_columns(parts, self.crop_origin_xy)
                hist = stacked_histogram(x, y, np.maximum.accumulate(t) if len(t) else t, p)
            else:
                hist = np.zeros((2 * NUM_BINS, *RVT_HW), np.uint8)
            decoded, states = runner.step(hist[None], states)
            rows = postprocess(decoded, self.threshold, self.nms_threshold)[0]
            self._boxes = (end_us, np.zeros((0, 7), np.float32) if rows is None else rows)
            self.latency_ms.append((time.monotonic() - t_offer) * 1000)
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

    @staticmethod
    def _fps(times: deque) -> float:
        now = time.monotonic()
        recent = [t for t in list(times) if now - t <= 1.0]
        return float(len(recent))

    def stats(self) -> dict:
        """Counters of the view (JSON-ready); ``display`` holds the same as short texts for the page."""
        latency = list(self.latency_ms)
        behind = list(self.behind_ms)
        out = {
            "events": self.tap.offered_events,
            "event_rate_hz": self._rate_hz,
            "dropped_transfers": self._camera_stats.get("dropped_transfers"),
            "view_dropped_chunks": self.tap.dropped_chunks + self._camera_stats.get("upstream_dropped_chunks", 0),
            "frames_rendered": self.frames_rendered,
            "render_fps": self._fps(self._render_times),
            "served_fps": self._fps(self._served_times),
            "detector": None if self.detector is None else {
                "model": self.detector.name, "threshold": self.threshold, "windows_scored": self.windows_scored,
                "windows_skipped": self._mailbox.replaced, "latency_ms_median": _percentile(latency, 50),
                "latency_ms_p95": _percentile(latency, 95), "latency_ms_max": max(latency) if latency else None,
                "latency_ms_last": latency[-1] if latency else None, "behind_ms_median": _percentile(behind, 50),
                "behind_ms_p95": _percentile(behind, 95), "behind_ms_max": max(behind) if behind else None,
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
