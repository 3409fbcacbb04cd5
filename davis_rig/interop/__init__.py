"""interop: a session.h5 in the formats other tools read — AEDAT4 (iniVation DV), Prophesee ``.dat`` +
``_bbox.npy``, RVT's preprocessed Gen1 layout, tonic-style ``.npz``.

Public API: :func:`export_session` (what ``davis-export`` runs) and :data:`FORMATS`. The exporters sit above
``session`` and ``events`` (they crop events and build RVT histograms); the imports back into a session, which
need neither, live in :mod:`davis_rig.session` (``aedat4``, ``prophesee``, ``npz``).
"""

from davis_rig.interop.export import FORMATS, export_session
from davis_rig.interop.summary import ExportSummary

__all__ = ["FORMATS", "ExportSummary", "export_session"]
