"""session: the session.h5 file of one recording (schema, writer, reader, journal, recovery, imports).

Public API: :class:`SessionWriter`, :class:`SessionReader`, :func:`recover_session`, :func:`record_session`.
Nothing here imports torch; the AEDAT4 importer (:mod:`davis_rig.session.aedat4`) needs ``dv-processing``.
"""

from davis_rig._lazy import lazy_exports
from davis_rig.session.reader import SessionReader
from davis_rig.session.writer import SessionWriter

__getattr__, __dir__ = lazy_exports(__name__, {"davis_rig.session.recovery": ("recover_session",),
                                               "davis_rig.session.record": ("record_session",)})

__all__ = ["SessionReader", "SessionWriter", "recover_session", "record_session"]
