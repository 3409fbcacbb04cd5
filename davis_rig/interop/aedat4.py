"""Export a session as AEDAT4 (iniVation DV) through ``dv-processing`` (the import is :mod:`davis_rig.session.aedat4`).

Every stream travels, with the device clock (µs) as DV timestamps:

- events -> the ``events`` stream, in packets of :data:`DV_PACKET_EVENTS` (dv-processing builds them from
  Python objects: under 1 M events/s, where the other exports run at several M events/s);
- APS frames -> the ``frames`` stream as 16-bit grey images (libcaer scale, nothing rounded), each its read-out
  region at its position; DV keeps the exposure start and duration only (start/end of frame are not kept). With
  a crop, each frame is the 304x240 window (zeros outside the read-out region), at position (0, 0);
- special events -> ``triggers`` (DV's trigger types; types DV has no name for are counted as not exported);
- IMU samples -> ``imu``; labels -> a ``boundingBoxes`` stream (``topLeft = (x, y)``, ``bottomRight = (x + w,
  y + h)`` in the events' pixels, the confidence, and :func:`~davis_rig.session.aedat4.box_label` text). DV keeps
  the corners, so ``w, h`` come back from ``bottomRight − topLeft`` rounded to float32 (≤ 6.1e-5 px below 512 px).

Stream metadata (:mod:`davis_rig.session.aedat4`'s ``META_*`` keys) records the crop and the labels' origin and
provenance, so the import restores the session's geometry.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from davis_rig.interop.source import ExportSource
from davis_rig.interop.summary import ExportSummary
from davis_rig.session.aedat4 import (BOX_STREAM, META_LABELS_ATTRS, META_LABELS_CROP_ORIGIN_XY, META_ORIGIN_XY,
                                      META_SENSOR_WH, SPECIAL_TO_TRIGGER, box_label, import_dv)
from davis_rig.session.staging import staged_outputs

__all__ = ["export_aedat4"]

#: Events per DV packet: dv-processing takes Python objects, so this bounds the temporary objects (~100 B each).
DV_PACKET_EVENTS = 1 << 16


def _camera_name(info: dict) -> str:
    if info.get("camera_name"):
        return str(info["camera_name"])
    return f"DAVIS346_{info.get('serial') or '00000000'}"


def _write_frames(dv, writer, source: ExportSource) -> int:
    frames = source.reader.frames
    starts = frames.times_us("t_start_exposure_us")
    exposures = frames.times_us("t_end_exposure_us") - starts
    x0, y0 = source.origin_xy
    height, width = source.frame_hw
    for i in range(len(frames)):
        if source.crop:
            image, position = np.ascontiguousarray(frames.data[i, y0:y0 + height, x0:x0 + width]), (0, 0)
        else:
            frame = frames[i]
            image, position = np.ascontiguousarray(frame.pixels), (frame.position_x, frame.position_y)
        writer.writeFrame(dv.Frame(int(starts[i]), int(exposures[i]), position[0], position[1], image,
                                   dv.FrameSource.SENSOR))
    return len(frames)


def _write_boxes(dv, writer, boxes: np.ndarray) -> None:
    x2 = boxes["x"].astype(np.float64) + boxes["w"]
    y2 = boxes["y"].astype(np.float64) + boxes["h"]
    for box, right, bottom in zip(boxes, x2.tolist(), y2.tolist()):
        writer.writeBoundingBox(dv.BoundingBox(int(box["t"]), float(box["x"]), float(box["y"]), right, bottom,
                                               float(box["class_confidence"]),
                                               box_label(box["class_id"], box["track_id"])))


def export_aedat4(source: ExportSource, out: str | os.PathLike, *, overwrite: bool = False,
                  progress: Callable[[int, int], None] | None = None) -> ExportSummary:
    """Write ``out`` (``.aedat4``) with every stream of the session (module docstring).

    Args:
        source: an open :class:`~davis_rig.interop.source.ExportSource` (its crop decides the pixels).
        out: the ``.aedat4`` file.
        overwrite: replace an existing file.
        progress: called with (session events read so far, session events) after each piece.

    Returns:
        An :class:`~davis_rig.interop.summary.ExportSummary`.

    Raises:
        MissingDependencyError: dv-processing is not installed (``pip install "davis_rig[aedat4]"``).
        FormatError: ``out`` exists (without ``overwrite``) or its folder does not exist.
    """
    dv = import_dv()
    out = Path(out)
    reader = source.reader
    height, width = source.frame_hw
    labels = source.labels()
    specials = reader.specials()
    triggers = specials[np.isin(specials["type"], list(SPECIAL_TO_TRIGGER))]
    imu = reader.imu()
    config = dv.io.MonoCameraWriter.Config(_camera_name(reader.device_info))
    config.addEventStream((width, height))
    config.addStreamMetadata("events", (META_ORIGIN_XY, "%d %d" % source.origin_xy))
    config.addStreamMetadata("events", (META_SENSOR_WH, f"{source.sensor_hw[1]} {source.sensor_hw[0]}"))
    if len(reader.frames):
        config.addFrameStream((width, height))
    if len(triggers):
        config.addTriggerStream()
    if imu is not None and len(imu):
        config.addImuStream()
    if labels is not None:
        config.addBoundingBoxStream(BOX_STREAM)
        config.addStreamMetadata(BOX_STREAM, (META_LABELS_CROP_ORIGIN_XY, "%d %d" % source.labels_origin_xy))
        config.addStreamMetadata(BOX_STREAM, (META_LABELS_ATTRS, json.dumps(source.labels_attrs, default=str)))
    events = read = 0
    with staged_outputs(out, overwrite=overwrite) as (tmp,):
        writer = dv.io.MonoCameraWriter(str(tmp), config)
        try:
            for chunk, n_read in source.event_chunks():
                for start in range(0, len(chunk), DV_PACKET_EVENTS):
                    part = chunk[start:start + DV_PACKET_EVENTS]
                    vector = dv.EventPacket.EventVector(map(dv.Event, part["t"].tolist(), part["x"].tolist(),
                                                            part["y"].tolist(), (part["p"] > 0).tolist()))
                    writer.writeEventPacket(dv.EventPacket(vector))
                events += len(chunk)
                read += n_read
                if progress is not None:
                    progress(read, source.num_events)
            frames = _write_frames(dv, writer, source) if len(reader.frames) else 0
            for t, kind in zip(triggers["t"].tolist(), triggers["type"].tolist()):
                writer.writeTrigger(dv.Trigger(t, dv.TriggerType(SPECIAL_TO_TRIGGER[kind])))
            if imu is not None:
                for row in imu:
                    writer.writeImu(dv.IMU(int(row["t"]), float(row["temperature_c"]), float(row["accel_x_g"]),
                                           float(row["accel_y_g"]), float(row["accel_z_g"]), float(row["gyro_x_dps"]),
                                           float(row["gyro_y_dps"]), float(row["gyro_z_dps"]), 0.0, 0.0, 0.0))
            if labels is not None:
                _write_boxes(dv, writer, labels)
        finally:
            del writer  # dv-processing finishes and closes the file in its destructor
    notes = ["times are device µs, as in the session; frames are 16-bit (libcaer scale)"]
    if len(specials) > len(triggers):
        notes.append(f"{len(specials) - len(triggers)} special events of types DV has no trigger for are left out")
    return ExportSummary(
        format="aedat4", session=str(source.path), outputs=(str(out),), events=events, events_read=read,
        labels=0 if labels is None else len(labels), labels_left_out=0, frame_hw=tuple(source.frame_hw),
        origin_xy=tuple(source.origin_xy), t_offset_us=0,
        not_exported={"specials": len(specials) - len(triggers)} if len(specials) > len(triggers) else {},
        notes=tuple(notes), extra={"frames": frames, "triggers": len(triggers),
                                   "imu": 0 if imu is None else len(imu)})
