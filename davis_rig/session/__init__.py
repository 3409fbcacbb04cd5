"""session: the session.h5 file of one recording (schema, writer, reader, journal, recovery, imports).

Public API: :class:`SessionWriter`, :class:`SessionReader`, :func:`recover_session`, :func:`record_session`.
Nothing here imports torch; the AEDAT4 importer (:mod:`davis_rig.session.aedat4`) needs ``dv-processing``.
"""

from davis_rig.session.reader import SessionReader
from davis_rig.session.writer import SessionWriter

__all__ = ["SessionReader", "SessionWriter", "recover_session", "record_session"]


def __getattr__(name):
    if name == "recover_session":
        from davis_rig.session.recovery import recover_session

        return recover_session
    if name == "record_session":
        from davis_rig.session.record import record_session

        return record_session
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
