"""Prophesee ``.dat`` event files (+ Gen1 ``_bbox.npy`` labels): the format, and their import into a session.h5.

The DAT format (Prophesee/Metavision "DAT File Format"; the Gen1 automotive dataset and RVT's
``psee_loader`` / ``dat_events_tools`` read it), little-endian:

1. an ASCII header of lines ``% <keyword> <value>\\n`` (``% Data file containing CD events``, ``% Version 2``,
   ``% Date YYYY-MM-DD HH:MM:SS``, ``% Width W``, ``% Height H``; readers skip keywords they do not know);
2. two bytes: event type (12 = EventCD; 0 = Event2D, the same layout) and event size (8);
3. 8-byte records: ``t`` uint32 µs, then a uint32 word with ``x`` in bits 0-13, ``y`` in bits 14-27 and the
   polarity in bit 28. A file without header lines has no type/size bytes either (older files).

Labels travel beside it as ``<name>_bbox.npy`` (Gen1: ``<name>_td.dat`` + ``<name>_bbox.npy``), a
:data:`~davis_rig.types.BBOX_DTYPE` array in the event pixels, ``t`` in the file's µs (older files call it
``ts``).

Files written by ``davis-export --to prophesee-dat`` carry ``davis_rig.*`` header lines (:data:`DAT_KEYS`) so
the import puts everything back where it was: the device µs of ``t = 0`` (DAT times are 32-bit, so the export
stores times relative to the session's first millisecond), the sensor pixel of the file's ``(0, 0)`` (non-zero
after ``--crop``), the sensor size, the crop origin and provenance of the labels. A file from elsewhere is
imported as it is: ``t`` as device µs, the file's Width x Height as the sensor (Gen1's 304x240 when the header
has none), labels in its own pixels with crop origin ``(0, 0)``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
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
from davis_rig.types import BBOX_DTYPE, RVT_HW, make_events

__all__ = ["DAT_EVENT_SIZE", "DAT_KEYS", "DAT_MAX_T_US", "DAT_RECORD", "DatHeader", "DatImportSummary",
           "bbox_path", "dat_header", "import_prophesee_dat", "pack_dat", "read_dat_header", "unpack_dat"]

#: One DAT record: timestamp (µs) and the packed x / y / polarity word.
DAT_RECORD: Final = np.dtype([("t", "<u4"), ("xyp", "<u4")])
DAT_EVENT_SIZE: Final = 8
#: Event type byte of contrast-detection events (EventCD); 0 (Event2D) has the same layout and is read too.
DAT_TYPE_CD: Final = 12
DAT_TYPES_READ: Final = (0, DAT_TYPE_CD)
_X_MASK: Final = (1 << 14) - 1
_Y_SHIFT: Final = 14
_P_SHIFT: Final = 28
#: Largest coordinate a DAT word holds, px.
DAT_MAX_COORD: Final = _X_MASK
#: Largest timestamp a DAT record holds, µs (about 71.6 minutes).
DAT_MAX_T_US: Final = (1 << 32) - 1

#: The ``davis_rig.*`` header keywords of exported files.
DAT_KEYS: Final = {
    "source": "davis_rig.source",  # the session file name
    "serial": "davis_rig.serial",  # the camera's serial number
    "t_offset_us": "davis_rig.t_offset_us",  # device µs of t = 0
    "origin_xy": "davis_rig.origin_xy",  # sensor pixel "x y" of the file's (0, 0)
    "sensor_wh": "davis_rig.sensor_wh",  # the sensor's "width height", px
    "labels_crop_origin_xy": "davis_rig.labels_crop_origin_xy",  # the session labels' crop origin "x y"
    "labels_attrs": "davis_rig.labels_attrs",  # the session's /labels attributes, JSON
}

#: Events read per step while importing (bounded memory: 8 bytes each in the file, 13 in the session).
IMPORT_CHUNK_EVENTS: Final = 1 << 21


# --- the format -------------------------------------------------------------------------------
def pack_dat(t_us, x, y, p) -> np.ndarray:
    """Pack event columns into DAT records (a new array).

    Args:
        t_us: timestamps, integer µs in ``[0, 2**32)``, shape [N].
        x, y: pixel coordinates in ``[0, 2**14)``, shape [N].
        p: polarities, {0, 1} (anything > 0 counts as ON), shape [N].

    Returns:
        :data:`DAT_RECORD` [N].

    Raises:
        FormatError: a timestamp or coordinate outside what the format holds.
    """
    t_us = np.asarray(t_us)
    x = np.asarray(x)
    y = np.asarray(y)
    out = np.empty(t_us.shape[0], dtype=DAT_RECORD)
    if len(out):
        if int(t_us.min()) < 0 or int(t_us.max()) > DAT_MAX_T_US:
            raise FormatError(f"DAT timestamps are 32-bit µs: got [{int(t_us.min())}, {int(t_us.max())}] µs, "
                              f"outside [0, {DAT_MAX_T_US}]")
        if max(int(x.max()), int(y.max())) > DAT_MAX_COORD or min(int(x.min()), int(y.min())) < 0:
            raise FormatError(f"DAT coordinates are 14-bit: got x up to {int(x.max())}, y up to {int(y.max())}")
    out["t"] = t_us
    word = x.astype(np.uint32)
    word |= y.astype(np.uint32) << _Y_SHIFT
    word |= (np.asarray(p) > 0).astype(np.uint32) << _P_SHIFT
    out["xyp"] = word
    return out


def unpack_dat(records: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unpack DAT records into ``(t_us int64, x uint16, y uint16, p uint8)`` columns, each [N]."""
    word = records["xyp"]
    return (records["t"].astype(np.int64), (word & _X_MASK).astype(np.uint16),
            ((word >> _Y_SHIFT) & _X_MASK).astype(np.uint16), ((word >> _P_SHIFT) & 1).astype(np.uint8))


def dat_header(width: int, height: int, *, date_utc: _dt.datetime | None = None,
               fields: dict[str, str] | None = None) -> bytes:
    """The header of a CD-event DAT file: the text lines, then the event type and size bytes.

    Args:
        width, height: sensor size, px (``% Width``, ``% Height``).
        date_utc: recording date (``% Date``); default now.
        fields: more ``keyword -> value`` lines (values on one line).

    Raises:
        FormatError: a keyword with a space or a value with a line break.
    """
    date_utc = date_utc or _dt.datetime.now(_dt.timezone.utc)
    lines = ["Data file containing CD events", "Version 2", f"Date {date_utc:%Y-%m-%d %H:%M:%S}",
             f"Width {int(width)}", f"Height {int(height)}"]
    for key, value in (fields or {}).items():
        if " " in key or "\n" in str(value) or "\r" in str(value):
            raise FormatError(f"DAT header: keyword {key!r} / value {value!r} must fit one 'keyword value' line")
        lines.append(f"{key} {value}")
    text = "".join(f"% {line}\n" for line in lines).encode("utf-8")
    return text + bytes([DAT_TYPE_CD, DAT_EVENT_SIZE])


@dataclass(frozen=True)
class DatHeader:
    """What the header of a DAT file says.

    Attributes:
        fields: ``keyword -> value`` of every header line (``"Width" -> "346"``).
        event_type, event_size: the two bytes after the text (0 and 8 for a file without header lines).
        data_offset: byte offset of the first record.
    """

    fields: dict
    event_type: int
    event_size: int
    data_offset: int

    def size_wh(self) -> tuple[int, int] | None:
        """``(width, height)`` from the ``Width`` / ``Height`` lines, or ``None`` when either is missing."""
        try:
            return int(self.fields["Width"]), int(self.fields["Height"])
        except (KeyError, ValueError):
            return None


def read_dat_header(file) -> DatHeader:
    """Parse the header of an open DAT file (binary mode); leaves the file at the first record.

    Raises:
        FormatError: a header without the type/size bytes, or a record layout other than 8-byte CD events.
    """
    file.seek(0)
    fields: dict[str, str] = {}
    lines = 0
    while True:
        start = file.tell()
        line = file.readline()
        if not line.startswith(b"% "):
            file.seek(start)
            break
        lines += 1
        key, _, value = line[2:].decode("latin-1").rstrip("\r\n").partition(" ")
        if key == "Data" and value.startswith("file containing"):
            key, value = "Data file containing", value[len("file containing"):].strip()
        fields[key] = value.strip()
    if lines == 0:
        return DatHeader(fields, 0, DAT_EVENT_SIZE, file.tell())
    type_size = file.read(2)
    if len(type_size) < 2:
        raise FormatError("DAT file: the header is not followed by the event type and size bytes")
    event_type, event_size = type_size[0], type_size[1]
    if event_type not in DAT_TYPES_READ or event_size != DAT_EVENT_SIZE:
        raise FormatError(f"DAT file: event type {event_type} of size {event_size} bytes; only CD / Event2D events "
                          f"(type {DAT_TYPE_CD} or 0, 8 bytes) are supported")
    return DatHeader(fields, event_type, event_size, file.tell())


def bbox_path(dat_path: str | os.PathLike) -> Path:
    """The labels file beside a DAT file: ``X_td.dat`` -> ``X_bbox.npy`` (Gen1), ``X.dat`` -> ``X_bbox.npy``."""
    dat_path = Path(dat_path)
    stem = dat_path.stem[:-3] if dat_path.stem.endswith("_td") else dat_path.stem
    return dat_path.with_name(f"{stem}_bbox.npy")


def _pair(text: str | None, what: str) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        a, b = (int(v) for v in text.split())
    except ValueError:
        raise FormatError(f"DAT header: {what} {text!r} is not two integers") from None
    return a, b


def _load_bbox(path: Path) -> np.ndarray:
    """A ``_bbox.npy`` as BBOX_DTYPE (Gen1's ``ts`` spelling of ``t`` accepted)."""
    try:
        raw = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise FormatError(f"{path}: not a readable .npy box file ({exc})") from exc
    if not isinstance(raw, np.ndarray):
        raw.close()
        raise FormatError(f"{path}: an .npz archive, not a .npy box array")
    names = raw.dtype.names or ()
    if "ts" in names and "t" not in names:
        names = tuple("t" if n == "ts" else n for n in names)
        raw = raw.copy()
        raw.dtype.names = names
    missing = [n for n in ("t", "x", "y", "w", "h", "class_id") if n not in names]
    if raw.ndim != 1 or missing:
        raise FormatError(f"{path}: expected a 1-D Prophesee box array, missing fields {missing} (has {names})")
    out = np.zeros(len(raw), dtype=BBOX_DTYPE)
    for name in BBOX_DTYPE.names:
        if name in names:
            out[name] = raw[name]
    return out


# --- import -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class DatImportSummary:
    """What :func:`import_prophesee_dat` wrote.

    Attributes:
        path: the session file; events, labels: items written; truncated_bytes: bytes of an incomplete last
        record that were left out; sensor_hw: (height, width) of the session's sensor, px; labels_path: the
        box file read (``None`` when there was none).
    """

    path: Path
    events: int
    labels: int
    truncated_bytes: int
    sensor_hw: tuple[int, int]
    labels_path: Path | None


def import_prophesee_dat(src: str | os.PathLike, dst: str | os.PathLike, *, labels: str | os.PathLike | None = None,
                         overwrite: bool = False) -> DatImportSummary:
    """Convert a Prophesee DAT file (and its ``_bbox.npy``) into a session.h5, chunk by chunk.

    Args:
        src: the ``.dat`` file.
        dst: the session.h5 to create (written as ``<stem>.partial-<random>.h5`` beside it and moved into place when complete).
        labels: the box file; default :func:`bbox_path` of ``src`` when it exists.
        overwrite: replace an existing ``dst``.

    Returns:
        A :class:`DatImportSummary`.

    Raises:
        FormatError: ``src`` is missing or not a CD-event DAT file, an event lies outside the sensor, the header's
            ``davis_rig.*`` values are malformed, the box file is unreadable, or ``dst`` exists.
        SessionError: ``dst`` cannot be written.
    """
    src = Path(src)
    if not src.is_file():
        raise FormatError(f"{src}: no such DAT file")
    labels_path = Path(labels) if labels is not None else bbox_path(src)
    if labels is not None and not labels_path.is_file():
        raise FormatError(f"{labels_path}: no such box file")
    with open(src, "rb") as file:
        header = read_dat_header(file)
    fields = header.fields
    try:
        t_offset_us = int(fields.get(DAT_KEYS["t_offset_us"], 0))
        labels_attrs = json.loads(fields[DAT_KEYS["labels_attrs"]]) if DAT_KEYS["labels_attrs"] in fields else {}
    except (ValueError, json.JSONDecodeError) as exc:
        raise FormatError(f"{src}: malformed davis_rig header value ({exc})") from exc
    origin_x, origin_y = _pair(fields.get(DAT_KEYS["origin_xy"]), "origin_xy") or (0, 0)
    sensor_w, sensor_h = (_pair(fields.get(DAT_KEYS["sensor_wh"]), "sensor_wh") or header.size_wh()
                          or (RVT_HW[1], RVT_HW[0]))
    labels_origin = _pair(fields.get(DAT_KEYS["labels_crop_origin_xy"]), "labels_crop_origin_xy") or (0, 0)

    data_bytes = src.stat().st_size - header.data_offset
    n_events, truncated = divmod(data_bytes, DAT_EVENT_SIZE)
    device_info = {"serial": fields.get(DAT_KEYS["serial"], ""), "imported_from": str(src),
                   "layout": sensor_layout(sensor_w, sensor_h)}
    config = {"source": "prophesee-dat", "dat_header": fields}
    boxes = _load_bbox(labels_path) if labels_path.is_file() else None
    with staged_outputs(dst, overwrite=overwrite) as (tmp,), open(src, "rb") as file:
        file.seek(header.data_offset)
        with SessionWriter(tmp, device_info=device_info, config=config, overwrite=True) as writer:
            for start in range(0, n_events, IMPORT_CHUNK_EVENTS):
                count = min(IMPORT_CHUNK_EVENTS, n_events - start)
                t, x, y, p = unpack_dat(np.fromfile(file, dtype=DAT_RECORD, count=count))
                x += np.uint16(origin_x)
                y += np.uint16(origin_y)
                if len(x) and (int(x.max()) >= sensor_w or int(y.max()) >= sensor_h):
                    raise FormatError(f"{src}: events at x up to {int(x.max())}, y up to {int(y.max())} lie outside "
                                      f"the {sensor_w}x{sensor_h} sensor of its header")
                writer.append_events(make_events(t + t_offset_us, x, y, p))
                writer.maybe_flush()
            writer.set_stats({"imported_from": {"file": str(src), "format": "prophesee-dat",
                                                "truncated_bytes": int(truncated)}})
            n_written = writer.counts["events"]
        if boxes is not None:
            boxes["t"] = boxes["t"].astype(np.int64) + t_offset_us
            boxes = shift_boxes(boxes, origin_x - labels_origin[0], origin_y - labels_origin[1])
            attrs = {"labeler": "davis_rig.session.prophesee", "labeler_version": __version__,
                     "source": labels_path.name, **labels_attrs, "imported_from": str(labels_path)}
            if labels_crop_origin(attrs) is None:
                attrs.update(crop_origin_x=int(labels_origin[0]), crop_origin_y=int(labels_origin[1]))
            write_labels(tmp, boxes, attrs)
    return DatImportSummary(path=Path(dst), events=int(n_written), labels=0 if boxes is None else len(boxes),
                                   truncated_bytes=int(truncated), sensor_hw=(sensor_h, sensor_w),
                                   labels_path=labels_path if boxes is not None else None)
