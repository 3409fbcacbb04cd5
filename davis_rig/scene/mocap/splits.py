"""Train/test split of CMU mocap trials by trial, as in the paper (47 train / 13 test trials).

The paper names neither the trials nor the rule, so this module defines a documented, deterministic rule
over the trials a user has:

1. :func:`find_trials` lists ``<root>/<subject>/<subject>_<trial>_poses.npz`` files (AMASS CMU layout), or with
   ``pattern="*.bvh"`` the ``<root>/<subject>/<subject>_<trial>.bvh`` files of the CMU BVH conversion,
   optionally only some subjects; trial ids are ``"<subject>/<subject>_<trial>"`` in both formats, so a CMU
   trial gets the same id (and, for the same set of trials, the same side) as AMASS ``.npz`` or as BVH.
2. :func:`split_trials` ranks the trial ids by ``sha256(salt + ":" + trial_id)`` and puts the
   ``n_test`` lowest ranks in the test set (default ``n_test = round(n * 13 / 60)``: 13 of 60 trials as in
   the paper). The assignment of a trial depends only on its id, the salt and ``n``: it does not depend on
   file order, the file system or the machine, and is stable under renaming the root folder.

Splitting by trial (not by subject) follows the paper; ``by="subject"`` keeps all trials of a subject on
one side (no subject in both sets) for stricter experiments.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

__all__ = ["PAPER_TEST_TRIALS", "PAPER_TRAIN_TRIALS", "TrialSplit", "find_trials", "split_trials", "trial_id"]

#: Trial counts of the paper's split.
PAPER_TRAIN_TRIALS = 47
PAPER_TEST_TRIALS = 13
DEFAULT_SALT = "davis_rig/amass-cmu-split/v1"


@dataclass(frozen=True)
class TrialSplit:
    """A train/test split: sorted trial ids per side, and where the trial files are (id -> path, if known)."""

    train: tuple[str, ...]
    test: tuple[str, ...]
    paths: dict

    def train_paths(self) -> list[Path]:
        """Files of the training trials (sorted by id)."""
        return [self.paths[t] for t in self.train]

    def test_paths(self) -> list[Path]:
        """Files of the test trials (sorted by id)."""
        return [self.paths[t] for t in self.test]


def trial_id(path: str | Path) -> str:
    """``"<subject folder>/<file stem without _poses>"`` of a trial file, e.g. ``"07/07_01"`` for
    ``CMU/07/07_01_poses.npz`` (AMASS) and for ``cmu/07/07_01.bvh`` (BVH)."""
    p = Path(path)
    return f"{p.parent.name}/{p.stem.removesuffix('_poses')}"


def find_trials(root: str | Path, subjects: Iterable[str] | None = None, pattern: str = "*_poses.npz") -> dict[str, Path]:
    """Trial files under ``root`` (``<root>/<subject>/<pattern>``).

    Args:
        root: the user's AMASS CMU folder, or CMU BVH folder with ``pattern="*.bvh"``.
        subjects: subject folder names to keep (e.g. ``["07", "08"]``); ``None`` = all.
        pattern: file glob inside a subject folder (AMASS: ``"*_poses.npz"``, BVH: ``"*.bvh"``).

    Returns:
        trial id -> path, sorted by id.

    Raises:
        FileNotFoundError: root is not a folder.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"mocap folder not found: {root}")
    keep = None if subjects is None else {str(s) for s in subjects}
    found = {}
    for path in root.glob(f"*/{pattern}"):
        if keep is None or path.parent.name in keep:
            found[trial_id(path)] = path
    return dict(sorted(found.items()))


def _rank(key: str, salt: str) -> str:
    return hashlib.sha256(f"{salt}:{key}".encode()).hexdigest()


def split_trials(
    trials: Sequence[str | Path] | dict,
    n_test: int | None = None,
    *,
    test_fraction: float = PAPER_TEST_TRIALS / (PAPER_TRAIN_TRIALS + PAPER_TEST_TRIALS),
    by: str = "trial",
    salt: str = DEFAULT_SALT,
) -> TrialSplit:
    """Deterministic train/test split (see the module docstring).

    Args:
        trials: trial ids, trial file paths (``Path``, or strings ending in ``.npz`` / ``.bvh``), or the dict of
            :func:`find_trials`.
        n_test: number of test trials (``by="trial"``) or subjects (``by="subject"``); default
            ``round(n * test_fraction)``, i.e. 13 of 60.
        test_fraction: used when ``n_test`` is None.
        by: ``"trial"`` (the paper) or ``"subject"``.
        salt: changes the (otherwise fixed) ranking.

    Returns:
        :class:`TrialSplit`.

    Raises:
        ValueError: duplicate ids, bad ``by`` or ``n_test`` outside ``[0, n]``.
    """
    if isinstance(trials, dict):
        paths = {str(k): Path(v) for k, v in trials.items()}
        ids = list(paths)
    else:
        ids, paths = [], {}
        for t in trials:
            is_file = isinstance(t, Path) or str(t).endswith((".npz", ".bvh"))
            tid = trial_id(t) if is_file else str(t)
            ids.append(tid)
            if is_file:
                paths[tid] = Path(t)
    if len(set(ids)) != len(ids):
        raise ValueError("duplicate trial ids")
    if by == "trial":
        units = {tid: [tid] for tid in ids}
    elif by == "subject":
        units: dict[str, list[str]] = {}
        for tid in ids:
            units.setdefault(tid.split("/")[0], []).append(tid)
    else:
        raise ValueError(f"by must be 'trial' or 'subject', got {by!r}")
    n = len(units)
    n_test = int(round(n * test_fraction)) if n_test is None else int(n_test)
    if not 0 <= n_test <= n:
        raise ValueError(f"n_test {n_test} outside [0, {n}]")
    ranked = sorted(units, key=lambda u: _rank(u, salt))
    test_units = set(ranked[:n_test])
    test = sorted(t for u in test_units for t in units[u])
    train = sorted(t for u in units if u not in test_units for t in units[u])
    return TrialSplit(train=tuple(train), test=tuple(test), paths=paths)
