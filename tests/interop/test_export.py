"""export_session: refusals, and a failure at any point leaves the destination as it was."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.errors import ConfigError, FormatError, MissingDependencyError
from davis_rig.interop import ExportFormat, export_session
from davis_rig.interop.source import ExportSource
from davis_rig.session import SessionReader, SessionWriter

FILE_OUTPUTS = {"aedat4": "x.aedat4", "prophesee-dat": "x_td.dat", "npz": "x.npz"}


def _listing(folder):
    return sorted((p.name, p.read_bytes()) for p in folder.iterdir())


@pytest.mark.parametrize("fmt", sorted(FILE_OUTPUTS))
def test_a_failure_midway_leaves_nothing(tmp_path, rich_session, fmt, monkeypatch):
    if fmt == "aedat4":
        pytest.importorskip("dv_processing", reason="AEDAT4 needs the optional dv-processing package")
    path, _, _ = rich_session
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    original = ExportSource.event_chunks

    def fails_after_one_piece(self, max_events=None):
        pieces = original(self, 1000)
        yield next(pieces)
        raise OSError("No space left on device")

    monkeypatch.setattr(ExportSource, "event_chunks", fails_after_one_piece)
    with pytest.raises(OSError, match="No space left"):
        export_session(path, fmt, out_dir / FILE_OUTPUTS[fmt])
    assert list(out_dir.iterdir()) == []


@pytest.mark.parametrize("fmt", sorted(FILE_OUTPUTS))
def test_existing_outputs_are_kept_unless_overwrite(tmp_path, rich_session, fmt):
    if fmt == "aedat4":
        pytest.importorskip("dv_processing", reason="AEDAT4 needs the optional dv-processing package")
    path, events, _ = rich_session
    out = tmp_path / FILE_OUTPUTS[fmt]
    out.write_bytes(b"older")
    with pytest.raises(FormatError, match="file exists"):
        export_session(path, fmt, out)
    assert out.read_bytes() == b"older"
    assert export_session(path, fmt, out, overwrite=True).events == len(events)


def test_dat_refuses_recordings_longer_than_32_bit_microseconds(tmp_path, rich_session, monkeypatch):
    monkeypatch.setattr("davis_rig.interop.prophesee.DAT_MAX_T_US", 500_000)  # the fixture spans 0.8 s
    with pytest.raises(FormatError, match="do not fit the DAT format's 32-bit"):
        export_session(rich_session[0], "prophesee-dat", tmp_path / "x.dat")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rich.h5"]


def test_dat_without_labels_and_a_stale_box_file(tmp_path, rng):
    from tests.helpers.session_data import random_events

    with SessionWriter(tmp_path / "bare.h5") as writer:
        writer.append_events(random_events(rng, 100))
    (tmp_path / "x_bbox.npy").write_bytes(b"from an older export")
    with pytest.raises(FormatError, match="has no labels to replace it"):
        export_session(tmp_path / "bare.h5", "prophesee-dat", tmp_path / "x_td.dat")
    assert not (tmp_path / "x_td.dat").exists()
    summary = export_session(tmp_path / "bare.h5", "prophesee-dat", tmp_path / "x_td.dat", overwrite=True)
    assert summary.outputs == (str(tmp_path / "x_td.dat"),) and summary.labels == 0
    assert not (tmp_path / "x_bbox.npy").exists()


def test_unknown_format_and_missing_dv_processing(tmp_path, rich_session, monkeypatch):
    with pytest.raises(ConfigError, match="expected one of aedat4, prophesee-dat, rvt, npz") as err:
        export_session(rich_session[0], "hdf5", tmp_path / "x")
    assert err.value.field == "to" and tuple(ExportFormat) == ("aedat4", "prophesee-dat", "rvt", "npz")

    def no_dv():
        raise MissingDependencyError('AEDAT4 needs dv-processing: pip install "davis_rig[aedat4]"')

    monkeypatch.setattr("davis_rig.interop.aedat4.import_dv", no_dv)
    with pytest.raises(MissingDependencyError, match="davis_rig\\[aedat4\\]"):
        export_session(rich_session[0], "aedat4", tmp_path / "x.aedat4")
    assert not (tmp_path / "x.aedat4").exists()


def test_the_summary_says_what_was_left_out(tmp_path, rich_session):
    with SessionReader(rich_session[0]) as reader:
        n_frames, n_specials, n_imu = len(reader.frames), len(reader.specials()), len(reader.imu())
    summary = export_session(rich_session[0], "npz", tmp_path / "x.npz")
    assert summary.not_exported == {"frames": n_frames, "specials": n_specials, "imu": n_imu}
    assert summary.notes[0] == "the full 346x260 sensor; boxes moved from their crop at (17, 12) onto it"
    assert np.load(tmp_path / "x.npz")["events"].shape == (summary.events,)


@pytest.mark.parametrize("fmt", ["npz", "prophesee-dat", "rvt", "aedat4"])
def test_a_device_info_that_is_no_json_object_does_not_stop_an_export(tmp_path, rich_session, fmt):
    import h5py

    if fmt == "aedat4":
        pytest.importorskip("dv_processing", reason="the AEDAT4 export needs the optional dv-processing package")

    session = tmp_path / "odd.h5"
    session.write_bytes(rich_session[0].read_bytes())
    with h5py.File(session, "a") as f:
        f.attrs["device_info"] = "[1]"  # damaged or hand-edited: a JSON list
    out = {"rvt": "out", "aedat4": "out.aedat4"}.get(fmt, "out_td.dat")
    summary = export_session(session, fmt, tmp_path / out)
    assert summary.events > 0
