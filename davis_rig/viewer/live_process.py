"""The live view in a process of its own, so that it never competes with the recording for Python's GIL.

Measured (``benchmarks/view_live.py``): run as threads of the recording process, the detector's histograms and
the rendering hold the GIL for milliseconds at a time and the recording dropped transfers at 12 M ev/s. Here
the recording's interpreter only copies each chunk's events into shared memory and, in one thread, sends the
newest APS frame and the camera's counters a few times a second.

Recording process (:class:`LiveViewProcess`):

- ``record_session`` reads the camera through :class:`~davis_rig.viewer.live.TappedCamera`, which hands each
  decoded chunk to :class:`RingTap`: its events are copied into an :class:`EventRing` in shared memory (a memcpy,
  never a wait: the ring overwrites what the view has not read) with a mark (the chunk's end, last event time,
  when the recording read it), and the newest APS frame is kept by reference;
- a sender thread (nice +10) sends that APS frame (at most one per display period) and the camera's counters
  over a pipe.

View process (spawned; its ring reader, display and detector threads at nice +10 like the sender): reads the
ring, rebuilds the chunks and feeds them to a :class:`~davis_rig.viewer.live.LiveView` (frames, RVT), served by
:class:`~davis_rig.viewer.server.ViewerServer`.
When it falls behind, the ring is overwritten: it skips to the newest events (display data lost, counted).
"""

from __future__ import annotations

import multiprocessing
import threading
import time
from dataclasses import dataclass
from multiprocessing import shared_memory
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from davis_rig.errors import ConfigError, DavisRigError, MissingDependencyError, ModelFormatError
from davis_rig.types import EVENT_DTYPE
from davis_rig.viewer.live import lower_priority

__all__ = ["EventRing", "LiveViewProcess", "MARK_DTYPE", "RingTap", "retain_freed_memory"]

#: One chunk's mark in the ring: its end (events written after it), last event time, when the recording read it.
MARK_DTYPE = np.dtype([("end", "<i8"), ("t_last_us", "<i8"), ("t_offer_ns", "<i8")])
#: Header of the ring: events written, marks written, event capacity, mark capacity.
_HEADER = 4
#: Page size (bytes) for touching every page of the ring once when it is created or attached.
_PAGE_BYTES = 4096


class EventRing:
    """One producer, one consumer: events and chunk marks in a shared-memory ring (a context manager).

    The producer never waits: it overwrites what the consumer has not read yet. The consumer notices (the
    counters are monotonic) and keeps only what was not overwritten, before and after copying.

    Args:
        name: the shared memory block's name (``None``: create a new block; the creator unlinks it on close).
        capacity: events the ring holds (when creating).
        mark_capacity: chunk marks the ring holds (when creating).
    """

    def __init__(self, name: str | None = None, capacity: int = 1 << 22, mark_capacity: int = 1 << 14):
        if name is None:
            size = 8 * _HEADER + MARK_DTYPE.itemsize * mark_capacity + EVENT_DTYPE.itemsize * capacity
            self._shm = shared_memory.SharedMemory(create=True, size=size)
            self._owner = True
            # every page allocated now, not by the recording's first lap through the ring (measured: a first lap
            # at 12 M ev/s took the recording thread ~3x as long, one page fault per 4 KiB)
            np.ndarray((self._shm.size,), np.uint8, self._shm.buf)[:] = 0
            header = np.ndarray((_HEADER,), np.int64, self._shm.buf)
            header[:] = (0, 0, capacity, mark_capacity)
        else:
            self._shm = shared_memory.SharedMemory(name=name)
            self._owner = False
            int(np.ndarray((self._shm.size,), np.uint8, self._shm.buf)[::_PAGE_BYTES].sum())  # map every page now
        self._header = np.ndarray((_HEADER,), np.int64, self._shm.buf)
        capacity, mark_capacity = int(self._header[2]), int(self._header[3])
        self._marks = np.ndarray((mark_capacity,), MARK_DTYPE, self._shm.buf, offset=8 * _HEADER)
        # the events as raw bytes: a byte copy is a memcpy, ~10x cheaper than numpy's field-wise structured copy
        self._bytes = np.ndarray((capacity * EVENT_DTYPE.itemsize,), np.uint8, self._shm.buf,
                                 offset=8 * _HEADER + MARK_DTYPE.itemsize * mark_capacity)
        self._capacity = capacity
        self._read_events: int | None = 0  # end of the last chunk read (None: unknown, after lost marks)
        self._read_marks = 0
        self.dropped_chunks = 0  # chunks the consumer lost because the producer overwrote them

    @property
    def name(self) -> str:
        """The shared memory block's name (to attach from the other process)."""
        return self._shm.name

    def write(self, events: np.ndarray, t_offer_s: float) -> None:
        """Producer: append one chunk's events (EVENT_DTYPE [N], N >= 1) read by the recording at ``t_offer_s``."""
        capacity, size = self._capacity, EVENT_DTYPE.itemsize
        written = int(self._header[0])
        if len(events) > capacity:
            events = events[-capacity:]
        n = len(events)
        raw = np.ascontiguousarray(events, EVENT_DTYPE).view(np.uint8)
        pos = written % capacity
        first = min(n, capacity - pos)
        self._bytes[pos * size:(pos + first) * size] = raw[:first * size]
        self._bytes[:(n - first) * size] = raw[first * size:]
        marks = int(self._header[1])
        self._marks[marks % len(self._marks)] = (written + n, int(events["t"][-1]), int(t_offer_s * 1e9))
        self._header[0] = written + n  # events first, then the mark that points at them
        self._header[1] = marks + 1

    def read(self) -> list[tuple[float, np.ndarray]]:
        """Consumer: the chunks written since the last read, ``[(t_offer s, events)]``; a chunk (partly)
        overwritten before it was copied out is left out and counted in :attr:`dropped_chunks`.

        The chunks are copied out in one block and handed out as consecutive views of it, so that a reader can
        take several as one array without copying again (:func:`~davis_rig.viewer.live_windows.join_events`).
        """
        marks_written = int(self._header[1])  # the marks first: every chunk they point at is written
        capacity, mark_capacity = self._capacity, len(self._marks)
        first_mark = max(self._read_marks, marks_written - mark_capacity)
        lost_marks = first_mark - self._read_marks  # overwritten marks: their chunks are lost too
        marks = self._marks[np.arange(first_mark, marks_written) % mark_capacity].copy()
        self._read_marks = marks_written
        if int(self._header[1]) - mark_capacity > first_mark:  # the marks were overwritten while being copied
            self.dropped_chunks += lost_marks + len(marks)
            self._read_events = None
            return []
        if not len(marks):
            self.dropped_chunks += lost_marks
            return []
        ends = marks["end"].tolist()
        # a chunk starts where the one before it ended; unknown after lost marks (that chunk is dropped too)
        begins = [None if lost_marks or self._read_events is None else self._read_events, *ends[:-1]]
        self._read_events = ends[-1]
        oldest = int(self._header[0]) - capacity  # what is still in the ring before copying
        first = next((i for i, begin in enumerate(begins) if begin is not None and begin >= oldest), len(begins))
        out = []
        if first < len(begins):
            block = self._copy(begins[first], ends[-1])
            oldest_intact = int(self._header[0]) - capacity  # re-read after copying: what was overwritten meanwhile
            base = begins[first]
            out = [(t_ns / 1e9, block[begin - base:end - base])
                   for t_ns, begin, end in zip(marks["t_offer_ns"].tolist()[first:], begins[first:], ends[first:])
                   if begin >= oldest_intact]
        self.dropped_chunks += lost_marks + len(begins) - len(out)
        return out

    def _copy(self, begin: int, end: int) -> np.ndarray:
        """A copy of the events written at positions ``begin .. end - 1`` (``end - begin <= capacity``)."""
        size = EVENT_DTYPE.itemsize
        a, b = begin % self._capacity, end % self._capacity
        if a < b or end == begin:
            raw = self._bytes[a * size:b * size].copy()
        else:
            raw = np.concatenate([self._bytes[a * size:], self._bytes[:b * size]])
        return raw.view(EVENT_DTYPE)

    def close(self) -> None:
        """Detach (and unlink, for the creator)."""
        del self._header, self._marks, self._bytes
        self._shm.close()
        if self._owner:
            self._shm.unlink()

    def __enter__(self) -> "EventRing":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


@dataclass(frozen=True)
class _Chunk:
    events: np.ndarray | None = None
    frames: tuple = ()


@dataclass(frozen=True)
class _Frame:
    pixels: np.ndarray
    position_x: int
    position_y: int


def retain_freed_memory(mmap_threshold: int = 32 << 20, trim_threshold: int = 256 << 20) -> bool:
    """Make glibc's malloc serve blocks below ``mmap_threshold`` bytes from its heaps and keep up to
    ``trim_threshold`` bytes of freed heap memory instead of handing it back (the view process's allocator).

    The view allocates arrays of ~0.1–2 MB hundreds of times a second (ring copies, crops, counts). By default
    glibc maps such blocks fresh and unmaps them when freed, so every 4 KiB page of every array costs a page
    fault (measured here: cropping 1 s of 12 M ev/s in 2 ms batches took 0.11 CPU-s, 0.06 with the blocks kept
    in the heap). Kept in the heap, freed blocks are reused.

    Returns:
        Whether the settings were taken (``False`` where the C library has no ``mallopt``: not glibc).
    """
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's <malloc.h>
    return bool(mallopt(m_mmap_threshold, int(mmap_threshold))) and bool(mallopt(m_trim_threshold, int(trim_threshold)))


def _child_main(conn, ring_name: str, options: dict) -> None:
    """The view process: LiveView + web server fed from the ring; answers ``ready``/``error`` on ``conn``."""
    retain_freed_memory()
    from davis_rig.viewer.live import LiveApp, LiveView
    from davis_rig.viewer.server import ViewerServer

    stats = {"value": SimpleNamespace(dropped_transfers=0, view_dropped_chunks=0)}
    try:
        with EventRing(ring_name) as ring:
            view = LiveView(detector=options["detector"], threshold=options["threshold"],
                            threads=options["threads"], fps=options["fps"], stats=lambda: stats["value"])
            server = ViewerServer(LiveApp(view), host=options["host"], port=options["port"],
                                  allow_remote=options["allow_remote"])
            with view:
                try:
                    server.__enter__()
                except OSError as exc:
                    conn.send(("error", "port", f"cannot listen on {options['host']}:{options['port']} "
                                                f"({exc.strerror or exc})"))
                    return
                try:
                    conn.send(("ready", server.url))
                    _serve_ring(conn, ring, view, stats)
                finally:
                    server.__exit__(None, None, None)
    except (DavisRigError, ValueError) as exc:  # the detector cannot be loaded, a bad host
        conn.send(("error", type(exc).__name__, str(exc)))
    finally:
        conn.close()


def _serve_ring(conn, ring: EventRing, view, stats: dict) -> None:
    """Feed the view from the ring (a thread) and take the parent's messages until ``stop`` (or it is gone)."""
    stop = threading.Event()

    def feed():
        lower_priority()
        while not stop.is_set():
            for t_offer, events in ring.read():
                view.tap.offer(_Chunk(events=events), t_offer)
            stop.wait(0.002)

    feeder = threading.Thread(target=feed, name="davis-view-ring", daemon=True)
    feeder.start()
    try:
        while True:
            message = conn.recv()
            if message[0] == "stop":
                return
            if message[0] == "aps":
                view.tap.offer(_Chunk(frames=(_Frame(*message[1:]),)))
            elif message[0] == "stats":
                stats["value"] = SimpleNamespace(dropped_transfers=message[1],
                                                 view_dropped_chunks=message[2] + ring.dropped_chunks)
    except EOFError:
        return  # the recording process is gone
    finally:
        stop.set()
        feeder.join()


class RingTap:
    """The recording loop's side of the live view process: each chunk's events go straight into the ring.

    :meth:`offer` copies the events (a memcpy into shared memory, never waits: the ring overwrites what the view
    has not read) and keeps a reference to the newest APS frame; nothing else runs in the recording's thread.
    """

    def __init__(self, ring: EventRing):
        self._ring = ring
        self.latest_frame = None  # the newest APS frame offered (sent to the view by the sender thread)
        self.offered_chunks = 0
        self.offered_events = 0

    def offer(self, chunk, t_offer_s: float | None = None) -> None:
        """Hand over one decoded chunk (the interface of :class:`~davis_rig.viewer.live.LiveTap`)."""
        events = getattr(chunk, "events", None)
        if events is not None and len(events):
            self._ring.write(events, time.monotonic() if t_offer_s is None else t_offer_s)
            self.offered_events += len(events)
        frames = getattr(chunk, "frames", None)
        if frames:
            self.latest_frame = frames[-1]
        self.offered_chunks += 1


class LiveViewProcess:
    """The live view and its page in a child process, fed from this one (see the module); a context manager.

    Args:
        detector: RVT step ONNX, or ``None`` for no boxes.
        threshold, threads, fps: see :class:`~davis_rig.viewer.live.LiveView`.
        host, port, allow_remote: see :class:`~davis_rig.viewer.server.ViewerServer`.
        stats: called about twice a second for the camera's counters (``dropped_transfers``), or ``None``.
        ring_events: events the shared ring holds (4 Mi = 0.35 s at 12 M ev/s, 52 MiB).
        start_timeout_s: how long the child may take to load the detector and bind the port.

    Attributes:
        tap: a :class:`RingTap` (after entering): hand the recording's chunks to it
            (:class:`~davis_rig.viewer.live.TappedCamera`).
        url: the page's address (after entering).

    Raises (on entering):
        ConfigError: the port cannot be bound (field ``--view-port``).
        ModelFormatError / MissingDependencyError: the detector cannot be loaded.
        DavisRigError: the view process did not start.
    """

    def __init__(self, *, detector: Path | None = None, threshold: float = 0.1, threads: int | None = None,
                 fps: float = 25.0, host: str = "127.0.0.1", port: int = 0, allow_remote: bool = False, stats=None,
                 ring_events: int = 1 << 22, start_timeout_s: float = 120.0):
        self.options = {"detector": None if detector is None else Path(detector), "threshold": float(threshold),
                        "threads": threads, "fps": float(fps), "host": host, "port": int(port),
                        "allow_remote": bool(allow_remote)}
        self.period_s = 1.0 / float(fps)
        self.stats_source = stats
        self.ring_events = int(ring_events)
        self.start_timeout_s = float(start_timeout_s)
        self.tap: RingTap | None = None
        self.url: str | None = None
        self._stop = threading.Event()

    def __enter__(self) -> "LiveViewProcess":
        context = multiprocessing.get_context("spawn")  # no fork of a process with running threads
        self._ring = EventRing(capacity=self.ring_events)
        self._conn, child_conn = context.Pipe()
        self._process = context.Process(target=_child_main, args=(child_conn, self._ring.name, self.options),
                                        name="davis-view-live", daemon=True)
        try:
            self._process.start()
            child_conn.close()
            if not self._conn.poll(self.start_timeout_s):
                raise DavisRigError(f"the live view did not start within {self.start_timeout_s:g} s")
            try:
                message = self._conn.recv()
            except EOFError:
                raise DavisRigError(f"the live view process ended at start (exit {self._process.exitcode})") from None
            if message[0] == "error":
                raise _start_error(message[1], message[2])
            self.url = message[1]
        except BaseException:
            self._close()
            raise
        self.tap = RingTap(self._ring)
        self._sender = threading.Thread(target=self._send, name="davis-view-sender", daemon=True)
        self._sender.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._sender.join()
        self._close()

    def _close(self) -> None:
        try:
            self._conn.send(("stop",))
        except (OSError, ValueError):
            pass  # the child is gone already
        self._process.join(10)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join()
        self._conn.close()
        self._ring.close()

    def _send(self) -> None:
        """Send the newest APS frame (at most one per display period) and the counters over the pipe."""
        lower_priority()
        sent_frame, next_stats = None, 0.0
        while not self._stop.wait(self.period_s):
            frame = self.tap.latest_frame
            try:
                if frame is not None and frame is not sent_frame:
                    self._conn.send(("aps", np.asarray(frame.pixels), int(frame.position_x), int(frame.position_y)))
                    sent_frame = frame
                if time.monotonic() >= next_stats:
                    stats = self.stats_source() if self.stats_source is not None else None
                    self._conn.send(("stats", int(getattr(stats, "dropped_transfers", 0) or 0), 0))
                    next_stats = time.monotonic() + 0.5
            except (OSError, ValueError):
                return  # the view process is gone: the recording goes on without it


def _start_error(kind: str, message: str) -> DavisRigError:
    """The parent's exception for a start failure the child reported."""
    if kind == "port":
        return ConfigError("--view-port", message + "; pick another --view-port (0 = any free port)")
    if kind == "MissingDependencyError":
        return MissingDependencyError(message)
    if kind in ("ModelFormatError", "FormatError"):
        return ModelFormatError(message)
    return DavisRigError(message)
