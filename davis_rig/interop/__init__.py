"""interop: a session.h5 in the formats other tools read — AEDAT4 (iniVation DV), Prophesee ``.dat`` +
``_bbox.npy``, RVT's preprocessed Gen1 layout, tonic-style ``.npz``.

Public API: :func:`export_session` (what ``davis-export`` runs) and :class:`ExportFormat`. The exporters sit above
``session`` and ``events`` (they crop events and build RVT histograms); the imports back into a session, which
need neither, live in :mod:`davis_rig.session` (``aedat4``, ``prophesee``, ``npz``). Importing this package
imports nothing heavy (the exporters load on first use).
"""

from __future__ import annotations

from davis_rig._lazy import lazy_exports

_LAZY = {
    "davis_rig.interop.export": ("export_session",),
    "davis_rig.interop.formats": ("ExportFormat",),
    "davis_rig.interop.summary": ("ExportSummary",),
}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY)

__all__ = [name for names in _LAZY.values() for name in names]
