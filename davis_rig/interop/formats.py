"""The export formats of ``davis-export`` (a module of its own, without numpy, so that ``--help`` stays fast)."""

from __future__ import annotations

from enum import StrEnum

__all__ = ["ExportFormat"]


class ExportFormat(StrEnum):
    """What :func:`~davis_rig.interop.export.export_session` writes, in the order ``davis-export --to`` lists them.

    ``aedat4``: iniVation DV; ``prophesee-dat``: Prophesee ``.dat`` + ``_bbox.npy`` (Gen1); ``rvt``: RVT's
    preprocessed Gen1 layout; ``npz``: tonic-style arrays.
    """

    AEDAT4 = "aedat4"
    PROPHESEE_DAT = "prophesee-dat"
    RVT = "rvt"
    NPZ = "npz"
