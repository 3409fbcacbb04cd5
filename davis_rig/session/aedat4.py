"""Import an AEDAT4 recording (iniVation DV) into a session.h5.

Reading uses iniVation's own ``dv-processing`` (``pip install "davis_rig[aedat4]"``), imported lazily so the
core package does not need it. What maps onto what:

- events -> ``/events`` (timestamp µs, x, y, polarity 0/1);
- frames -> ``/frames``: DV stores 8-bit grey frames; they are widened to the libcaer 16-bit scale as
  ``value << 8`` (16-bit DV frames are kept as they are). DV keeps only the exposure start and its duration,
  so ``t_start_of_frame_us = t_start_exposure_us`` and ``t_end_of_frame_us = t_end_exposure_us``;
- triggers -> ``/specials`` with libcaer special type ids;
- IMU -> ``/imu`` (g, °/s, °C: DV's units already);
- the camera name (``DAVIS346_00000499``) -> ``device_info.serial``; the event resolution -> the layout sizes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from davis_rig.errors import FormatError, MissingDependencyError
from davis_rig.session.writer import SessionWriter
from davis_rig.types import EVENT_DTYPE, make_events

#: First bytes of every AEDAT 4.0 file.
AEDAT4_MAGIC = b"#!AER-DAT4.0\r\n"

#: dv.TriggerType value -> libcaer special type id (``davis_rig.protocol.words.SpecialType``).
TRIGGER_TO_SPECIAL = {0: 1, 1: 2, 2: 3, 3: 4, 4: 12, 5: 13, 6: 14, 7: 15, 8: 16, 9: 17}

_SPECIAL_DTYPE = np.dtype([("t", "<i8"), ("type", "u1")])
_IMU_DTYPE = np.dtype([("t", "<i8"), ("accel_x_g", "<f4"), ("accel_y_g", "<f4"), ("accel_z_g", "<f4"),
                       ("gyro_x_dps", "<f4"), ("gyro_y_dps", "<f4"), ("gyro_z_dps", "<f4"),
                       ("temperature_c", "<f4")])


def import_dv():
    """Import ``dv_processing`` or raise :class:`MissingDependencyError` naming the extra to install."""
    try:
        import dv_processing
    except ImportError as exc:
        raise MissingDependencyError(
            'AEDAT4 import needs dv-processing: pip install "davis_rig[aedat4]" (or pip install dv-processing)'
        ) from exc
    return dv_processing


@dataclass(frozen=True)
class Aedat4ImportSummary:
    """What :func:`import_aedat4` wrote.

    Attributes:
        path: the session file; events, frames, specials, imu: items written; camera_name: DV's camera name.
    """

    path: Path
    camera_name: str
    events: int
    frames: int
    specials: int
    imu: int


@dataclass
class _Chunk:
    events: np.ndarray
    frames: list
    specials: np.ndarray
    imu: np.ndarray | None = None


def _frame(dv_frame):
    from davis_rig.session.reader import StoredFrame

    image = np.asarray(dv_frame.image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2:
        raise FormatError(f"AEDAT4 frame at t={dv_frame.timestamp}: expected a grey image, got shape {image.shape}")
    if image.dtype == np.uint8:
        pixels = image.astype(np.uint16) << 8
    elif image.dtype == np.uint16:
        pixels = image.copy()
    else:
        raise FormatError(f"AEDAT4 frame at t={dv_frame.timestamp}: unsupported pixel type {image.dtype}")
    t_start = int(dv_frame.timestamp)
    exposure_us = int(dv_frame.exposure.total_seconds() * 1e6 + 0.5)
    return StoredFrame(pixels, int(dv_frame.positionX), int(dv_frame.positionY), t_start, t_start,
                       t_start + exposure_us, t_start + exposure_us)


def import_aedat4(src: str | os.PathLike, dst: str | os.PathLike, *, overwrite: bool = False) -> Aedat4ImportSummary:
    """Convert an AEDAT4 file into a session.h5: one stream after the other (events, frames, triggers, IMU),
    each in its own time order, batch by batch.

    Args:
        src: the ``.aedat4`` file.
        dst: the session.h5 to create.
        overwrite: replace an existing ``dst``.

    Returns:
        An :class:`Aedat4ImportSummary`.

    Raises:
        MissingDependencyError: dv-processing is not installed.
        FormatError: ``src`` is not a readable AEDAT4 file or a frame has an unsupported pixel type.
        SessionError: ``dst`` exists (without ``overwrite``) or cannot be written.
    """
    dv = import_dv()
    src = Path(src)
    if not src.exists():
        raise FormatError(f"{src}: no such AEDAT4 file")
    with open(src, "rb") as file:
        magic = file.read(len(AEDAT4_MAGIC))
    if magic != AEDAT4_MAGIC:
        raise FormatError(f"{src}: not an AEDAT4 file (starts with {magic!r}, expected {AEDAT4_MAGIC!r})")
    try:
        recording = dv.io.MonoCameraRecording(str(src))
    except RuntimeError as exc:
        raise FormatError(f"{src}: not a readable AEDAT4 file ({exc})") from exc
    camera_name = recording.getCameraName()
    device_info: dict = {"serial": camera_name.rsplit("_", 1)[-1] if "_" in camera_name else camera_name,
                         "camera_name": camera_name, "imported_from": str(src)}
    layout: dict = {}
    if recording.isEventStreamAvailable():
        width, height = recording.getEventResolution()
        layout.update(dvs_size_columns=int(width), dvs_size_rows=int(height), dvs_width=int(width),
                      dvs_height=int(height))
    if recording.isFrameStreamAvailable():
        width, height = recording.getFrameResolution()
        layout.update(aps_size_columns=int(width), aps_size_rows=int(height), aps_width=int(width),
                      aps_height=int(height))
    device_info["layout"] = layout
    config = {"source": "aedat4", "frame_scale": "dv 8-bit value << 8"}

    with SessionWriter(dst, device_info=device_info, config=config, overwrite=overwrite) as writer:
        try:
            if recording.isEventStreamAvailable():
                while (batch := recording.getNextEventBatch()) is not None:
                    raw = batch.numpy()
                    if len(raw):
                        writer.append_events(make_events(raw["timestamp"], raw["x"], raw["y"],
                                                         raw["polarity"].astype(np.uint8)))
                        writer.maybe_flush()
            if recording.isFrameStreamAvailable():
                while (frame := recording.getNextFrame()) is not None:
                    writer.append_frame(_frame(frame))
                    writer.maybe_flush()  # frames are buffered until a flush: keep at most one interval in RAM
            if recording.isTriggerStreamAvailable():
                specials = []
                while (batch := recording.getNextTriggerBatch()) is not None:
                    specials += [(int(tr.timestamp), TRIGGER_TO_SPECIAL.get(int(tr.type), 255)) for tr in batch]
                if specials:
                    writer.append(_Chunk(np.zeros(0, EVENT_DTYPE), [], np.array(specials, dtype=_SPECIAL_DTYPE)),
                                  device_clock=False)
            if recording.isImuStreamAvailable():
                samples = []
                while (batch := recording.getNextImuBatch()) is not None:
                    samples += [(int(s.timestamp), s.accelerometerX, s.accelerometerY, s.accelerometerZ, s.gyroscopeX,
                                 s.gyroscopeY, s.gyroscopeZ, s.temperature) for s in batch]
                if samples:
                    writer.append(_Chunk(np.zeros(0, EVENT_DTYPE), [], np.zeros(0, _SPECIAL_DTYPE),
                                         np.array(samples, dtype=_IMU_DTYPE)))
        except RuntimeError as exc:  # dv-processing reports damaged packets as RuntimeError
            raise FormatError(f"{src}: damaged AEDAT4 data after {writer.counts['events']} events ({exc}); "
                              f"{dst} keeps what was read and is marked incomplete") from exc
        counts = writer.counts
    return Aedat4ImportSummary(path=Path(dst), camera_name=camera_name, events=counts["events"],
                               frames=counts["frames"], specials=counts["specials"], imu=counts["imu"])

