"""The session viewer's API: recordings by index, one rendered window per request, misses, exports.

Routes (all GET, below ``/api/``; ``i`` is the recording's index in the command line, ``k`` a window index):

- ``info``: ``{"mode": "sessions", "sessions": [summary of each recording]}``;
- ``sessions/i``: the summary of recording ``i`` (windows, labels, detection source and scoring progress);
- ``sessions/i/frame?k=&layers=&threshold=&fmt=png|jpg``: window ``k`` rendered (event and APS panels);
- ``sessions/i/misses?threshold=&mode=paper|strict``: the missed windows and the attack's successful sequences
  (:mod:`davis_rig.viewer.misses`) among the windows scored so far;
- ``sessions/i/export?start=&stop=&format=gif|mp4&layers=&threshold=&fps=``: windows ``start .. stop - 1``
  as a video download (at most :attr:`SessionsApp.max_export_windows`).
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

from davis_rig.events.histogram import WINDOW_US
from davis_rig.viewer.export import VideoFormat, export_video
from davis_rig.viewer.render import LAYERS, ImageFormat, encode_image
from davis_rig.viewer.server import (RequestError, Response, float_param, int_param, json_response,
                                     layers_param)

__all__ = ["SessionsApp"]

class SessionsApp:
    """Answer the page's requests about the recordings it was started with.

    Args:
        views: :class:`~davis_rig.viewer.recording.RecordingView` objects, addressed by their index.
        settings: :class:`~davis_rig.evaluation.physical.EvalSettings` for the misses (filters, ``seq_len``).
        max_export_windows: longest export the page may ask for, windows (default: 60 s of RVT windows).
    """

    mode = "sessions"

    def __init__(self, views, settings, *, max_export_windows: int = 60 * 1_000_000 // WINDOW_US):
        self.views = list(views)
        self.settings = settings
        self.max_export_windows = int(max_export_windows)

    def info(self) -> dict:
        """What the page asks first: the mode and every recording's summary."""
        return {"mode": self.mode, "sessions": [view.info() for view in self.views]}

    def handle(self, parts: list[str], params: dict) -> Response:
        """Answer ``/api/<parts>?<params>`` (see the module's routes).

        Raises:
            RequestError: unknown route (404) or bad parameter (400).
        """
        if parts == ["info"]:
            return json_response(self.info())
        if len(parts) in (2, 3) and parts[0] == "sessions":
            view = self._view(parts[1])
            if len(parts) == 2:
                return json_response(view.info())
            action = {"frame": self._frame, "misses": self._misses, "export": self._export}.get(parts[2])
            if action is not None:
                return action(view, params)
        raise RequestError(404, "no such API route")

    def _view(self, text: str):
        if not (text.isascii() and text.isdigit() and len(text) <= 6) or int(text) >= len(self.views):
            raise RequestError(404, f"no recording {text[:12]!r}; there are {len(self.views)} (0..{len(self.views) - 1})")
        return self.views[int(text)]

    @staticmethod
    def _threshold(view, params: dict) -> float | None:
        if view.detections is None:
            if params.get("threshold"):
                raise RequestError(400, "threshold: this recording has no detections")
            return None
        thresholds = view.detections.thresholds
        return float_param(params, "threshold", thresholds, default=thresholds[-1])

    def _frame(self, view, params: dict) -> Response:
        k = int_param(params, "k", 0, view.num_windows - 1)
        layers = layers_param(params, LAYERS, LAYERS)
        fmt = (params.get("fmt") or [ImageFormat.PNG.value])[-1]
        if fmt not in tuple(ImageFormat):
            raise RequestError(400, f"fmt: expected {' or '.join(ImageFormat)}, got {fmt[:8]!r}")
        image = view.render(k, layers=layers, threshold=self._threshold(view, params))
        scored = view.detections.scored() if view.detections is not None else 0
        return Response(200, encode_image(image, fmt), "image/png" if fmt == ImageFormat.PNG else "image/jpeg",
                        (("X-Window", str(k)), ("X-Scored", str(scored))))

    def _misses(self, view, params: dict) -> Response:
        from davis_rig.metrics.seqasr import SeqAsrMode
        from davis_rig.viewer.misses import find_misses

        mode = (params.get("mode") or [SeqAsrMode.PAPER.value])[-1]
        if mode not in tuple(SeqAsrMode):
            raise RequestError(400, f"mode: expected {' or '.join(SeqAsrMode)}, got {mode[:8]!r}")
        threshold = self._threshold(view, params)
        if threshold is None:
            raise RequestError(400, "misses need detections (score on the fly or pass --detections)")
        scored = view.detections.scored()
        detections = [view.detections.get(k, threshold) for k in range(scored)]
        misses = find_misses(view.labels, view.window_end_us, detections, view.window_us, view.t0_us,
                             self.settings, mode)
        return json_response(misses.as_dict() | {"threshold": threshold, "mode": mode})

    def _export(self, view, params: dict) -> Response:
        start = int_param(params, "start", 0, view.num_windows - 1)
        stop = int_param(params, "stop", start + 1, view.num_windows)
        if stop - start > self.max_export_windows:
            raise RequestError(400, f"stop: at most {self.max_export_windows} windows per export, asked "
                                    f"{stop - start}")
        fmt = (params.get("format") or [VideoFormat.GIF.value])[-1]
        if fmt not in tuple(VideoFormat):
            raise RequestError(400, f"format: expected {' or '.join(VideoFormat)}, got {fmt[:8]!r}")
        fps = int_param(params, "fps", 1, 100, default=round(1e6 / view.window_us))  # default: real time
        layers = layers_param(params, LAYERS, LAYERS)
        threshold = self._threshold(view, params)

        with tempfile.TemporaryDirectory(prefix="davis-view-") as folder:
            path = export_video(view, Path(folder) / f"export.{fmt}", start=start, stop=stop, fps=fps,
                                layers=layers, threshold=threshold, overwrite=True)
            body = path.read_bytes()
        stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", view.path.stem) or "recording"
        name = f"{stem}_{start}-{stop}.{fmt}"
        return Response(200, body, "image/gif" if fmt == VideoFormat.GIF else "video/mp4",
                        (("Content-Disposition", f'attachment; filename="{name}"'),))
