"""The HDF5 side of :class:`~davis_rig.session.writer.SessionWriter`: create a session.h5's empty layout (see
:mod:`davis_rig.session.schema`) and append rows to its datasets.

Everything here writes what it is given; the writer decides when (buffering, flushes, free space) and at which
recording times (:mod:`davis_rig.session.clock`).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import enum
import errno
import json
from collections.abc import Mapping

import numpy as np

from davis_rig import __version__
from davis_rig.session import schema

__all__ = ["create_layout", "extend", "frame_hw_from_device_info", "is_disk_full", "to_jsonable", "write_events",
           "write_frames", "write_table"]

#: ``ms_to_idx`` entries computed and written at once (8 MiB): memory stays bounded whatever the time gap.
MS_INDEX_BLOCK = 1 << 20


def to_jsonable(obj):
    """Convert device info / config objects (dataclasses, enums, numpy scalars, mappings) into JSON-able values.

    A string enum becomes its value, any other enum its name.
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        for name in ("dvs_width", "dvs_height", "aps_width", "aps_height"):
            if hasattr(type(obj), name) and isinstance(getattr(type(obj), name), property):
                out.setdefault(name, to_jsonable(getattr(obj, name)))
        return out
    if isinstance(obj, enum.StrEnum):
        return obj.value
    if isinstance(obj, enum.Enum):
        return obj.name
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if hasattr(obj, "_asdict"):
        return to_jsonable(obj._asdict())
    return str(obj)


def frame_hw_from_device_info(info: Mapping | None) -> tuple[int, int]:
    """Return the APS (height, width) in px from a device-info dict (its ``layout``), else DAVIS346's."""
    layout = (info or {}).get("layout") or {}
    height = layout.get("aps_height") or layout.get("aps_size_rows")
    width = layout.get("aps_width") or layout.get("aps_size_columns")
    if height and width:
        return int(height), int(width)
    return schema.DEFAULT_FRAME_HW


def create_layout(f, *, info: dict, config: dict, start_us: int, frame_hw: tuple[int, int],
                  compression: dict) -> None:
    """Write the root attributes (``complete=False``) and the empty groups and datasets of a new session file.

    Args:
        f: the new, empty ``h5py.File`` open for writing.
        info: device info, JSON-able dict.
        config: recording configuration, JSON-able dict (its ``biases`` also go to the ``biases`` attribute).
        start_us: wall-clock start of the recording, µs since the Unix epoch.
        frame_hw: APS (height, width), px.
        compression: ``create_dataset`` keyword arguments (:func:`~davis_rig.session.schema.compression_options`).

    Raises:
        OSError: HDF5 cannot write.
    """
    start_utc = _dt.datetime.fromtimestamp(start_us / 1e6, tz=_dt.timezone.utc).isoformat()
    f.attrs[schema.ATTR_FORMAT] = schema.FORMAT_NAME
    f.attrs[schema.ATTR_FORMAT_VERSION] = schema.FORMAT_VERSION
    f.attrs[schema.ATTR_TOOLKIT_VERSION] = __version__
    f.attrs[schema.ATTR_COMPLETE] = False
    f.attrs[schema.ATTR_START_UTC] = start_utc
    f.attrs[schema.ATTR_START_UNIX_US] = np.int64(start_us)
    f.attrs[schema.ATTR_DEVICE_INFO] = json.dumps(info)
    f.attrs[schema.ATTR_CONFIG] = json.dumps(config)
    f.attrs[schema.ATTR_BIASES] = json.dumps(config.get("biases", {}) if isinstance(config, dict) else {})
    f.attrs[schema.ATTR_STATS] = json.dumps({})
    events = f.create_group(schema.EVENTS_GROUP)
    for name, dtype in schema.EVENT_COLUMNS.items():
        events.create_dataset(
            name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(schema.EVENT_CHUNK,), **compression
        )
    events.create_dataset(
        schema.MS_TO_IDX, shape=(0,), maxshape=(None,), dtype=schema.MS_TO_IDX_DTYPE,
        chunks=(schema.SMALL_CHUNK * 4,), **compression,
    )
    events.attrs[schema.T_OFFSET_ATTR] = np.int64(0)
    # DSEC's EventSlicer reads /ms_to_idx and /t_offset at the root: a hard link and a scalar dataset.
    f[schema.MS_TO_IDX] = events[schema.MS_TO_IDX]
    f.create_dataset(schema.T_OFFSET_ATTR, data=np.int64(0))
    frames = f.create_group(schema.FRAMES_GROUP)
    height, width = frame_hw
    frames.create_dataset(
        schema.FRAME_DATA, shape=(0, height, width), maxshape=(None, height, width),
        dtype=schema.FRAME_DTYPE, chunks=(1, height, width), **compression,
    )
    frames.create_dataset(
        schema.FRAME_ROI, shape=(0, 4), maxshape=(None, 4), dtype="<i4", chunks=(schema.SMALL_CHUNK, 4)
    )
    for name in schema.FRAME_TIME_COLUMNS:
        frames.create_dataset(
            name, shape=(0,), maxshape=(None,), dtype="<i8", chunks=(schema.SMALL_CHUNK,)
        )
    f.create_group(schema.SPECIALS_GROUP)
    f.flush()


def write_events(group, parts: list[np.ndarray], t_offset_us: int, n_written: int, ms_written: int) -> int:
    """Append event batches to ``/events`` and the ``ms_to_idx`` entries they make final.

    Args:
        group: the ``/events`` group.
        parts: EVENT_DTYPE arrays in time order, recording µs.
        t_offset_us: the file's ``t_offset`` (subtracted from ``t``), µs.
        n_written: events already in the file.
        ms_written: final ``ms_to_idx`` entries already in the file.

    Returns:
        The final ``ms_to_idx`` entries in the file now.
    """
    # Column by column: contiguous arrays straight from the strided views, no structured copy.
    t_rel = np.concatenate([part["t"] for part in parts])
    t_rel -= t_offset_us
    extend(group["t"], t_rel)
    for name in ("x", "y", "p"):
        extend(group[name], np.concatenate([part[name] for part in parts]))
    # ms m is final once an event with t >= 1000 m has been seen (later events are not older).
    # Written in blocks of MS_INDEX_BLOCK entries: memory stays bounded however long the gap is.
    last_ms = int(t_rel[-1]) // 1000
    for lo in range(ms_written, last_ms + 1, MS_INDEX_BLOCK):
        ms = np.arange(lo, min(lo + MS_INDEX_BLOCK, last_ms + 1), dtype=np.int64) * 1000
        idx = n_written + np.searchsorted(t_rel, ms, side="left")
        extend(group[schema.MS_TO_IDX], idx.astype(schema.MS_TO_IDX_DTYPE))
    return max(ms_written, last_ms + 1)


def write_frames(group, frames: list, frame_hw: tuple[int, int]) -> None:
    """Append APS frames to ``/frames``: each ``(ApsFrame, offset µs)`` as a full-sensor image (zeros outside its
    region), its region and its four times plus the offset."""
    height, width = frame_hw
    data = np.zeros((len(frames), height, width), dtype=schema.FRAME_DTYPE)
    roi = np.empty((len(frames), 4), dtype="<i4")
    times = {name: np.empty(len(frames), dtype="<i8") for name in schema.FRAME_TIME_COLUMNS}
    for i, (frame, offset_us) in enumerate(frames):
        pixels = np.asarray(frame.pixels)
        x0, y0 = int(frame.position_x), int(frame.position_y)
        data[i, y0 : y0 + pixels.shape[0], x0 : x0 + pixels.shape[1]] = pixels
        roi[i] = (x0, y0, pixels.shape[1], pixels.shape[0])
        for name in schema.FRAME_TIME_COLUMNS:
            times[name][i] = int(getattr(frame, name)) + offset_us
    extend(group[schema.FRAME_DATA], data)
    extend(group[schema.FRAME_ROI], roi)
    for name, column in times.items():
        extend(group[name], column)


def write_table(f, group_name: str, table: np.ndarray) -> None:
    """Append a structured table (specials, IMU samples) to ``/<group_name>``, one 1-D dataset per field (created
    with the field's dtype on first use)."""
    group = f.require_group(group_name)
    for name in table.dtype.names:
        if name not in group:
            group.create_dataset(
                name, shape=(0,), maxshape=(None,), dtype=table.dtype[name], chunks=(schema.SMALL_CHUNK,)
            )
        extend(group[name], np.ascontiguousarray(table[name]))


def extend(dataset, values: np.ndarray) -> None:
    """Append ``values`` along the first axis of a resizable dataset."""
    n0 = dataset.shape[0]
    dataset.resize((n0 + len(values), *dataset.shape[1:]))
    dataset[n0:] = values


def is_disk_full(exc: OSError) -> bool:
    """Whether an HDF5 / OS error means the disk (or the file size limit or quota) is full."""
    text = str(exc)
    return getattr(exc, "errno", None) in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT) or "No space" in text \
        or "File too large" in text
