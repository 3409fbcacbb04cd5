"""Export what the viewer shows as a video: MP4 (OpenCV ``VideoWriter``, codec ``mp4v``) or GIF (Pillow).

Each video frame is one window rendered by :meth:`~davis_rig.viewer.recording.RecordingView.render` (the page's
pixels, with a caption). The file is written beside its destination and moved into place when complete, so a
failed export leaves nothing half-written.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

from davis_rig.errors import FormatError, MissingDependencyError
from davis_rig.viewer.render import LAYERS

__all__ = ["VideoFormat", "export_video"]


class VideoFormat(StrEnum):
    """Videos :func:`export_video` writes, named by their file suffix."""

    MP4 = "mp4"
    GIF = "gif"

    @property
    def suffix(self) -> str:
        """The file suffix, e.g. ``".mp4"``."""
        return f".{self.value}"

    @classmethod
    def of(cls, path) -> "VideoFormat | None":
        """The format of a file name by its suffix (any case), ``None`` for another suffix."""
        suffix = Path(path).suffix.lower()
        return next((fmt for fmt in cls if fmt.suffix == suffix), None)

    @classmethod
    def expected(cls) -> str:
        """``".mp4 or .gif"``: the suffixes for an error message."""
        return " or ".join(fmt.suffix for fmt in cls)


def _frames(view, start: int, stop: int, layers, threshold, scoring_timeout_s: float | None):
    """Yield the rendered windows ``start .. stop - 1`` (waiting for on-the-fly scoring to reach each one)."""
    for k in range(start, stop):
        source = view.detections
        if threshold is not None and source is not None and hasattr(source, "wait_scored"):
            source.wait_scored(k + 1, scoring_timeout_s)
        yield view.render(k, layers=layers, threshold=threshold, caption=True)


def export_video(view, path, *, start: int = 0, stop: int | None = None, fps: float | None = None, layers=LAYERS,
                 threshold: float | None = None, scoring_timeout_s: float | None = None, overwrite: bool = False) -> Path:
    """Write windows ``start .. stop - 1`` of a recording as an MP4 or a GIF (by ``path``'s suffix).

    Args:
        view: a :class:`~davis_rig.viewer.recording.RecordingView`.
        path: ``.mp4`` or ``.gif`` to create.
        start, stop: window range (``stop=None``: to the end).
        fps: frames per second of the video (``None``: real time, one frame per window: ``1e6 / view.window_us``).
        layers: overlays to draw.
        threshold: which threshold's boxes to draw (``None``: none); with on-the-fly scoring the export waits
            for each window to be scored (up to ``scoring_timeout_s`` per window, ``None`` = no limit).
        overwrite: replace ``path`` if it exists (else refuse before rendering anything).

    Returns:
        ``path``.

    Raises:
        ValueError: unknown suffix, empty range, or ``fps <= 0``.
        MissingDependencyError: a GIF without Pillow (the ``report`` extra).
        FormatError: ``path`` exists (without ``overwrite``) or is a folder, its folder does not exist, or
            OpenCV cannot write the MP4 (no mp4v encoder in this OpenCV build).
    """
    path = Path(path)
    video_format = VideoFormat.of(path)
    if video_format is None:
        raise ValueError(f"{path}: expected a {VideoFormat.expected()} file")
    stop = view.num_windows if stop is None else int(stop)
    if not 0 <= int(start) < stop <= view.num_windows:
        raise ValueError(f"window range [{start}, {stop}) is empty or outside 0..{view.num_windows}")
    fps = 1e6 / view.window_us if fps is None else fps
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    from davis_rig.session.staging import staged_outputs

    frames = _frames(view, int(start), stop, layers, threshold, scoring_timeout_s)
    with staged_outputs(path, overwrite=overwrite) as (tmp,):  # created by the writer: the user's umask applies
        if video_format == VideoFormat.MP4:
            _write_mp4(frames, tmp, fps)
        else:
            _write_gif(frames, tmp, fps)
    return path


def _write_mp4(frames, path: Path, fps: float) -> None:
    import cv2

    writer = None
    try:
        for rgb in frames:
            if writer is None:
                height, width = rgb.shape[:2]
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (width, height))
                if not writer.isOpened():
                    raise FormatError(f"{path}: OpenCV cannot write MP4 (mp4v) here; export a .gif instead")
            writer.write(rgb[..., ::-1].copy())
    finally:
        if writer is not None:
            writer.release()


def _write_gif(frames, path: Path, fps: float) -> None:
    try:
        from PIL import Image
    except ImportError as exc:
        raise MissingDependencyError('a GIF export needs Pillow: pip install "davis_rig[report]"') from exc
    images = (Image.fromarray(rgb) for rgb in frames)  # one at a time: Pillow keeps only its palette frames
    next(images).save(path, format="GIF", save_all=True, append_images=images, duration=round(1000 / fps), loop=0)
