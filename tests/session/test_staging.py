"""``staged_outputs``: destinations refused before anything is written; no temporary file left on any failure."""

from __future__ import annotations

import os

import pytest

from davis_rig.errors import FormatError
from davis_rig.session import staging
from davis_rig.session.staging import staged_outputs


def test_a_folder_as_destination_is_refused_before_writing(tmp_path):
    (tmp_path / "out.npz").mkdir()
    with pytest.raises(FormatError, match=r"out\.npz: a folder, not a file that can be replaced"):
        with staged_outputs(tmp_path / "out.npz", overwrite=True):
            pytest.fail("the block ran")
    assert [p.name for p in tmp_path.iterdir()] == ["out.npz"]


def test_a_move_that_fails_leaves_no_temporary_file(tmp_path, monkeypatch):
    moves = []

    def replace(src, dst):
        if moves:
            raise OSError(28, "No space left on device", str(dst))
        moves.append(dst)
        os.rename(src, dst)

    monkeypatch.setattr(staging.os, "replace", replace)
    with pytest.raises(OSError):
        with staged_outputs(tmp_path / "a.dat", tmp_path / "a_bbox.npy") as (dat, bbox):
            dat.write_bytes(b"events")
            bbox.write_bytes(b"boxes")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.dat"]


def test_a_folder_that_cannot_be_written_is_refused_before_writing(tmp_path, monkeypatch):
    real_access = os.access
    monkeypatch.setattr(staging.os, "access", lambda path, mode: False if path == tmp_path else real_access(path, mode))
    with pytest.raises(FormatError, match=r"out\.npz: the folder .* is not writable"):
        with staged_outputs(tmp_path / "out.npz"):
            pytest.fail("the block ran")


def test_a_users_own_partial_named_file_is_not_touched(tmp_path):
    own = tmp_path / "out.partial.dat"
    own.write_bytes(b"the user's file")
    with staged_outputs(tmp_path / "out.dat") as (tmp,):
        assert tmp.parent == tmp_path and tmp.suffix == ".dat" and tmp.name.startswith("out.partial-")
        assert not tmp.exists()
        tmp.write_bytes(b"export")
    assert own.read_bytes() == b"the user's file"
    assert (tmp_path / "out.dat").read_bytes() == b"export"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.dat", "out.partial.dat"]
