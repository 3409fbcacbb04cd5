"""Export one session into one of the :class:`~davis_rig.interop.formats.ExportFormat` formats (what
``davis-export`` runs).

Geometry (:mod:`davis_rig.interop.source`): ``rvt`` always crops to RVT's 304x240 Gen1 window; the other formats
keep the full sensor (346x260 on a DAVIS346) unless ``crop=True``. Every output is written beside its destination
and moved into place only when complete: a failed export leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path

from davis_rig.errors import ConfigError
from davis_rig.interop.formats import ExportFormat
from davis_rig.interop.source import ExportSource
from davis_rig.interop.summary import ExportSummary

__all__ = ["export_session"]


def export_session(path: str | os.PathLike, to: str, out: str | os.PathLike, *, crop: bool = False,
                   crop_origin_xy: tuple[int, int] | None = None, split: str = "test", overwrite: bool = False,
                   progress: Callable[[int, int], None] | None = None) -> ExportSummary:
    """Export the session ``path`` as ``to`` into ``out``.

    Args:
        path: the session.h5.
        to: an :class:`~davis_rig.interop.formats.ExportFormat` (or its name).
        out: the output file (``aedat4``, ``prophesee-dat``: the ``.dat``, its ``_bbox.npy`` goes beside it;
            ``npz``) or the dataset folder (``rvt``: the sequence goes to ``out/<split>/<session stem>``).
        crop: write only the 304x240 RVT window (implied by ``rvt``).
        crop_origin_xy: that window's top-left on the sensor, px (default: the labels' origin, else centred).
        split: ``rvt`` only: ``train``, ``val`` or ``test``.
        overwrite: replace existing outputs.
        progress: called with (session events read so far, session events in all).

    Returns:
        An :class:`~davis_rig.interop.summary.ExportSummary`; its ``notes`` say what the user should know (crop,
        time base, what was left out).

    Raises:
        ConfigError: an unknown format (field ``to``), a crop origin that does not fit or differs from the labels'
            (``crop_origin_xy``), a bad ``split``, an ``out`` that is the session itself or, for ``aedat4``, does
            not end in ``.aedat4`` (field ``out``).
        SessionError: the session cannot be read.
        FormatError: an output exists (without ``overwrite``), or the format cannot hold this session (DAT: over
            71.6 min; RVT: no labels).
        MissingDependencyError: ``aedat4`` without dv-processing.
    """
    if to not in tuple(ExportFormat):
        raise ConfigError("to", f"expected one of {', '.join(ExportFormat)}, got {to!r}")
    if to == ExportFormat.AEDAT4 and Path(out).suffix != ".aedat4":
        raise ConfigError("out", f"--to aedat4 writes a .aedat4 file (dv-processing aborts on any other name), "
                                 f"got {str(out)!r}")
    if Path(out).exists() and Path(path).exists() and os.path.samefile(out, path):
        raise ConfigError("out", f"{out} is the session being exported")
    crop = crop or to == ExportFormat.RVT or crop_origin_xy is not None
    with ExportSource(path, crop=crop, crop_origin_xy=crop_origin_xy) as source:
        if to == ExportFormat.AEDAT4:
            from davis_rig.interop.aedat4 import export_aedat4

            summary = export_aedat4(source, out, overwrite=overwrite, progress=progress)
        elif to == ExportFormat.PROPHESEE_DAT:
            from davis_rig.interop.prophesee import export_prophesee_dat

            summary = export_prophesee_dat(source, out, overwrite=overwrite, progress=progress)
        elif to == ExportFormat.NPZ:
            from davis_rig.interop.npz import export_npz

            summary = export_npz(source, out, overwrite=overwrite, progress=progress)
        else:
            from davis_rig.interop.rvt import export_rvt

            summary = export_rvt(source, out, split=split, overwrite=overwrite, progress=progress)
        geometry = (f"cropped to the {source.frame_hw[1]}x{source.frame_hw[0]} window at {tuple(source.origin_xy)}"
                    if crop else f"the full {source.frame_hw[1]}x{source.frame_hw[0]} sensor"
                    + (f"; boxes moved from their crop at {tuple(source.labels_origin_xy)} onto it"
                       if source.labels_origin_xy not in (None, (0, 0)) else ""))
    return summary if to == ExportFormat.RVT else dataclasses.replace(summary, notes=(geometry, *summary.notes))
