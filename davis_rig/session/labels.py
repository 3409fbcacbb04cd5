"""The ``/labels`` group of a session: writing it, and reading where its boxes sit on the sensor.

Labels are Prophesee boxes (:data:`~davis_rig.types.BBOX_DTYPE`, ``t`` in device µs) in the pixels of the RVT crop
(304x240) whose top-left corner is the *crop origin* on the sensor. Writers store that origin as attributes:
``davis-label`` as ``crop_origin_x`` / ``crop_origin_y``, the synthetic recordings as ``crop_origin_xy`` (a JSON
list); :func:`labels_crop_origin` reads both.
"""

from __future__ import annotations

import json
import os

import numpy as np

from davis_rig.errors import FormatError, SessionError
from davis_rig.session import schema
from davis_rig.session.journal import journal_in_use, journal_path
from davis_rig.types import BBOX_DTYPE

__all__ = ["labels_crop_origin", "refuse_session_being_recorded", "shift_boxes", "write_labels"]


def refuse_session_being_recorded(path: str | os.PathLike) -> None:
    """Raise :class:`SessionError` when a running recording holds ``path``'s journal: labels written beside a
    recording would corrupt the file (two writers)."""
    if journal_in_use(journal_path(path)):
        raise SessionError(f"{path}: being recorded right now; label it once the recording has ended (two writers "
                           "would corrupt the file)")


def write_labels(path: str | os.PathLike, labels: np.ndarray, attrs: dict, *, overwrite: bool = False) -> None:
    """Store labels as ``/labels/boxes`` with attributes (JSON-encoded when not scalar).

    Args:
        path: a closed session.h5 (opened for writing here).
        labels: BBOX_DTYPE [B].
        attrs: the provenance attributes (``labeler``, ``labeler_version``, ``created_utc``, ``source``, ...).
        overwrite: replace an existing ``/labels`` group.

    Raises:
        SessionError: ``/labels`` exists and ``overwrite`` is false, the session is being recorded (its journal
            is held, or another process has the file open for writing: HDF5's lock), or the file cannot be written.
        FormatError: ``labels`` is not BBOX_DTYPE.
    """
    import h5py

    if not isinstance(labels, np.ndarray) or labels.dtype != BBOX_DTYPE:
        raise FormatError(f"labels: expected BBOX_DTYPE, got {getattr(labels, 'dtype', type(labels))}")
    refuse_session_being_recorded(path)
    schema.import_hdf5plugin()
    try:
        # HDF5's own lock refuses a file another process writes (a recording without a journal); file systems
        # without locks are written as before.
        with h5py.File(path, "r+", locking="best-effort") as f:
            if schema.LABELS_GROUP in f:
                if not overwrite:
                    raise SessionError(f"{path}: already has /labels ({f[schema.LABELS_GROUP].attrs.get('labeler')}); "
                                       "pass --overwrite to replace them")
                del f[schema.LABELS_GROUP]
            group = f.create_group(schema.LABELS_GROUP)
            group.create_dataset(schema.LABEL_BOXES, data=labels, maxshape=(None,), chunks=True)
            for key, value in attrs.items():
                group.attrs[key] = value if isinstance(value, (str, int, float, bool, np.integer, np.floating)) \
                    else json.dumps(value)
    except OSError as exc:
        raise SessionError(f"{path}: cannot write /labels: {exc}") from exc


def labels_crop_origin(attrs: dict, path: str | os.PathLike | None = None) -> tuple[int, int] | None:
    """The crop origin ``(x0, y0)`` on the sensor (px) stored with the labels, or ``None`` when none is stored.

    Args:
        attrs: the ``/labels`` attributes (:meth:`~davis_rig.session.SessionReader.labels_attrs`).
        path: the session they come from (named in the error).

    Raises:
        SessionError: an origin attribute is present but is not two integers.
    """
    try:
        if "crop_origin_x" in attrs and "crop_origin_y" in attrs:
            return int(attrs["crop_origin_x"]), int(attrs["crop_origin_y"])
        if "crop_origin_xy" in attrs:
            value = attrs["crop_origin_xy"]
            x0, y0 = json.loads(value) if isinstance(value, str) else value
            return int(x0), int(y0)
    except (TypeError, ValueError) as exc:
        where = "" if path is None else f"{path}: "
        raise SessionError(f"{where}/labels: unreadable crop origin attribute ({exc})") from exc
    return None


def shift_boxes(boxes: np.ndarray, dx_px: float, dy_px: float) -> np.ndarray:
    """Move boxes by ``(dx_px, dy_px)`` into another pixel frame (a new array; sums in float64, stored float32).

    A shift by whole pixels is exact for box coordinates whose float32 value keeps its last bits at the new
    magnitude; in general it rounds to the float32 spacing of the result (≤ 6.1e-5 px below 512 px), so a shift
    and the opposite shift give the coordinates back to within that.

    Args:
        boxes: BBOX_DTYPE [B].
        dx_px, dy_px: added to ``x`` and ``y``, px.
    """
    out = boxes.copy()
    for axis, shift in (("x", dx_px), ("y", dy_px)):
        if shift:
            out[axis] = (out[axis].astype(np.float64) + shift).astype(np.float32)
    return out
