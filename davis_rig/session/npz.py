"""Event ``.npz`` files for tonic-style pipelines: the layout, and their import into a session.h5.

One ``.npz`` (a zip of ``.npy`` arrays, ``np.load`` reads it) holds:

- ``events``: structured [N] with tonic's own field names and types (``tonic.io``'s ``events_struct``):
  ``x``, ``y`` int16 px, ``t`` int64 µs (device clock), ``p`` bool (True = ON); time-sorted;
- ``sensor_size``: int64 [3] = ``(width, height, 2)``, the ``sensor_size`` tonic's transforms take;
- ``labels``: :data:`~davis_rig.types.BBOX_DTYPE` [B] in the same pixels and clock as the events (only when the
  session has labels);
- ``meta``: a JSON string: ``format`` (:data:`NPZ_FORMAT`), ``version``, ``source``, ``origin_xy`` (sensor pixel
  of the events' ``(0, 0)``, non-zero after a crop), ``sensor_hw`` (the camera's pixel array, px),
  ``labels_crop_origin_xy`` and ``labels_attrs`` (where the session kept its labels and who made them),
  ``device_info``, ``config``, ``recording_start_utc``.

Use it as ``data = np.load("walk.npz"); events = data["events"]; tonic.transforms.ToFrame(sensor_size=
tuple(data["sensor_size"]), time_window=50_000)(events)``. :func:`import_npz` turns such a file back into a
session, reading the events chunk by chunk straight from the zip.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np

from davis_rig import __version__
from davis_rig.errors import FormatError
from davis_rig.session.info import sensor_layout
from davis_rig.session.labels import labels_crop_origin, shift_boxes, write_labels
from davis_rig.session.staging import staged_outputs
from davis_rig.session.writer import SessionWriter
from davis_rig.types import BBOX_DTYPE, make_events

__all__ = ["NPZ_FORMAT", "NPZ_VERSION", "TONIC_EVENT_DTYPE", "NpzImportSummary", "import_npz"]

NPZ_FORMAT: Final = "davis_rig.events-npz"
NPZ_VERSION: Final = 1
#: tonic's structured event type (``tonic.io.events_struct``): x, y int16 px; t int64 µs; p bool.
TONIC_EVENT_DTYPE: Final = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")])
#: Events read per step while importing.
IMPORT_CHUNK_EVENTS: Final = 1 << 21


@dataclass(frozen=True)
class NpzImportSummary:
    """What :func:`import_npz` wrote: the session ``path``, ``events`` and ``labels`` written, the sensor
    (height, width) in px."""

    path: Path
    events: int
    labels: int
    sensor_hw: tuple[int, int]


def _read_npy_header(member) -> tuple[np.dtype, int]:
    """Read the ``.npy`` header of an open zip member; returns ``(dtype, length)`` of its 1-D array."""
    version = np.lib.format.read_magic(member)
    shape, fortran, dtype = (np.lib.format.read_array_header_1_0(member) if version == (1, 0)
                             else np.lib.format.read_array_header_2_0(member))
    if len(shape) != 1 or fortran:
        raise FormatError(f"events: expected a 1-D array, got shape {shape}")
    return dtype, int(shape[0])


def _iter_member(archive: zipfile.ZipFile, name: str, chunk: int):
    """Yield the 1-D structured array stored as ``name`` in pieces of ``chunk`` items (bounded memory)."""
    with archive.open(name) as member:
        dtype, length = _read_npy_header(member)
        if dtype.hasobject:
            raise FormatError(f"{name}: object arrays are not read (they need pickle)")
        for start in range(0, length, chunk):
            count = min(chunk, length - start)
            raw = member.read(count * dtype.itemsize)
            if len(raw) != count * dtype.itemsize:
                raise FormatError(f"{name}: the array is cut short after {start + len(raw) // dtype.itemsize} items")
            yield np.frombuffer(raw, dtype=dtype)


def import_npz(src: str | os.PathLike, dst: str | os.PathLike, *, overwrite: bool = False) -> NpzImportSummary:
    """Convert an event ``.npz`` (see the module docstring) into a session.h5, chunk by chunk.

    Events go back to the sensor pixels (``meta.origin_xy`` added), labels back to the session's crop
    coordinates (``meta.labels_crop_origin_xy``); a file without ``meta`` is imported as it is (its
    ``sensor_size`` is the sensor, labels keep its pixels with crop origin ``(0, 0)``). Any structured ``events``
    with fields ``x, y, t, p`` is accepted; polarities > 0 are ON.

    Args:
        src: the ``.npz`` file.
        dst: the session.h5 to create (written as ``<stem>.partial-<random>.h5`` beside it, moved into place when complete).
        overwrite: replace an existing ``dst``.

    Returns:
        A :class:`NpzImportSummary`.

    Raises:
        FormatError: ``src`` is missing or not a zip, lacks ``events`` or ``sensor_size``, has malformed
            ``meta`` / ``labels``, an event outside the sensor, or ``dst`` exists.
        SessionError: ``dst`` cannot be written.
    """
    src = Path(src)
    if not src.is_file():
        raise FormatError(f"{src}: no such .npz file")
    try:
        npz = np.load(src, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{src}: not a readable .npz file ({type(exc).__name__}: {exc})") from exc
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise FormatError(f"{src}: a single .npy array, not an .npz of named arrays")
    with npz:
        members = set(npz.files)
        if not {"events", "sensor_size"} <= members:
            raise FormatError(f"{src}: expected arrays 'events' and 'sensor_size' (tonic's (width, height, 2)), "
                              f"has {sorted(members)}")
        try:
            meta = json.loads(str(npz["meta"])) if "meta" in members else {}
            width, height = (int(v) for v in np.asarray(npz["sensor_size"]).reshape(-1)[:2])
            labels = np.asarray(npz["labels"]) if "labels" in members else None
        except (ValueError, TypeError, json.JSONDecodeError) as exc:
            raise FormatError(f"{src}: malformed meta / sensor_size / labels ({exc})") from exc
    if labels is not None and (labels.dtype.names is None or not set(BBOX_DTYPE.names) <= set(labels.dtype.names)):
        raise FormatError(f"{src}: 'labels' must have the Prophesee box fields {BBOX_DTYPE.names}, got {labels.dtype}")
    origin_x, origin_y = (int(v) for v in meta.get("origin_xy", (0, 0)))
    sensor_h, sensor_w = (int(v) for v in meta.get("sensor_hw", (height, width)))
    labels_origin = tuple(int(v) for v in (meta.get("labels_crop_origin_xy") or (0, 0)))
    device_info = dict(meta.get("device_info") or {})
    device_info.setdefault("layout", sensor_layout(sensor_w, sensor_h))
    device_info["imported_from"] = str(src)
    config = dict(meta.get("config") or {"source": "npz"})

    with staged_outputs(dst, overwrite=overwrite) as (tmp,), zipfile.ZipFile(src) as archive:
        with SessionWriter(tmp, device_info=device_info, config=config, overwrite=True) as writer:
            for part in _iter_member(archive, "events.npy", IMPORT_CHUNK_EVENTS):
                if part.dtype.names is None or not {"x", "y", "t", "p"} <= set(part.dtype.names):
                    raise FormatError(f"{src}: 'events' must be structured with fields x, y, t, p, got {part.dtype}")
                x = part["x"].astype(np.int64) + origin_x
                y = part["y"].astype(np.int64) + origin_y
                if len(x) and (x.min() < 0 or y.min() < 0 or x.max() >= sensor_w or y.max() >= sensor_h):
                    raise FormatError(f"{src}: events at x in [{x.min()}, {x.max()}], y in [{y.min()}, {y.max()}] lie "
                                      f"outside the {sensor_w}x{sensor_h} sensor")
                writer.append_events(make_events(part["t"], x, y, (part["p"] > 0).astype(np.uint8)))
                writer.maybe_flush()
            writer.set_stats({"imported_from": {"file": str(src), "format": "npz"}})
            n_events = writer.counts["events"]
        if labels is not None:
            boxes = np.zeros(len(labels), BBOX_DTYPE)
            for name in BBOX_DTYPE.names:
                boxes[name] = labels[name]
            boxes = shift_boxes(boxes, origin_x - labels_origin[0], origin_y - labels_origin[1])
            attrs = {"labeler": "davis_rig.session.npz", "labeler_version": __version__, "source": src.name,
                     **dict(meta.get("labels_attrs") or {}), "imported_from": str(src)}
            if labels_crop_origin(attrs) is None:
                attrs.update(crop_origin_x=labels_origin[0], crop_origin_y=labels_origin[1])
            write_labels(tmp, boxes, attrs)
    return NpzImportSummary(path=Path(dst), events=int(n_events), labels=0 if labels is None else len(labels),
                            sensor_hw=(sensor_h, sensor_w))
