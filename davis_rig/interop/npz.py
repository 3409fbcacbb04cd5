"""Export a session as an event ``.npz`` for tonic-style pipelines (layout: :mod:`davis_rig.session.npz`).

Events keep the device clock (int64 µs) and go into tonic's structured type. The ``.npz`` is written without
holding the events in memory: they are packed piece by piece into a scratch file beside the output, which is then
copied into the zip behind an ``.npy`` header that carries their final count (the crop decides it only at the end).
The zip is stored uncompressed (``np.savez``'s choice too): reading stays as fast as ``np.load`` of an ``.npy``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from davis_rig.interop.source import ExportSource
from davis_rig.interop.summary import ExportSummary
from davis_rig.session.npz import NPZ_FORMAT, NPZ_VERSION, TONIC_EVENT_DTYPE
from davis_rig.session.staging import staged_outputs

__all__ = ["export_npz"]

#: Bytes copied per step from the scratch file into the zip.
_COPY_BYTES = 1 << 24


def _write_member(archive: zipfile.ZipFile, name: str, array: np.ndarray) -> None:
    with archive.open(name, "w", force_zip64=True) as member:
        np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def export_npz(source: ExportSource, out: str | os.PathLike, *, overwrite: bool = False,
               progress: Callable[[int, int], None] | None = None) -> ExportSummary:
    """Write ``out`` (``.npz``: ``events``, ``sensor_size``, ``labels`` when the session has them, ``meta``).

    Args:
        source: an open :class:`~davis_rig.interop.source.ExportSource` (its crop decides the pixels).
        out: the ``.npz`` file.
        overwrite: replace an existing file.
        progress: called with (session events read so far, session events) after each piece.

    Returns:
        An :class:`~davis_rig.interop.summary.ExportSummary`.

    Raises:
        FormatError: ``out`` exists (without ``overwrite``) or its folder does not exist.
    """
    out = Path(out)
    reader = source.reader
    labels = source.labels()
    meta = {"format": NPZ_FORMAT, "version": NPZ_VERSION, "source": source.path.name,
            "origin_xy": list(source.origin_xy), "sensor_hw": list(source.sensor_hw),
            "labels_crop_origin_xy": None if labels is None else list(source.labels_origin_xy),
            "labels_attrs": source.labels_attrs, "device_info": reader.device_info, "config": reader.config,
            "recording_start_utc": reader.recording_start_utc}
    events = read = 0
    with staged_outputs(out, overwrite=overwrite) as (tmp,):
        scratch = tmp.with_name(tmp.name + ".events")  # beside the staged file, as unique as its name
        try:
            with open(scratch, "wb") as file:
                for chunk, n_read in source.event_chunks():
                    packed = np.empty(len(chunk), TONIC_EVENT_DTYPE)
                    for name in ("x", "y", "t"):
                        packed[name] = chunk[name]
                    packed["p"] = chunk["p"] > 0
                    packed.tofile(file)
                    events += len(chunk)
                    read += n_read
                    if progress is not None:
                        progress(read, source.num_events)
            with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
                with archive.open("events.npy", "w", force_zip64=True) as member, open(scratch, "rb") as file:
                    header = {"descr": np.lib.format.dtype_to_descr(TONIC_EVENT_DTYPE), "fortran_order": False,
                              "shape": (events,)}
                    np.lib.format.write_array_header_1_0(member, header)
                    shutil.copyfileobj(file, member, _COPY_BYTES)
                _write_member(archive, "sensor_size.npy",
                              np.array([source.frame_hw[1], source.frame_hw[0], 2], dtype=np.int64))
                if labels is not None:
                    _write_member(archive, "labels.npy", labels)
                _write_member(archive, "meta.npy", np.array(json.dumps(meta, default=str)))
        finally:
            with contextlib.suppress(OSError):
                scratch.unlink(missing_ok=True)
    not_exported = {"frames": len(reader.frames), "specials": len(reader.specials()),
                    "imu": 0 if (imu := reader.imu()) is None else len(imu)}
    return ExportSummary(
        format="npz", session=str(source.path), outputs=(str(out),), events=events, events_read=read,
        labels=0 if labels is None else len(labels), labels_left_out=0, frame_hw=tuple(source.frame_hw),
        origin_xy=tuple(source.origin_xy), t_offset_us=0,
        not_exported={k: v for k, v in not_exported.items() if v},
        notes=("times are device µs, as in the session",))
