"""session: the session.h5 file of one recording (schema, writer, reader, journal, recovery, imports).

The writer's parts: :mod:`~davis_rig.session.writer` (buffering, flushes, free space, life cycle),
:mod:`~davis_rig.session.clock` (the recording time across timestamp resets and damaged timestamps),
:mod:`~davis_rig.session.h5file` (the HDF5 layout and its writes), :mod:`~davis_rig.session.timeline` (the pure
timestamp-repair kernels).

Public API: :class:`SessionWriter`, :class:`SessionReader`, :func:`recover_session`, :func:`record_session`.
Nothing here imports torch; the AEDAT4 importer (:mod:`davis_rig.session.aedat4`) needs ``dv-processing``.
"""

from davis_rig._lazy import lazy_exports
from davis_rig.session.reader import SessionReader
from davis_rig.session.writer import SessionWriter

__getattr__, __dir__ = lazy_exports(__name__, {"davis_rig.session.recovery": ("recover_session",),
                                               "davis_rig.session.record": ("record_session",)})

__all__ = ["SessionReader", "SessionWriter", "recover_session", "record_session"]
