"""Reading the scene's ``.npz`` files (body asset, motions, AMASS trials) safely: no pickle, typed errors."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from davis_rig.errors import FormatError


def read_npz(path: str | Path, required: Iterable[str], what: str) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file (``allow_pickle=False``), after checking that ``required`` keys exist.

    Args:
        path: the file.
        required: keys the file must hold.
        what: the kind of file, for messages (``"body asset"``, ``"motion file"``).

    Returns:
        ``{key: array}`` for every key of the file.

    Raises:
        FileNotFoundError: no such file.
        FormatError: not a readable ``.npz`` (or one needing pickle), or a required key is missing.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files}
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable .npz {what} ({exc})") from exc
    missing = sorted(set(required) - set(arrays))
    if missing:
        raise FormatError(f"{path}: {what} lacks keys {missing} (has {sorted(arrays)})")
    return arrays
