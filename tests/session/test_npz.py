"""Event .npz import: tonic-style files from elsewhere, and the refusals that leave nothing behind."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.session import SessionReader
from davis_rig.session.npz import import_npz
from davis_rig.types import BBOX_DTYPE


def test_a_tonic_dataset_sample(tmp_path):
    """tonic's datasets use int64 fields and, for some, polarities -1 / 1; no meta: taken as they are."""
    events = np.zeros(4, dtype=[("x", int), ("y", int), ("t", int), ("p", int)])
    events["x"] = [0, 33, 1, 2]
    events["y"] = [0, 33, 3, 4]
    events["t"] = [10, 20, 20, 30]
    events["p"] = [-1, 1, 1, -1]
    labels = np.zeros(1, BBOX_DTYPE)
    labels["t"], labels["x"] = 20, 3.25
    np.savez(tmp_path / "nmnist.npz", events=events, sensor_size=np.array([34, 34, 2]), labels=labels)
    summary = import_npz(tmp_path / "nmnist.npz", tmp_path / "s.h5")
    assert summary.events == 4 and summary.labels == 1 and summary.sensor_hw == (34, 34)
    with SessionReader(tmp_path / "s.h5") as reader:
        got = reader.events()
        assert reader.device_info["layout"]["dvs_width"] == 34
        np.testing.assert_array_equal(reader.labels(), labels)
        assert reader.labels_attrs()["crop_origin_x"] == 0
    assert got["p"].tolist() == [0, 1, 1, 0] and got["t"].tolist() == [10, 20, 20, 30]


@pytest.mark.parametrize("content, says", [
    ({"events": np.zeros(1, dtype=[("x", "i2"), ("y", "i2"), ("t", "i8"), ("p", "?")])}, "sensor_size"),
    ({"events": np.zeros(1, dtype=[("x", "i2"), ("t", "i8")]), "sensor_size": np.array([4, 4, 2])},
     "fields x, y, t, p"),
    ({"events": np.zeros(1, dtype=[("x", "i2"), ("y", "i2"), ("t", "i8"), ("p", "?")]),
      "sensor_size": np.array([4, 4, 2]), "labels": np.zeros(2)}, "Prophesee box fields"),
])
def test_malformed_files(tmp_path, content, says):
    np.savez(tmp_path / "bad.npz", **content)
    with pytest.raises(FormatError, match=says):
        import_npz(tmp_path / "bad.npz", tmp_path / "s.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz"]


def test_events_outside_the_sensor(tmp_path):
    events = np.zeros(2, dtype=[("x", "i2"), ("y", "i2"), ("t", "i8"), ("p", "?")])
    events["x"] = [0, 9]
    np.savez(tmp_path / "e.npz", events=events, sensor_size=np.array([8, 8, 2]))
    with pytest.raises(FormatError, match="outside the 8x8 sensor"):
        import_npz(tmp_path / "e.npz", tmp_path / "s.h5")
    assert not (tmp_path / "s.h5").exists() and not list(tmp_path.glob("*partial*"))


def test_an_events_array_cut_short(tmp_path):
    events = np.zeros(100, dtype=[("x", "i2"), ("y", "i2"), ("t", "i8"), ("p", "?")])
    np.savez(tmp_path / "full.npz", events=events, sensor_size=np.array([8, 8, 2]))
    with zipfile.ZipFile(tmp_path / "full.npz") as src, zipfile.ZipFile(tmp_path / "cut.npz", "w") as dst:
        dst.writestr("events.npy", src.read("events.npy")[:-50])
        dst.writestr("sensor_size.npy", src.read("sensor_size.npy"))
    with pytest.raises(FormatError, match="cut short"):
        import_npz(tmp_path / "cut.npz", tmp_path / "s.h5")
    assert not (tmp_path / "s.h5").exists()


@pytest.mark.parametrize("content", [b"", b"not a zip"])
def test_not_an_npz(tmp_path, content):
    (tmp_path / "x.npz").write_bytes(content)
    with pytest.raises(FormatError, match="x.npz"):
        import_npz(tmp_path / "x.npz", tmp_path / "s.h5")


def test_a_plain_npy_is_not_an_npz(tmp_path):
    with open(tmp_path / "x.npz", "wb") as f:
        np.save(f, np.arange(3))
    with pytest.raises(FormatError, match="a single .npy array"):
        import_npz(tmp_path / "x.npz", tmp_path / "s.h5")
