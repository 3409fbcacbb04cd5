"""Export a session as a Prophesee ``.dat`` event file and its Gen1 ``_bbox.npy`` labels.

The format and its import are in :mod:`davis_rig.session.prophesee`. DAT timestamps are unsigned 32-bit µs, so
the file's ``t = 0`` is the session's first millisecond (``t_offset``, device µs, kept in the header): a
recording may last up to 71.6 minutes, and the Gen1 tools' conventions (the first 0.5 s skipped by the RVT /
Prophesee evaluation) apply from the start of the recording. Boxes get the same time base and the events' pixels.
Only events and boxes travel: APS frames, special events and IMU samples have no place in the format.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from davis_rig.errors import FormatError
from davis_rig.interop.source import ExportSource
from davis_rig.interop.summary import ExportSummary
from davis_rig.session.prophesee import DAT_KEYS, DAT_MAX_T_US, bbox_path, dat_header, pack_dat
from davis_rig.session.staging import staged_outputs

__all__ = ["export_prophesee_dat"]


def _start_date(text: str) -> _dt.datetime | None:
    try:
        return _dt.datetime.fromisoformat(text)
    except ValueError:
        return None


def export_prophesee_dat(source: ExportSource, out: str | os.PathLike, *, overwrite: bool = False,
                         progress: Callable[[int, int], None] | None = None) -> ExportSummary:
    """Write ``out`` (``.dat``) and, when the session has labels, :func:`~davis_rig.session.prophesee.bbox_path`
    of it (``X_td.dat`` -> ``X_bbox.npy``).

    Args:
        source: an open :class:`~davis_rig.interop.source.ExportSource` (its crop decides the pixels).
        out: the ``.dat`` file.
        overwrite: replace existing output files.
        progress: called with (session events read so far, session events) after each piece.

    Returns:
        An :class:`~davis_rig.interop.summary.ExportSummary`.

    Raises:
        FormatError: the recording is longer than the format's 32-bit µs, an output exists (without
            ``overwrite``), or a stale box file would sit beside a file without labels.
    """
    out = Path(out)
    reader = source.reader
    t_offset = source.t_offset_us
    span_us = reader.indexed_span_us()
    if span_us > DAT_MAX_T_US:
        raise FormatError(f"{source.path}: {span_us / 60e6:.1f} min of events do not fit the DAT format's 32-bit µs "
                          f"timestamps ({DAT_MAX_T_US / 60e6:.1f} min)")
    labels = source.labels()
    boxes_out = bbox_path(out)
    if labels is None and boxes_out.exists() and not overwrite:
        raise FormatError(f"{boxes_out}: exists, and {source.path} has no labels to replace it with (pass "
                          "--overwrite to remove it)")
    fields = {DAT_KEYS["source"]: source.path.name, DAT_KEYS["serial"]: reader.device_info.get("serial", ""),
              DAT_KEYS["t_offset_us"]: str(t_offset), DAT_KEYS["origin_xy"]: "%d %d" % source.origin_xy,
              DAT_KEYS["sensor_wh"]: f"{source.sensor_hw[1]} {source.sensor_hw[0]}"}
    kept = None
    if labels is not None:
        t_rel = labels["t"].astype(np.int64) - t_offset
        kept = labels[(t_rel >= 0) & (t_rel <= DAT_MAX_T_US)]
        kept["t"] = kept["t"].astype(np.int64) - t_offset
        fields[DAT_KEYS["labels_crop_origin_xy"]] = "%d %d" % source.labels_origin_xy
        fields[DAT_KEYS["labels_attrs"]] = json.dumps(source.labels_attrs, separators=(",", ":"), default=str)
    targets = (out, boxes_out) if labels is not None else (out,)
    events = read = 0
    with staged_outputs(*targets, overwrite=overwrite) as staged:
        with open(staged[0], "wb") as file:
            file.write(dat_header(source.frame_hw[1], source.frame_hw[0],
                                  date_utc=_start_date(reader.recording_start_utc), fields=fields))
            for chunk, n_read in source.event_chunks():
                pack_dat(chunk["t"] - t_offset, chunk["x"], chunk["y"], chunk["p"]).tofile(file)
                events += len(chunk)
                read += n_read
                if progress is not None:
                    progress(read, source.num_events)
        if kept is not None:
            with open(staged[1], "wb") as file:
                np.save(file, kept)
    if labels is None and boxes_out.exists():
        boxes_out.unlink()
    notes = [f"times are µs since the session's first millisecond (device µs {t_offset}, kept in the header)"]
    if labels is not None and len(kept) < len(labels):
        notes.append(f"{len(labels) - len(kept)} boxes lie before the first event's millisecond and are left out")
    not_exported = {"frames": len(reader.frames), "specials": len(reader.specials()),
                    "imu": 0 if (imu := reader.imu()) is None else len(imu)}
    return ExportSummary(
        format="prophesee-dat", session=str(source.path), outputs=tuple(str(t) for t in targets), events=events,
        events_read=read, labels=0 if kept is None else len(kept),
        labels_left_out=0 if kept is None else len(labels) - len(kept), frame_hw=tuple(source.frame_hw),
        origin_xy=tuple(source.origin_xy), t_offset_us=t_offset,
        not_exported={k: v for k, v in not_exported.items() if v}, notes=tuple(notes))
