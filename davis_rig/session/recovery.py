"""Rebuild a session.h5 from its raw-transfer journal after a crash (kill -9, power cut, unplug mid-write).

Run it with ``davis-record --recover session.h5`` or :func:`recover_session`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from pathlib import Path

from davis_rig.errors import ProtocolError, SessionError
from davis_rig.session.h5file import to_jsonable
from davis_rig.session.journal import (KIND_HEADER, KIND_NOTE, KIND_TRANSFER, iter_journal, journal_in_use,
                                      journal_path)
from davis_rig.session.reader import SessionReader
from davis_rig.session.writer import SessionWriter


@dataclass(frozen=True)
class RecoveryReport:
    """What :func:`recover_session` did.

    Attributes:
        path: the session file.
        recovered: True when the file was rebuilt from the journal; False when there was no journal.
        complete: whether the file was closed cleanly (always True after a rebuild). Without a journal, False
            means an interrupted recording made without one (``--no-journal``): the file holds the data up to its
            last flush and nothing more can be recovered.
        transfers: raw USB transfers re-decoded.
        events, frames, specials: items in the rebuilt file.
        t_last_us: device time of the last recovered event, µs (None when there are none).
        discarded_bytes: bytes at the journal's end that were cut short by the crash and dropped.
        kept_original: the crashed file held more events or frames than the journal gave back (its data reached
            the disk, the journal's last second did not: a power cut), so it was kept as it is and the rebuild
            dropped; the other counts are then the file's.
    """

    path: Path
    recovered: bool
    complete: bool = True
    transfers: int = 0
    events: int = 0
    frames: int = 0
    specials: int = 0
    t_last_us: int | None = None
    discarded_bytes: int = 0
    kept_original: bool = False


def recover_session(path: str | os.PathLike) -> RecoveryReport:
    """Rebuild ``path`` from ``<path>.journal`` (re-decoding every journaled transfer), then delete the journal.

    The journal holds every raw transfer of the recording from its start and is flushed to the OS every 0.25 s
    (fsync'd every 1 s), so the rebuilt file loses at most the last fraction of a second before a ``kill -9``
    (≤ 1 s before a power cut). The new file is written next to the old one (``<path>.recovering``, removed
    again if the rebuild fails) and swapped in atomically; the old, possibly unreadable, file is replaced, unless
    it opens and holds more events or frames than the rebuild (the journal is handed to the OS before every write
    of the file, so only a power cut can leave it behind): then the old file is kept and the rebuild dropped
    (:attr:`RecoveryReport.kept_original`). Damaged
    timestamps in the journal are handled as while recording (see ``SessionWriter.append``): memory and the
    file's time span stay proportional to the data. Without a journal the file is only checked (see
    :attr:`RecoveryReport.complete`).

    Args:
        path: the session.h5 (which may be missing, truncated or unreadable).

    Returns:
        A :class:`RecoveryReport`.

    Raises:
        SessionError: there is no journal and the file is unreadable, or the journal is unusable.
    """
    from davis_rig.protocol.layout import SensorLayout

    path = Path(path)
    jpath = journal_path(path)
    if not jpath.exists():
        try:
            with SessionReader(path) as reader:
                return RecoveryReport(path=path, recovered=False, complete=reader.complete,
                                      events=reader.num_events, frames=len(reader.frames),
                                      specials=len(reader.specials()))
        except SessionError as exc:
            raise SessionError(f"{path}: unreadable and there is no journal {jpath} to rebuild it from ({exc})") \
                from exc

    if journal_in_use(jpath):
        raise SessionError(f"{path}: being recorded right now ({jpath.name} is held by the recording); --recover "
                           "rebuilds a recording that crashed: let this one end (Ctrl-C stops it cleanly)")
    records = iter_journal(jpath)
    first = next(records, None)
    if first is None or first[0] != KIND_HEADER:
        raise SessionError(f"{jpath}: journal has no intact header record; nothing can be recovered")
    header = _json_object(first[1], jpath, "header")
    device_info = header.get("device_info") or {}
    try:
        layout_fields = device_info.get("layout") or {}  # AttributeError when device_info is not an object
        layout = SensorLayout.from_mapping(layout_fields) if layout_fields else SensorLayout.davis346()
    except (ProtocolError, TypeError, ValueError, AttributeError) as exc:
        raise SessionError(f"{jpath}: the journal header's sensor layout is unusable: {exc}") from exc
    tmp = path.with_name(path.name + ".recovering")
    try:
        transfers, counts, t_last, end = _rebuild(tmp, records, first[2], header, device_info, layout, jpath)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a failed rebuild leaves nothing behind; the journal is kept
        raise
    discarded = jpath.stat().st_size - end
    held = _held(path)
    if held is not None and (held.events > counts["events"] or held.frames > counts["frames"]):
        tmp.unlink()  # the crashed file got further than the journal (a power cut before the journal's fsync)
        jpath.unlink()
        return replace(held, kept_original=True, transfers=transfers)
    os.replace(tmp, path)
    jpath.unlink()
    return RecoveryReport(path=path, recovered=True, transfers=transfers, events=counts["events"],
                          frames=counts["frames"], specials=counts["specials"], t_last_us=t_last,
                          discarded_bytes=discarded)


def _held(path: Path) -> RecoveryReport | None:
    """What the crashed file holds, if it opens (``None``: missing or unreadable)."""
    try:
        with SessionReader(path) as reader:
            t_last = reader.events_end_us() - 1 if reader.num_events else None
            return RecoveryReport(path=path, recovered=False, complete=reader.complete, events=reader.num_events,
                                  frames=len(reader.frames), specials=len(reader.specials()), t_last_us=t_last)
    except SessionError:
        return None


def _json_object(payload: bytes, jpath: Path, what: str) -> dict:
    """A journal record's JSON object, or SessionError naming the journal."""
    try:
        value = json.loads(payload)
    except ValueError as exc:
        raise SessionError(f"{jpath}: the journal {what} is not valid JSON ({exc})") from exc
    if not isinstance(value, dict):
        raise SessionError(f"{jpath}: the journal {what} is not a JSON object")
    return value


def _rebuild(tmp: Path, records, end: int, header: dict, device_info, layout, jpath: Path):
    """Re-decode the journal's transfers into ``tmp``; returns (transfers, counts, last event µs, end offset)."""
    from davis_rig.protocol.decoder import StreamDecoder

    decoder = StreamDecoder(layout)
    transfers = 0
    notes: dict = {}
    with SessionWriter(tmp, device_info=device_info, config=header.get("config"), overwrite=True,
                       start_unix_us=header.get("recording_start_unix_us")) as writer:
        for kind, payload, end in records:
            if kind == KIND_TRANSFER:
                writer.append(decoder.feed(payload))
                transfers += 1
            elif kind == KIND_NOTE:
                notes.update(_json_object(payload, jpath, "note"))
        counts = writer.counts
        t_last = writer.last_t_us
        writer.set_stats({
            **notes,
            "decoder": to_jsonable(decoder.stats),
            "recovered_from_journal": {"transfers": transfers, "discarded_bytes": jpath.stat().st_size - end},
        })
    return transfers, counts, t_last, end
