"""davis_rig.scene._npz.read_npz: the safe .npz reader of the body asset, motions and AMASS trials."""

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.scene._npz import read_npz


def test_reads_every_array(tmp_path):
    np.savez(tmp_path / "a.npz", x=np.arange(3), y=np.float32(2.5))
    arrays = read_npz(tmp_path / "a.npz", ("x",), "test file")
    assert sorted(arrays) == ["x", "y"]
    np.testing.assert_array_equal(arrays["x"], [0, 1, 2])


def test_errors_name_the_file_kind(tmp_path):
    with pytest.raises(FileNotFoundError, match="test file not found"):
        read_npz(tmp_path / "missing.npz", (), "test file")
    np.savez(tmp_path / "a.npz", x=np.arange(3))
    with pytest.raises(FormatError, match=r"test file lacks keys \['y', 'z'\] \(has \['x'\]\)"):
        read_npz(tmp_path / "a.npz", ("x", "y", "z"), "test file")
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(FormatError, match="not a readable .npz test file"):
        read_npz(tmp_path / "text.npz", (), "test file")
    np.savez(tmp_path / "objects.npz", o=np.array([{"a": 1}], dtype=object))
    with pytest.raises(FormatError, match="not a readable .npz"):  # pickled arrays are refused
        read_npz(tmp_path / "objects.npz", (), "test file")
