"""A synthetic scene → a full DAVIS346 recording (session.h5): DVS events, APS frames and ground-truth labels.

It lives in ``training`` (synthetic data), the layer above the capture stack it drives (protocol, usb, device,
session), the events simulator, the scene's APS model and the label writer: the scene package below stays free of
capture imports.

Two paths produce the same file layout (:mod:`davis_rig.session.schema`):

* ``through_usb=False`` (default): events and frames go straight into :class:`~davis_rig.session.SessionWriter`;
* ``through_usb=True``: they are encoded into the DAVIS346 word stream (:class:`~davis_rig.usb.sources.EncodedSource`
  → :class:`~davis_rig.protocol.encoder.StreamEncoder`), served by the virtual camera
  (:class:`~davis_rig.usb.virtual.VirtualDavis346`) through pyusb, read by :class:`~davis_rig.device.camera.Davis346`
  and written by :func:`~davis_rig.session.record_session` — the whole capture path, as with a real camera.

Geometry: the video is either the full sensor (260 × 346) or the RVT crop (240 × 304), which is placed at
``origin_xy`` (default the centred crop, :func:`~davis_rig.events.crop.center_crop_origin`) inside a sensor frame
of constant ``pad_intensity`` (no events outside the crop). Ground-truth boxes (BBOX_DTYPE, in video pixels,
``t`` in µs) are stored as ``/labels/boxes`` in the RVT crop's coordinates, clamped like RVT's labels, with the
same convention as :mod:`davis_rig.labelers.session_labels`.

Time: the video's ``t_us`` are device µs (the USB path starts the device clock at 0, so ``t_us`` must be ≥ 0).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from davis_rig import __version__
from davis_rig.errors import FormatError, SessionError, ShapeError
from davis_rig.events.crop import center_crop_origin
from davis_rig.events.simulator import EventSimulator, SimulatorConfig
from davis_rig.scene.aps import ApsConfig, synthesize_aps_frames
from davis_rig.types import BBOX_DTYPE, DAVIS346_HW, EVENT_DTYPE, RVT_HW

__all__ = [
    "SYNTHETIC_LABELER",
    "SyntheticRecording",
    "embed_in_sensor",
    "labels_to_crop",
    "simulate_recording",
    "write_clip_session",
    "write_synthetic_session",
]

#: ``labeler`` of the ground-truth labels (and ``generator`` of the settings) this module writes: its name.
SYNTHETIC_LABELER = __name__
#: Video frames simulated per call (bounds the memory of the float64 simulator state and output).
_SIM_CHUNK_FRAMES = 64


@dataclass(frozen=True)
class SyntheticRecording:
    """What :func:`write_synthetic_session` wrote.

    Attributes:
        path: the session file.
        events: DVS events written.
        frames: APS frames written.
        labels: label boxes written.
        through_usb: whether the data went through the encoder and the virtual camera.
        t_first_us, t_last_us: time span of the video, device µs.
    """

    path: Path
    events: int
    frames: int
    labels: int
    through_usb: bool
    t_first_us: int
    t_last_us: int


def embed_in_sensor(
    video,
    *,
    sensor_hw: tuple[int, int] = DAVIS346_HW,
    origin_xy: tuple[int, int] | None = None,
    pad_intensity: float = 0.25,
):
    """Place a crop-sized video inside a sensor-sized one (constant padding), or pass a sensor-sized video through.

    Args:
        video: float array/tensor [T, H, W] (torch tensors are detached and moved to CPU numpy).
        sensor_hw: sensor (height, width), px.
        origin_xy: top-left of the video on the sensor, px (default: centred).
        pad_intensity: linear intensity outside the video.

    Returns:
        ``(sensor_video float32 [T, *sensor_hw], origin_xy)``.

    Raises:
        ShapeError: the video is not [T, H, W] or does not fit the sensor.
    """
    if hasattr(video, "detach"):
        video = video.detach().cpu().numpy()
    video = np.asarray(video)
    if video.ndim != 3:
        raise ShapeError(f"video: expected [T, H, W], got shape {video.shape}")
    height, width = video.shape[1:]
    if (height, width) == tuple(sensor_hw):
        return video.astype(np.float32, copy=False), (0, 0)
    if origin_xy is None:
        origin_xy = center_crop_origin(sensor_hw, (height, width))
    x0, y0 = (int(v) for v in origin_xy)
    if x0 < 0 or y0 < 0 or x0 + width > sensor_hw[1] or y0 + height > sensor_hw[0]:
        raise ShapeError(f"video of (H, W) = {(height, width)} at {(x0, y0)} does not fit the sensor {sensor_hw}")
    out = np.full((video.shape[0], *sensor_hw), pad_intensity, dtype=np.float32)
    out[:, y0:y0 + height, x0:x0 + width] = video
    return out, (x0, y0)


def labels_to_crop(
    labels: np.ndarray,
    video_origin_xy: tuple[int, int],
    *,
    sensor_hw: tuple[int, int] = DAVIS346_HW,
    crop_hw: tuple[int, int] = RVT_HW,
    crop_origin_xy: tuple[int, int] | None = None,
) -> np.ndarray:
    """Map labels given in video pixels to the RVT crop, clamped like RVT (boxes without area dropped).

    Args:
        labels: BBOX_DTYPE [B], box ``x, y, w, h`` in video pixels, ``t`` µs.
        video_origin_xy: where the video's top-left lies on the sensor, px.
        sensor_hw: sensor (height, width), px.
        crop_hw: RVT crop (height, width), px.
        crop_origin_xy: crop top-left on the sensor (default: centred).

    Returns:
        BBOX_DTYPE [B'] in crop pixels, sorted by ``t`` (stable).

    Raises:
        FormatError: ``labels`` is not a BBOX_DTYPE array.
    """
    from davis_rig.labelers.session_labels import crop_boxes

    labels = np.asarray(labels)
    if labels.dtype != BBOX_DTYPE:
        raise FormatError(f"labels: expected BBOX_DTYPE, got {labels.dtype}")
    if crop_origin_xy is None:
        crop_origin_xy = center_crop_origin(sensor_hw, crop_hw)
    xyxy = np.stack([labels["x"], labels["y"], labels["x"] + labels["w"], labels["y"] + labels["h"]], axis=1)
    xyxy = xyxy.astype(np.float64) + np.array([video_origin_xy[0], video_origin_xy[1]] * 2, dtype=np.float64)
    boxes, kept = crop_boxes(xyxy, crop_origin_xy, crop_hw)
    out = labels[kept].copy()
    out["x"], out["y"] = boxes[:, 0], boxes[:, 1]
    out["w"], out["h"] = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    return out[np.argsort(out["t"], kind="stable")]


def simulate_recording(
    video,
    t_us,
    *,
    simulator: SimulatorConfig | None = None,
    aps: ApsConfig | None = None,
    device=None,
) -> tuple[np.ndarray, list]:
    """Events and APS frames of a sensor-sized video.

    Args:
        video: linear intensity, float [T, H, W] (sensor size), numpy or torch.
        t_us: frame times, integer µs [T], strictly increasing.
        simulator: event simulator settings (default: ideal sensor, θ = 0.2).
        aps: APS settings (default: 25 fps, 4 ms exposure).
        device: torch device of the event simulation.

    Returns:
        ``(events EVENT_DTYPE [N] sorted by t, frames list[ApsFrame])``.
    """
    if hasattr(video, "detach"):
        video = video.detach().cpu().numpy()
    video = np.asarray(video)
    t = np.asarray(t_us).astype(np.int64)
    sim = EventSimulator(video.shape[1], video.shape[2], simulator or SimulatorConfig(), device=device)
    parts = [sim.feed(video[a:a + _SIM_CHUNK_FRAMES], t[a:a + _SIM_CHUNK_FRAMES])
             for a in range(0, video.shape[0], _SIM_CHUNK_FRAMES)]
    events = np.concatenate(parts) if parts else np.zeros(0, EVENT_DTYPE)
    frames = synthesize_aps_frames(video, t, aps or ApsConfig())
    return events, frames


def _config_dict(simulator: SimulatorConfig, aps: ApsConfig, origin_xy, pad_intensity: float) -> dict:
    return {
        "exposure_us": aps.exposure_us,
        "frame_interval_us": aps.frame_interval_us,
        "synthetic": {
            "generator": SYNTHETIC_LABELER,
            "simulator": dataclasses.asdict(simulator),
            "aps": dataclasses.asdict(aps),
            "video_origin_xy": list(origin_xy),
            "pad_intensity": pad_intensity,
        },
    }


def _record_through_usb(path: Path, events, frames, config: dict, overwrite: bool, timeout_s: float) -> None:
    from davis_rig.device.camera import Davis346
    from davis_rig.protocol.layout import SensorLayout
    from davis_rig.session.record import record_session
    from davis_rig.usb.sources import EncodedSource
    from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

    source = EncodedSource(events, frames, layout=SensorLayout.davis346(), paced=False)
    device = VirtualDavis346(serial="SYNTH001", source=source)
    stop = threading.Event()
    # Unpaced, the virtual camera serves the scene as fast as pyusb reads it: give the reader a queue that holds
    # every transfer, so a slow decoder/writer never makes it drop one.
    queue_transfers = 2 * len(source) + 64

    with Davis346.open(backend=VirtualDavis346Backend(device), queue_transfers=queue_transfers) as camera:
        def served_and_read() -> bool:
            stats = camera.stats
            return (len(source) == 0 and getattr(device, "_pending", None) is None
                    and stats.bytes + stats.dropped_bytes >= device.bytes_served)

        def watch() -> None:
            deadline = time.monotonic() + timeout_s
            while not stop.is_set() and time.monotonic() < deadline:
                if served_and_read():
                    stop.wait(0.2)  # let the reader hand the last transfers to the decoder queue
                    break
                stop.wait(0.02)
            stop.set()

        watcher = threading.Thread(target=watch, name="synthetic-recording-end", daemon=True)
        watcher.start()
        try:
            record_session(camera, path, overwrite=overwrite, journal=False, stop_event=stop)
        finally:
            stop.set()
            watcher.join()
        if not served_and_read():
            raise SessionError(f"{path}: the virtual camera did not deliver the whole scene within {timeout_s} s")
        dropped = camera.stats.dropped_transfers
        if dropped:
            raise SessionError(f"{path}: {dropped} USB transfers were dropped on the way (the file is incomplete)")
    import h5py

    with h5py.File(path, "r+", locking=False) as f:  # record_session stores the camera settings; add ours
        import json

        stored = json.loads(f.attrs.get("config", "{}"))
        stored.update(config)
        f.attrs["config"] = json.dumps(stored)


def _checked_times(t_us, num_frames: int) -> np.ndarray:
    """The frame times as an integer array [T] (µs); ShapeError / FormatError unless [num_frames] and ≥ 0."""
    t = np.asarray(t_us.detach().cpu().numpy() if hasattr(t_us, "detach") else t_us)
    if t.shape != (num_frames,):
        raise ShapeError(f"t_us: expected shape ({num_frames},), got {t.shape}")
    if not np.issubdtype(t.dtype, np.integer) or (t.size and int(t.min()) < 0):
        raise FormatError(f"t_us: expected non-negative integer µs, got dtype {t.dtype}")
    return t


def _write_directly(path: Path, events: np.ndarray, frames: list, config: dict, overwrite: bool) -> None:
    """Write events and frames straight into a session file (no encoder, no camera)."""
    from davis_rig.protocol.layout import SensorLayout
    from davis_rig.session.writer import SessionWriter

    info = {"serial": "SYNTH001", "synthetic": True, "layout": SensorLayout.davis346()}
    with SessionWriter(path, device_info=info, config=config, overwrite=overwrite) as writer:
        for start in range(0, len(events), 1 << 20):
            writer.append_events(events[start:start + (1 << 20)])
        for frame in frames:
            writer.append_frame(frame)
        writer.set_stats({"stopped_by": "end", "synthetic": {"events": len(events), "frames": len(frames)}})


def _write_ground_truth(path: Path, crop_labels: np.ndarray) -> None:
    """Store the ground-truth boxes (BBOX_DTYPE, RVT crop coordinates) as the session's labels."""
    from davis_rig.labelers.session_labels import write_labels

    write_labels(path, crop_labels, {
        "labeler": SYNTHETIC_LABELER,
        "labeler_version": __version__,
        "created_utc": _dt.datetime.now(tz=_dt.timezone.utc).isoformat(),
        "source": "ground truth of the rendered scene (visible-person boxes), RVT crop coordinates",
        "crop_origin_xy": list(center_crop_origin(DAVIS346_HW, RVT_HW)),
    })


def write_synthetic_session(
    path: str | os.PathLike,
    video,
    t_us,
    *,
    labels: np.ndarray | None = None,
    simulator: SimulatorConfig | None = None,
    aps: ApsConfig | None = None,
    through_usb: bool = False,
    overwrite: bool = False,
    origin_xy: tuple[int, int] | None = None,
    pad_intensity: float = 0.25,
    device=None,
    usb_timeout_s: float = 120.0,
) -> SyntheticRecording:
    """Turn a rendered video (+ ground-truth boxes) into a session.h5 (see the module docstring).

    Args:
        path: session.h5 to create.
        video: linear intensity in [0, 1], float [T, H, W] at sensor (260 × 346) or crop (240 × 304) size.
        t_us: frame times, integer device µs [T], strictly increasing, ≥ 0 (≥ 200 fps for realistic events).
        labels: optional BBOX_DTYPE [B] ground-truth boxes in video pixels (e.g. ``Clip.labels()``).
        simulator: event simulator settings (default: ideal sensor, θ = 0.2).
        aps: APS settings (default: 25 fps, 4 ms exposure, 10-bit ADC with noise).
        through_usb: go through the encoder, the virtual camera and ``record_session`` instead of writing directly.
        overwrite: replace an existing file.
        origin_xy: where a crop-sized video lies on the sensor (default: centred).
        pad_intensity: linear intensity of the sensor outside a crop-sized video.
        device: torch device of the event simulation.
        usb_timeout_s: longest wall time for the USB path, s.

    Returns:
        A :class:`SyntheticRecording`.

    Raises:
        ShapeError / FormatError: bad video, times or labels. SessionError: the file exists (without
        ``overwrite``), cannot be written, or the USB path did not deliver everything.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise SessionError(f"{path}: file exists (pass overwrite=True to replace it)")
    sensor_video, video_origin = embed_in_sensor(video, origin_xy=origin_xy, pad_intensity=pad_intensity)
    t = _checked_times(t_us, sensor_video.shape[0])
    crop_labels = labels_to_crop(labels, video_origin) if labels is not None else None
    simulator = simulator or SimulatorConfig()
    aps = aps or ApsConfig()
    events, frames = simulate_recording(sensor_video, t, simulator=simulator, aps=aps, device=device)
    config = _config_dict(simulator, aps, video_origin, pad_intensity)
    if through_usb:
        _record_through_usb(path, events, frames, config, overwrite, usb_timeout_s)
    else:
        _write_directly(path, events, frames, config, overwrite)
    if crop_labels is not None:
        _write_ground_truth(path, crop_labels)
    return SyntheticRecording(path=path, events=len(events), frames=len(frames),
                              labels=0 if crop_labels is None else len(crop_labels), through_usb=through_usb,
                              t_first_us=int(t[0]) if t.size else 0, t_last_us=int(t[-1]) if t.size else 0)


def write_clip_session(path: str | os.PathLike, clip, **kwargs) -> SyntheticRecording:
    """Write a rendered :class:`~davis_rig.scene.scene.Clip` (video, t_us, visible-person labels) as a session.h5.

    Args:
        path: session.h5 to create.
        clip: anything with ``video`` [T, H, W], ``t_us`` [T] and ``labels()`` (BBOX_DTYPE in video pixels).
        **kwargs: see :func:`write_synthetic_session`.

    Returns:
        A :class:`SyntheticRecording`.
    """
    labels = clip.labels() if hasattr(clip, "labels") else None
    return write_synthetic_session(path, clip.video, clip.t_us, labels=labels, **kwargs)
