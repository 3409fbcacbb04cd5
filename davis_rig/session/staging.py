"""Write new files beside their destination and move them into place only once they are complete.

Imports and exports write for minutes; a failure (bad input, disk full, Ctrl-C) must leave neither a partial file
at the destination nor a stray temporary file. :func:`staged_outputs` gives temporary paths next to the
destinations (same file system, so the final ``os.replace`` is atomic per file), moves them into place when the
``with`` block ends normally and deletes them when it does not.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

from davis_rig.errors import FormatError

__all__ = ["STAGING_SUFFIX", "staged_outputs"]

#: Marks the temporary files: ``out.dat`` is written as ``out.partial-<8 hex digits>.dat`` (the extension stays
#: last: some writers, dv-processing's among them, refuse a file name without theirs; the random digits keep a
#: user's own ``out.partial.dat`` and a concurrent export to the same name apart).
STAGING_SUFFIX = ".partial"


@contextlib.contextmanager
def staged_outputs(*paths: str | os.PathLike, overwrite: bool = False) -> Iterator[list[Path]]:
    """Yield temporary paths for ``paths``; on success move each into place, on any failure delete them.

    Args:
        paths: the destination files.
        overwrite: replace destinations that exist (else refuse before anything is written).

    Yields:
        ``[Path]``: one temporary path per destination (``<stem>.partial-<random><suffix>`` beside it, a name
        that does not exist yet); a temporary file the block did not create is skipped when moving.

    Raises:
        FormatError: a destination exists and ``overwrite`` is false, is a folder, or its folder does not exist
            or is not writable.
    """
    targets = [Path(p) for p in paths]
    for target in targets:
        if target.is_dir():
            raise FormatError(f"{target}: a folder, not a file that can be replaced")
        if target.exists() and not overwrite:
            raise FormatError(f"{target}: file exists (pass overwrite=True / --overwrite to replace it)")
        if not target.parent.is_dir():
            what = "is a file, not a folder" if target.parent.exists() else "does not exist"
            raise FormatError(f"{target}: the folder {target.parent} {what}")
        if not os.access(target.parent, os.W_OK | os.X_OK):
            raise FormatError(f"{target}: the folder {target.parent} is not writable")
    staged = [_unused_name(target) for target in targets]
    try:
        yield staged
    except BaseException:
        for tmp in staged:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
        raise
    try:
        for tmp, target in zip(staged, targets):
            if tmp.exists():
                os.replace(tmp, target)
    finally:  # a move that failed leaves no temporary file behind
        for tmp in staged:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)


def _unused_name(target: Path) -> Path:
    """``<stem>.partial-<8 random hex digits><suffix>`` beside ``target``, a name no file has yet."""
    while (staged := target.with_name(f"{target.stem}{STAGING_SUFFIX}-{secrets.token_hex(4)}{target.suffix}")).exists():
        continue
    return staged
