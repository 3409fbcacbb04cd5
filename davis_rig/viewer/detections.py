"""Where the viewer's RVT boxes come from: scored on the fly (in a background thread) or a ``davis-eval`` report.

Both sources answer per window of the recording's window grid (the grid of ``davis-eval``,
:class:`~davis_rig.viewer.recording.RecordingView`) and per confidence threshold:
``get(k, threshold)`` is float32 ``[K, 7]`` RVT rows ``(x1, y1, x2, y2, obj, class_conf, class_id)`` in crop px
(``[0, 7]``: nothing found) or ``None`` while window ``k`` is not scored yet.

On-the-fly scoring reads the windows front to back, like ``davis-eval``: the same crop, the same stacked
histograms, one RVT step per window with the LSTM states carried from the first window, the same post-processing
at every threshold at once — so its boxes are ``davis-eval``'s (``tests/viewer/test_detections.py`` compares
them with :func:`~davis_rig.evaluation.physical.score_session`).
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from davis_rig.errors import DavisRigError, FormatError
from davis_rig.types import RVT_NMS_IOU

__all__ = ["DetectionWorker", "OnTheFlyDetections", "StoredDetections", "find_stored_detections"]

_NONE = np.zeros((0, 7), np.float32)


class StoredDetections:
    """The detections of one recording from a ``davis-eval --out`` folder.

    Args:
        stored: the :class:`~davis_rig.evaluation.detections.WindowDetections` read from the file.
        source: the file, shown to the user.
        window_end_us: the viewer's window grid, int64 [T], device µs.
        crop_origin_xy: the viewer's crop origin, px.

    Raises:
        FormatError: the file's window grid or crop differs from the viewer's (another recording, another
            ``--crop-origin``, or a ``davis-eval`` run with another window length).
    """

    def __init__(self, stored, source: Path, window_end_us: np.ndarray, crop_origin_xy: tuple[int, int]):
        if not np.array_equal(stored.window_end_us, window_end_us):
            raise FormatError(
                f"{source}: its {len(stored.window_end_us)} windows of {stored.window_us} µs are not the "
                f"{len(window_end_us)} windows of this recording (another recording or window length?)")
        if tuple(stored.crop_origin_xy) != tuple(crop_origin_xy):
            raise FormatError(f"{source}: scored with crop origin {tuple(stored.crop_origin_xy)}, the recording's "
                              f"labels use {tuple(crop_origin_xy)}")
        self._stored = stored
        self.source = Path(source)
        self.thresholds = stored.thresholds

    def scored(self) -> int:
        """Windows with an answer: all of them."""
        return len(self._stored.window_end_us)

    def get(self, k: int, threshold: float) -> np.ndarray | None:
        """Detections of window ``k`` at ``threshold`` (one of :attr:`thresholds`)."""
        rows = self._stored.detections[float(threshold)][k]
        return _NONE if rows is None else rows

    def describe(self) -> dict:
        """JSON-ready description for the page."""
        return {"source": "report", "file": self.source.name, "thresholds": self.thresholds,
                "scored": self.scored(), "error": None}


def find_stored_detections(run: Path, session: Path):
    """The detections file of ``session`` in a ``davis-eval --out`` folder (or the file itself).

    A file is picked when the session it names resolves to the same file as ``session``; else, when exactly one
    file names a session with the same file name (a report made on another machine).

    Args:
        run: the report folder (with ``<name>.detections.npz`` files) or one such file.
        session: the session being viewed.

    Returns:
        ``(WindowDetections, path)``.

    Raises:
        FormatError: no or several matching files, or an unreadable one.
    """
    from davis_rig.evaluation.detections import read_detections

    run = Path(run)
    files = [run] if run.is_file() else sorted(run.glob("*.detections.npz")) if run.is_dir() else []
    if not files:
        raise FormatError(f"{run}: neither a davis-eval --out folder with *.detections.npz files nor such a file")
    stored = [(read_detections(f), f) for f in files]
    if run.is_file():
        return stored[0]
    same = [(s, f) for s, f in stored if _same_file(Path(s.session), session)]
    if len(same) == 1:
        return same[0]
    by_name = [(s, f) for s, f in stored if Path(s.session).name == session.name]
    if not same and len(by_name) == 1:
        return by_name[0]
    found = ", ".join(f"{f.name} ({s.session})" for s, f in stored) or "none"
    raise FormatError(f"{run}: no single detections file for {session} (files: {found})")


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and a.samefile(b)
    except OSError:
        return False


class OnTheFlyDetections:
    """Score a recording's windows in order with an RVT step ONNX, as ``davis-eval`` does (see the module).

    Construction only stores the arguments; :meth:`run` (in a worker thread, see :class:`DetectionWorker`)
    scores, and every other method may be called from any thread meanwhile.

    Args:
        session: the session file.
        runner: a :class:`~davis_rig.models.rvt.ort_runner.RVTOnnxRunner` (shared between recordings is fine).
        window_end_us: the window grid, int64 [T], device µs.
        window_us: window length, µs.
        crop_origin_xy: crop origin, px.
        thresholds: confidence thresholds to keep boxes for.
        nms_threshold: class-wise NMS IoU threshold.
        block_windows: windows read and histogrammed per read.
    """

    def __init__(self, session: Path, runner, window_end_us: np.ndarray, window_us: int,
                 crop_origin_xy: tuple[int, int], thresholds, nms_threshold: float = RVT_NMS_IOU,
                 block_windows: int = 20):
        self.session = Path(session)
        self.runner = runner
        self.window_end_us = np.asarray(window_end_us, np.int64)
        self.window_us = int(window_us)
        self.crop_origin_xy = tuple(int(v) for v in crop_origin_xy)
        self.thresholds = sorted({float(t) for t in thresholds})
        self.nms_threshold = float(nms_threshold)
        self.block_windows = int(block_windows)
        self._results: dict[float, list] = {t: [] for t in self.thresholds}
        self._scored = 0
        self._done = False  # run() returned (all scored, stopped or failed)
        self._changed = threading.Condition()
        self.error: str | None = None

    def scored(self) -> int:
        """Windows scored so far (windows ``0 .. scored() - 1``)."""
        return self._scored

    def get(self, k: int, threshold: float) -> np.ndarray | None:
        """Detections of window ``k`` at ``threshold``, or ``None`` while it is not scored."""
        if k >= self._scored:
            return None
        rows = self._results[float(threshold)][k]
        return _NONE if rows is None else rows

    def wait_scored(self, n: int, timeout_s: float | None = None) -> bool:
        """Wait until ``n`` windows are scored (or scoring ended); returns whether they are."""
        with self._changed:
            self._changed.wait_for(lambda: self._scored >= n or self.error is not None or self._done, timeout_s)
        return self._scored >= n

    def describe(self) -> dict:
        """JSON-ready description for the page."""
        return {"source": "on the fly", "file": self.runner.path.name, "thresholds": self.thresholds,
                "scored": self._scored, "error": self.error}

    def run(self, stop: threading.Event) -> None:
        """Score every window (or until ``stop`` is set); a failure is kept in :attr:`error`, not raised."""
        from davis_rig.events.crop import crop_events
        from davis_rig.events.histogram import stacked_histograms
        from davis_rig.models.rvt.postprocess import postprocess_thresholds
        from davis_rig.session import SessionReader
        from davis_rig.types import DAVIS346_HW, RVT_HW

        ends, states = self.window_end_us, None
        try:
            with SessionReader(self.session) as reader:
                for i0 in range(0, len(ends), self.block_windows):
                    if stop.is_set():
                        return
                    block = ends[i0:i0 + self.block_windows]
                    events = reader.events_between(int(block[0]) - self.window_us, int(block[-1]) + 1)
                    events = crop_events(events, self.crop_origin_xy, frame_hw=RVT_HW, sensor_hw=DAVIS346_HW)
                    hists = stacked_histograms(events, block, window_us=self.window_us, correct_time=True)
                    for hist in hists:
                        if stop.is_set():
                            return
                        decoded, states = self.runner.step(hist[None], states)
                        out = postprocess_thresholds(decoded, self.thresholds, self.nms_threshold)
                        with self._changed:
                            for threshold in self.thresholds:
                                self._results[threshold].append(out[threshold][0])
                            self._scored += 1
                            self._changed.notify_all()
        except DavisRigError as exc:
            self.error = f"scoring stopped at window {self._scored}: {exc}"
        finally:
            with self._changed:
                self._done = True
                self._changed.notify_all()


class DetectionWorker:
    """One background thread that scores the given :class:`OnTheFlyDetections` one after the other.

    Use as a context manager; leaving it stops the scoring (at the next window) and joins the thread.
    """

    def __init__(self, sources):
        self.sources = list(sources)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="davis-view-scoring", daemon=True)

    def _run(self) -> None:
        for source in self.sources:
            if self._stop.is_set():
                return
            source.run(self._stop)

    def __enter__(self) -> "DetectionWorker":
        if self.sources:
            self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
