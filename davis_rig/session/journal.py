"""A crash-safe, append-only journal of the raw USB transfers of a recording (``session.h5.journal``).

HDF5 files are not crash-safe: a ``kill -9`` or a power cut between two flushes can leave ``session.h5``
unreadable. While recording, every raw USB transfer is therefore also appended to a small journal next to the
file, flushed to the OS at least every 0.25 s (while data arrives) and ``fsync``'d once per second by a
background thread (fsync blocks, the recording thread must not). On a clean close the
journal is deleted; after a crash :func:`davis_rig.session.recovery.recover_session` re-decodes it into a valid
``session.h5``.

File format (all integers little-endian)::

    magic  b"DRJRNL01"
    record*   kind u8 | length u32 | crc32(payload) u32 | payload[length]

Record kinds: ``HEADER`` (JSON: device info, config, start time, toolkit version; first record), ``TRANSFER``
(one raw USB bulk transfer, bytes as received), ``NOTE`` (JSON: counters the byte stream does not carry, e.g.
transfers the device dropped). A reader stops at the first truncated or corrupt record: everything before it
is intact by construction (records are only ever appended).

The recording holds an exclusive ``flock`` on its journal until it closes it; the kernel drops the lock when the
process dies (kill -9, crash). :func:`journal_in_use` tells a journal of a recording still running from one
left by a crash, so recovery never rebuilds (and replaces) a file that is still being written.
"""

from __future__ import annotations

import json
import os
import struct
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from davis_rig.errors import SessionError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX (Windows): no lock, journal_in_use always answers False
    fcntl = None

MAGIC = b"DRJRNL01"
_RECORD = struct.Struct("<BII")

KIND_HEADER = 1
KIND_TRANSFER = 2
KIND_NOTE = 3

#: Seconds between flushes of the journal's user-space buffer to the OS (survives kill -9 from then on).
FLUSH_INTERVAL_S = 0.25
#: Seconds between fsyncs (survives a power cut from then on).
FSYNC_INTERVAL_S = 1.0


def journal_path(session_path: str | os.PathLike) -> Path:
    """Return the journal path that belongs to a session file (``<session>.journal``)."""
    return Path(str(session_path) + ".journal")


def journal_in_use(path: str | os.PathLike) -> bool:
    """Whether a running recording holds the journal ``path`` (its lock; ``False`` when there is no such file, it
    cannot be opened, or the system or file system has no ``flock``: then no recording can be seen)."""
    if fcntl is None:  # pragma: no cover - not POSIX
        return False
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # missing, unreadable, a folder: the callers' own checks report it
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:  # ENOLCK / ENOSYS: a file system without locks
        return False
    finally:
        os.close(fd)  # also releases a lock taken above
    return False


class SessionJournal:
    """Append-only, thread-safe journal of raw USB transfers.

    Args:
        path: journal file to create (an existing file is replaced).
        header: JSON-serialisable dict written as the first record (device info, config, ...).

    ``append_transfer`` may be called from the camera's reader thread while ``sync`` is called from the
    recording loop. A write error (e.g. disk full) does not raise in the caller's thread: it stops journaling and
    is re-raised as :class:`SessionError` by the next :meth:`sync` or :meth:`close`.
    """

    def __init__(self, path: str | os.PathLike, header: dict):
        self.path = Path(path)
        self.header = header
        self._file = None
        self._lock = threading.Lock()
        self._error: OSError | None = None
        self._last_flush = 0.0
        self._last_fsync = 0.0
        self.transfers = 0
        self.bytes = 0

    def open(self) -> "SessionJournal":
        """Create the file and write the magic and the header record; returns ``self``.

        Raises:
            SessionError: the file cannot be created or its header cannot be written (the file handle is
                closed and a file created by this call is removed again: it holds no transfer).
        """
        try:
            self._file = open(self.path, "wb", buffering=1 << 20)
        except OSError as exc:
            raise SessionError(f"{self.path}: cannot create the recording journal: {exc}") from exc
        try:
            if fcntl is not None:
                fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)  # held until close (journal_in_use)
        except OSError:
            pass  # a file system without flock: the recording goes on, journal_in_use cannot see it
        try:
            self._file.write(MAGIC)
            self._write_record(KIND_HEADER, json.dumps(self.header, default=str).encode())
            self._file.flush()
            os.fsync(self._file.fileno())
        except OSError as exc:
            self._discard_created_file()
            raise SessionError(f"{self.path}: cannot write the recording journal's header: {exc}") from exc
        self._last_flush = self._last_fsync = time.monotonic()
        self._closing = threading.Event()
        self._syncer = threading.Thread(target=self._fsync_loop, name="davis-rig-journal-fsync", daemon=True)
        self._syncer.start()
        return self

    def _discard_created_file(self) -> None:
        """Close the handle and remove the file of an :meth:`open` that failed after creating it (best effort)."""
        file, self._file = self._file, None
        try:
            file.close()
        except OSError:
            pass  # the buffered header is worthless; the file is removed below
        try:
            self.path.unlink(missing_ok=True)
        except OSError:
            pass  # nothing recorded in it; a leftover only makes the next recording ask for --overwrite

    def _fsync_loop(self) -> None:
        """Background thread: flush and fsync every FSYNC_INTERVAL_S, off the recording thread (fsync blocks)."""
        while not self._closing.wait(FSYNC_INTERVAL_S):
            try:
                self._flush_and_fsync()
            except OSError as exc:
                self._error = self._error or exc
                return

    def _flush_and_fsync(self) -> None:
        with self._lock:
            if self._file is None or self._error is not None:
                return
            self._file.flush()
            self._last_flush = time.monotonic()
            fileno = self._file.fileno()
        # Outside the lock so appends go on meanwhile; close() joins this thread before closing the descriptor.
        os.fsync(fileno)
        self._last_fsync = time.monotonic()

    def __enter__(self) -> "SessionJournal":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(delete=exc_type is None)

    def _write_record(self, kind: int, payload: bytes) -> None:
        self._file.write(_RECORD.pack(kind, len(payload), zlib.crc32(payload)))
        self._file.write(payload)

    def append_transfer(self, data: bytes | bytearray | memoryview) -> None:
        """Append one raw USB transfer (called from any thread; never raises on I/O errors, see class doc)."""
        self._append(KIND_TRANSFER, bytes(data))

    def note(self, values: dict) -> None:
        """Append a JSON note (counters the byte stream does not carry)."""
        self._append(KIND_NOTE, json.dumps(values, default=str).encode())

    def _append(self, kind: int, payload: bytes) -> None:
        with self._lock:
            if self._file is None or self._error is not None:
                return
            try:
                self._write_record(kind, payload)
                now = time.monotonic()
                if now - self._last_flush >= FLUSH_INTERVAL_S:
                    self._file.flush()
                    self._last_flush = now
            except OSError as exc:
                self._error = exc
                return
            if kind == KIND_TRANSFER:
                self.transfers += 1
                self.bytes += len(payload)

    def flush_to_os(self) -> None:
        """Hand every record appended so far to the OS (no fsync: cheap): from then on a ``kill -9`` loses none
        of them. :class:`~davis_rig.session.writer.SessionWriter` calls it before each HDF5 flush, so that the
        journal never holds less than the file (a rebuild from it then never has less data than the crashed file).
        Never raises on I/O errors (the next :meth:`sync` does)."""
        with self._lock:
            if self._file is None or self._error is not None:
                return
            try:
                self._file.flush()
                self._last_flush = time.monotonic()
            except OSError as exc:
                self._error = exc

    def sync(self, force: bool = False) -> None:
        """Check for write errors; with ``force`` also flush and ``fsync`` now (else a background thread fsyncs
        every :data:`FSYNC_INTERVAL_S`).

        Raises:
            SessionError: an earlier append, a background fsync or this sync failed (e.g. disk full).
        """
        if force:
            try:
                self._flush_and_fsync()
            except OSError as exc:
                self._error = self._error or exc
        self._raise_if_failed()

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            raise SessionError(
                f"{self.path}: writing the recording journal failed ({self._error}); "
                f"{self.transfers} transfers ({self.bytes} bytes) were journaled before the error"
            ) from self._error

    def close(self, delete: bool = False) -> None:
        """Close the journal; with ``delete=True`` remove the file (the session was closed cleanly).

        Raises:
            SessionError: buffered records could not be written (the file is kept).
        """
        if getattr(self, "_syncer", None) is not None:
            self._closing.set()
            self._syncer.join()
            self._syncer = None
        with self._lock:
            file, self._file = self._file, None
        if file is None:
            return
        try:
            file.close()
        except OSError as exc:
            self._error = self._error or exc
        if delete and self._error is None:
            self.path.unlink(missing_ok=True)
        self._raise_if_failed()


@dataclass
class JournalContents:
    """What :func:`read_journal` found: the header, the transfers and notes in order, and the damage.

    Attributes:
        header: the header dict.
        records: ``(kind, payload)`` in file order for TRANSFER (bytes) and NOTE (dict) records.
        valid_bytes: bytes of the file up to the end of the last intact record.
        discarded_bytes: bytes after it (a record cut short by the crash, or garbage).
    """

    header: dict
    records: list = field(default_factory=list)
    valid_bytes: int = 0
    discarded_bytes: int = 0


def iter_journal(path: str | os.PathLike) -> Iterator[tuple[int, bytes, int]]:
    """Yield ``(kind, payload, end_offset)`` of each intact record; stop at the first damaged one.

    Raises:
        SessionError: the file is missing or is not a journal.
    """
    path = Path(path)
    try:
        file = open(path, "rb")
    except OSError as exc:
        raise SessionError(f"{path}: cannot open the journal: {exc}") from exc
    with file:
        if file.read(len(MAGIC)) != MAGIC:
            raise SessionError(f"{path}: not a davis_rig journal (expected magic {MAGIC!r})")
        size = os.fstat(file.fileno()).st_size
        offset = len(MAGIC)
        while True:
            head = file.read(_RECORD.size)
            if len(head) < _RECORD.size:
                return
            kind, length, crc = _RECORD.unpack(head)
            if kind not in (KIND_HEADER, KIND_TRANSFER, KIND_NOTE) or offset + _RECORD.size + length > size:
                return  # a damaged length is never allocated: a record must end inside the file
            payload = file.read(length)
            if len(payload) < length or zlib.crc32(payload) != crc:
                return
            offset += _RECORD.size + length
            yield kind, payload, offset


def read_journal(path: str | os.PathLike) -> JournalContents:
    """Read a whole journal, stopping at the first truncated or corrupt record.

    Raises:
        SessionError: the file is missing, not a journal, or has no intact header record.
    """
    path = Path(path)
    contents: JournalContents | None = None
    end = len(MAGIC)
    for kind, payload, end in iter_journal(path):
        if contents is None:
            if kind != KIND_HEADER:
                raise SessionError(f"{path}: journal does not start with a header record (kind {kind})")
            contents = JournalContents(header=json.loads(payload))
        elif kind == KIND_TRANSFER:
            contents.records.append((kind, payload))
        elif kind == KIND_NOTE:
            contents.records.append((kind, json.loads(payload)))
    if contents is None:
        raise SessionError(f"{path}: journal has no intact header record")
    contents.valid_bytes = end
    contents.discarded_bytes = path.stat().st_size - end
    return contents
