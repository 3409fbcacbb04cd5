"""Import an AEDAT4 recording (iniVation DV) into a session.h5.

Reading uses iniVation's own ``dv-processing`` (``pip install "davis_rig[aedat4]"``), imported lazily so the
core package does not need it. What maps onto what:

- events -> ``/events`` (timestamp µs, x, y, polarity 0/1);
- frames -> ``/frames``: DV stores 8-bit grey frames; they are widened to the libcaer 16-bit scale as
  ``value << 8`` (16-bit DV frames are kept as they are). DV keeps only the exposure start and its duration,
  so ``t_start_of_frame_us = t_start_exposure_us`` and ``t_end_of_frame_us = t_end_exposure_us``;
- triggers -> ``/specials`` with libcaer special type ids;
- IMU -> ``/imu`` (g, °/s, °C: DV's units already);
- bounding boxes (a ``boundingBoxes`` stream) -> ``/labels``: ``x, y = topLeft``, ``w, h = bottomRight −
  topLeft``, the confidence, and the label text :func:`box_label` writes (``pedestrian``, ``car``,
  ``class_<id>``, with ``#<track id>`` when it is not 0); boxes with another label text are skipped and counted;
- the camera name (``DAVIS346_00000499``) -> ``device_info.serial``; the event resolution -> the layout sizes.

Files written by ``davis-export --to aedat4`` carry stream metadata (:data:`META_ORIGIN_XY` and
:data:`META_SENSOR_WH` on the event stream, :data:`META_LABELS_CROP_ORIGIN_XY` and :data:`META_LABELS_ATTRS` on
the box stream) that put cropped events back on the sensor and the boxes back into the session's crop
coordinates with their provenance. Without it, events keep their pixels and boxes keep theirs (crop origin
``(0, 0)``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from davis_rig import __version__
from davis_rig.errors import FormatError, MissingDependencyError
from davis_rig.protocol import IMU6_DTYPE, SPECIAL_DTYPE, ApsFrame, SpecialType
from davis_rig.session.info import sensor_layout
from davis_rig.session.labels import labels_crop_origin, shift_boxes, write_labels
from davis_rig.session.writer import SessionWriter
from davis_rig.types import BBOX_DTYPE, EVENT_DTYPE, GEN1_CLASSES, make_events

#: First bytes of every AEDAT 4.0 file.
AEDAT4_MAGIC = b"#!AER-DAT4.0\r\n"

#: dv.TriggerType value -> libcaer special type (``davis_rig.protocol.words.SpecialType``).
TRIGGER_TO_SPECIAL = {
    0: SpecialType.TIMESTAMP_RESET,
    1: SpecialType.EXTERNAL_INPUT_RISING_EDGE,
    2: SpecialType.EXTERNAL_INPUT_FALLING_EDGE,
    3: SpecialType.EXTERNAL_INPUT_PULSE,
    4: SpecialType.EXTERNAL_GENERATOR_RISING_EDGE,
    5: SpecialType.EXTERNAL_GENERATOR_FALLING_EDGE,
    6: SpecialType.APS_FRAME_START,
    7: SpecialType.APS_FRAME_END,
    8: SpecialType.APS_EXPOSURE_START,
    9: SpecialType.APS_EXPOSURE_END,
}
#: libcaer special type id -> dv.TriggerType value (the export direction).
SPECIAL_TO_TRIGGER = {special: trigger for trigger, special in TRIGGER_TO_SPECIAL.items()}

#: Name of the bounding-box stream (dv-processing's default).
BOX_STREAM = "boundingBoxes"
#: Stream metadata of exported files (string values): sensor pixel "x y" of the events' (0, 0), the sensor's
#: "width height", the session labels' crop origin "x y", the session's /labels attributes (JSON).
META_ORIGIN_XY = "davis_rig.origin_xy"
META_SENSOR_WH = "davis_rig.sensor_wh"
META_LABELS_CROP_ORIGIN_XY = "davis_rig.labels_crop_origin_xy"
META_LABELS_ATTRS = "davis_rig.labels_attrs"
_CLASS_IDS = {name: class_id for class_id, name in GEN1_CLASSES.items()}



def import_dv():
    """Import ``dv_processing`` or raise :class:`MissingDependencyError` naming the extra to install."""
    try:
        import dv_processing
    except ImportError as exc:
        raise MissingDependencyError(
            'AEDAT4 import needs dv-processing: pip install "davis_rig[aedat4]" (or pip install dv-processing)'
        ) from exc
    return dv_processing


def box_label(class_id: int, track_id: int = 0) -> str:
    """The DV bounding-box label of a Prophesee box: its Gen1 class name (``class_<id>`` for others), then
    ``#<track id>`` when the track id is not 0."""
    name = GEN1_CLASSES.get(int(class_id), f"class_{int(class_id)}")
    return f"{name}#{int(track_id)}" if int(track_id) else name


def parse_box_label(text: str) -> tuple[int, int] | None:
    """``(class_id, track_id)`` of a :func:`box_label` text, or ``None`` for any other text."""
    name, _, track = text.partition("#")
    class_id = _CLASS_IDS.get(name)
    if class_id is None and name.startswith("class_") and name[6:].isdigit():
        class_id = int(name[6:])
    if class_id is None or class_id > 255 or (track and not track.isdigit()):
        return None
    return class_id, int(track or 0)


def _pair(metadata: dict, key: str) -> tuple[int, int] | None:
    if key not in metadata:
        return None
    try:
        a, b = (int(v) for v in metadata[key].split())
    except ValueError:
        raise FormatError(f"AEDAT4 stream metadata {key}={metadata[key]!r} is not two integers") from None
    return a, b


@dataclass(frozen=True)
class Aedat4ImportSummary:
    """What :func:`import_aedat4` wrote.

    Attributes:
        path: the session file; events, frames, specials, imu, labels: items written; labels_skipped: boxes whose
        label text is not one :func:`box_label` writes; camera_name: DV's camera name.
    """

    path: Path
    camera_name: str
    events: int
    frames: int
    specials: int
    imu: int
    labels: int = 0
    labels_skipped: int = 0


@dataclass
class _Chunk:
    events: np.ndarray
    frames: list
    specials: np.ndarray
    imu: np.ndarray | None = None


def _frame(dv_frame, origin_xy: tuple[int, int] = (0, 0)) -> ApsFrame:
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
    return ApsFrame(pixels, int(dv_frame.positionX) + origin_xy[0], int(dv_frame.positionY) + origin_xy[1],
                    t_start, t_start, t_start + exposure_us, t_start + exposure_us)


def _read_boxes(recording) -> tuple[np.ndarray, int]:
    """Every box of the bounding-box stream as BBOX_DTYPE (file pixels) and the number skipped."""
    rows, skipped = [], 0
    while (packet := recording.getNextBoundingBox(BOX_STREAM)) is not None:
        for box in packet.elements:
            parsed = parse_box_label(box.label)
            if parsed is None:
                skipped += 1
                continue
            rows.append((box.timestamp, box.topLeftX, box.topLeftY, box.bottomRightX, box.bottomRightY,
                         box.confidence, *parsed))
    table = np.array(rows, dtype=np.float64).reshape(-1, 8)
    boxes = np.zeros(len(table), BBOX_DTYPE)
    boxes["t"] = np.array([row[0] for row in rows], dtype=np.int64)  # exact: not through float64
    boxes["x"], boxes["y"] = table[:, 1], table[:, 2]
    boxes["w"], boxes["h"] = table[:, 3] - table[:, 1], table[:, 4] - table[:, 2]
    boxes["class_confidence"] = table[:, 5]
    boxes["class_id"], boxes["track_id"] = table[:, 6], table[:, 7]
    return boxes, skipped


def _open_recording(dv, src: Path):
    """Open an AEDAT4 file with dv-processing (``MonoCameraRecording``) after checking its magic.

    Raises:
        FormatError: no such file, not an AEDAT4 file, or dv-processing cannot read it.
    """
    if not src.exists():
        raise FormatError(f"{src}: no such AEDAT4 file")
    with open(src, "rb") as file:
        magic = file.read(len(AEDAT4_MAGIC))
    if magic != AEDAT4_MAGIC:
        raise FormatError(f"{src}: not an AEDAT4 file (starts with {magic!r}, expected {AEDAT4_MAGIC!r})")
    if src.suffix != ".aedat4":
        raise FormatError(f"{src}: dv-processing reads AEDAT4 only from a file named *.aedat4; rename it")
    try:
        return dv.io.MonoCameraRecording(str(src))
    except RuntimeError as exc:
        raise FormatError(f"{src}: not a readable AEDAT4 file ({dv_reason(exc)})") from exc


def dv_reason(exc: RuntimeError) -> str:
    """The reason line of a dv-processing error, without its source location and C++ stack trace.

    dv-processing's text is ``<file>(<line>): <function>\n<Kind>: <reason>\nStacktrace:\n<frames>``.
    """
    lines = str(exc).split("Stacktrace:")[0].strip().splitlines()
    return lines[-1].strip() if lines else type(exc).__name__


def _device_info(recording, src: Path) -> tuple[dict, tuple[int, int]]:
    """The session's device info from the recording's camera name and resolutions, and the events' origin on
    the sensor, px (``(0, 0)`` unless the file is an exported crop: then the layout is the whole sensor's)."""
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
    events_meta = recording.getStreamMetadata("events") if recording.isEventStreamAvailable() else {}
    origin = _pair(events_meta, META_ORIGIN_XY) or (0, 0)
    if (sensor_wh := _pair(events_meta, META_SENSOR_WH)) is not None:
        layout = sensor_layout(*sensor_wh)  # an exported crop: the events and frames go back onto the sensor
    device_info["layout"] = layout
    return device_info, origin


def _write_streams(recording, writer: SessionWriter, origin: tuple[int, int]) -> None:
    """Write the events, frames, triggers (as specials) and IMU samples, one stream after the other.

    Raises:
        RuntimeError: dv-processing found a damaged packet.
    """
    if recording.isEventStreamAvailable():
        while (batch := recording.getNextEventBatch()) is not None:
            raw = batch.numpy()
            if len(raw):
                writer.append_events(make_events(raw["timestamp"], raw["x"] + origin[0],
                                                 raw["y"] + origin[1], raw["polarity"].astype(np.uint8)))
                writer.maybe_flush()
    if recording.isFrameStreamAvailable():
        while (frame := recording.getNextFrame()) is not None:
            writer.append_frame(_frame(frame, origin))
            writer.maybe_flush()  # frames are buffered until a flush: keep at most one interval in RAM
    if recording.isTriggerStreamAvailable():
        specials = []
        while (batch := recording.getNextTriggerBatch()) is not None:
            specials += [(int(tr.timestamp), TRIGGER_TO_SPECIAL.get(int(tr.type), 255)) for tr in batch]
        if specials:
            writer.append(_Chunk(np.zeros(0, EVENT_DTYPE), [], np.array(specials, dtype=SPECIAL_DTYPE)),
                          device_clock=False)
    if recording.isImuStreamAvailable():
        samples = []
        while (batch := recording.getNextImuBatch()) is not None:
            samples += [(int(s.timestamp), s.accelerometerX, s.accelerometerY, s.accelerometerZ, s.gyroscopeX,
                         s.gyroscopeY, s.gyroscopeZ, s.temperature) for s in batch]
        if samples:
            writer.append(_Chunk(np.zeros(0, EVENT_DTYPE), [], np.zeros(0, SPECIAL_DTYPE),
                                 np.array(samples, dtype=IMU6_DTYPE)))


def _write_box_labels(src: Path, dst, boxes: np.ndarray, box_meta, origin: tuple[int, int]) -> None:
    """Store the recording's boxes as the session's labels, moved from the labels' crop onto the events' one.

    Raises:
        FormatError: the labels' attribute metadata is not JSON.
    """
    labels_origin = _pair(box_meta, META_LABELS_CROP_ORIGIN_XY) or (0, 0)
    try:
        attrs = json.loads(box_meta.get(META_LABELS_ATTRS, "{}"))
    except json.JSONDecodeError as exc:
        raise FormatError(f"{src}: malformed {META_LABELS_ATTRS} metadata ({exc})") from exc
    attrs = {"labeler": "davis_rig.session.aedat4", "labeler_version": __version__, "source": src.name,
             **attrs, "imported_from": str(src)}
    if labels_crop_origin(attrs) is None:
        attrs.update(crop_origin_x=labels_origin[0], crop_origin_y=labels_origin[1])
    write_labels(dst, shift_boxes(boxes, origin[0] - labels_origin[0], origin[1] - labels_origin[1]), attrs)


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
    recording = _open_recording(dv, src)
    device_info, origin = _device_info(recording, src)
    config = {"source": "aedat4", "frame_scale": "dv 8-bit value << 8"}
    has_boxes = recording.isStreamAvailable(BOX_STREAM) and recording.isStreamOfBoundingBoxType(BOX_STREAM)
    box_meta = recording.getStreamMetadata(BOX_STREAM) if has_boxes else {}
    with SessionWriter(dst, device_info=device_info, config=config, overwrite=overwrite) as writer:
        try:
            _write_streams(recording, writer, origin)
            boxes, skipped = _read_boxes(recording) if has_boxes else (None, 0)
        except (RuntimeError, FormatError) as exc:  # dv-processing: damaged packets; the writer: garbage times
            reason = dv_reason(exc) if isinstance(exc, RuntimeError) else str(exc).removeprefix(f"{dst}: ")
            raise FormatError(f"{src}: damaged AEDAT4 data after {writer.counts['events']} events ({reason}); "
                              f"{dst} keeps what was read and is marked incomplete") from exc
        counts = writer.counts
    if boxes is not None:
        _write_box_labels(src, dst, boxes, box_meta, origin)
    return Aedat4ImportSummary(path=Path(dst), camera_name=device_info["camera_name"], events=counts["events"],
                               frames=counts["frames"], specials=counts["specials"], imu=counts["imu"],
                               labels=0 if boxes is None else len(boxes), labels_skipped=skipped)
