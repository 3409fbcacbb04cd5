"""Prophesee DAT: the byte layout, the header, and importing files from elsewhere (Gen1 style, damaged)."""

from __future__ import annotations

import io

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.session import SessionReader
from davis_rig.session.prophesee import (DAT_RECORD, bbox_path, dat_header, import_prophesee_dat, pack_dat,
                                         read_dat_header, unpack_dat)


def test_record_bytes():
    """x in bits 0-13, y in 14-27, polarity in bit 28, after a 32-bit µs timestamp (little-endian)."""
    records = pack_dat([5, 2**32 - 1], [3, 16383], [2, 16383], [1, 0])
    assert records.tobytes() == bytes.fromhex("05000000" "03800010" "ffffffff" "ffffff0f")
    t, x, y, p = unpack_dat(records)
    assert t.tolist() == [5, 2**32 - 1] and x.tolist() == [3, 16383] and y.tolist() == [2, 16383]
    assert p.tolist() == [1, 0] and t.dtype == np.int64 and x.dtype == np.uint16


@pytest.mark.parametrize("t, x", [([-1], [0]), ([2**32], [0]), ([0], [16384])])
def test_values_the_format_cannot_hold(t, x):
    with pytest.raises(FormatError):
        pack_dat(t, x, [0], [0])


def test_header_round_trip():
    raw = dat_header(346, 260, fields={"davis_rig.t_offset_us": "10000", "davis_rig.labels_attrs": '{"a": "b c"}'})
    assert raw.startswith(b"% Data file containing CD events\n% Version 2\n% Date ")
    assert raw.endswith(b"% davis_rig.labels_attrs {\"a\": \"b c\"}\n\x0c\x08")
    header = read_dat_header(io.BytesIO(raw + b"\0" * 8))
    assert header.size_wh() == (346, 260) and header.event_type == 12 and header.event_size == 8
    assert header.fields["davis_rig.labels_attrs"] == '{"a": "b c"}' and header.data_offset == len(raw)
    assert header.fields["Data file containing"] == "CD events"
    with pytest.raises(FormatError, match="one 'keyword value' line"):
        dat_header(1, 1, fields={"bad key": "x"})


def test_bbox_path():
    assert bbox_path("a/rec_td.dat").as_posix() == "a/rec_bbox.npy"
    assert bbox_path("rec.dat").as_posix() == "rec_bbox.npy"


def _gen1_file(path, records, *, header=True, ev_type=0):
    with open(path, "wb") as f:
        if header:
            f.write(b"% Data file containing Event2D events.\n% Version 2\n% Date 2017-04-06 09:57:37\n"
                    b"% Height 240\n% Width 304\n" + bytes([ev_type, 8]))
        records.tofile(f)


def test_import_a_gen1_style_file(tmp_path):
    records = pack_dat([0, 10, 10, 2000], [0, 303, 5, 7], [0, 239, 6, 8], [1, 0, 1, 0])
    _gen1_file(tmp_path / "seq_td.dat", records)
    boxes = np.zeros(2, dtype=[("ts", "<u8"), ("x", "<f4"), ("y", "<f4"), ("w", "<f4"), ("h", "<f4"),
                               ("class_id", "u1"), ("confidence", "<f4"), ("track_id", "<u4")])  # Gen1's old names
    boxes["ts"] = [10, 2000]
    boxes["x"] = [1.5, 2.5]
    boxes["class_id"] = [0, 1]
    np.save(tmp_path / "seq_bbox.npy", boxes)
    summary = import_prophesee_dat(tmp_path / "seq_td.dat", tmp_path / "s.h5")
    assert summary.events == 4 and summary.labels == 2 and summary.sensor_hw == (240, 304)
    with SessionReader(tmp_path / "s.h5") as reader:
        events = reader.events()
        labels = reader.labels()
        attrs = reader.labels_attrs()
        assert tuple(reader.frames.data.shape[1:]) == (240, 304)
    assert events["t"].tolist() == [0, 10, 10, 2000] and events["x"].tolist() == [0, 303, 5, 7]
    assert events["p"].tolist() == [1, 0, 1, 0]
    assert labels["t"].tolist() == [10, 2000] and labels["x"].tolist() == [1.5, 2.5]
    assert (attrs["crop_origin_x"], attrs["crop_origin_y"]) == (0, 0) and attrs["source"] == "seq_bbox.npy"


def test_import_without_header_and_with_a_cut_record(tmp_path):
    records = pack_dat([1, 2, 3], [1, 2, 3], [4, 5, 6], [0, 1, 0])
    _gen1_file(tmp_path / "old.dat", records, header=False)
    with open(tmp_path / "old.dat", "ab") as f:
        f.write(b"\x01\x02\x03")  # a record cut short
    summary = import_prophesee_dat(tmp_path / "old.dat", tmp_path / "s.h5")
    assert summary.events == 3 and summary.truncated_bytes == 3 and summary.labels_path is None
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.events()["y"].tolist() == [4, 5, 6] and reader.labels() is None


def test_damaged_files_are_refused_and_nothing_is_written(tmp_path):
    _gen1_file(tmp_path / "wide.dat", pack_dat([0, 1], [0, 400], [0, 0], [0, 0]))  # x = 400 on a 304-wide sensor
    with pytest.raises(FormatError, match="outside the 304x240 sensor"):
        import_prophesee_dat(tmp_path / "wide.dat", tmp_path / "s.h5")
    _gen1_file(tmp_path / "trig.dat", np.zeros(1, DAT_RECORD), ev_type=14)  # external triggers, not CD events
    with pytest.raises(FormatError, match="event type 14"):
        import_prophesee_dat(tmp_path / "trig.dat", tmp_path / "s.h5")
    with pytest.raises(FormatError, match="no such DAT file"):
        import_prophesee_dat(tmp_path / "none.dat", tmp_path / "s.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["trig.dat", "wide.dat"]


def test_an_existing_destination_is_kept(tmp_path):
    _gen1_file(tmp_path / "a.dat", pack_dat([0], [0], [0], [0]))
    (tmp_path / "s.h5").write_bytes(b"keep me")
    with pytest.raises(FormatError, match="file exists"):
        import_prophesee_dat(tmp_path / "a.dat", tmp_path / "s.h5")
    assert (tmp_path / "s.h5").read_bytes() == b"keep me"
    import_prophesee_dat(tmp_path / "a.dat", tmp_path / "s.h5", overwrite=True)
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.num_events == 1 and reader.labels() is None


def test_a_box_file_without_the_fields_is_refused(tmp_path):
    _gen1_file(tmp_path / "a_td.dat", pack_dat([0], [0], [0], [0]))
    np.save(tmp_path / "a_bbox.npy", np.zeros(2, dtype=[("t", "<u8"), ("x", "<f4")]))
    with pytest.raises(FormatError, match="missing fields"):
        import_prophesee_dat(tmp_path / "a_td.dat", tmp_path / "s.h5")
    assert not (tmp_path / "s.h5").exists()


@pytest.mark.parametrize("content, message", [(b"", "not a readable .npy box file"),
                                              (None, "an .npz archive, not a .npy box array")])
def test_an_empty_or_zipped_box_file_is_refused(tmp_path, content, message):
    _gen1_file(tmp_path / "a_td.dat", pack_dat([0], [0], [0], [0]))
    if content is None:
        np.savez(tmp_path / "boxes.npz", t=np.zeros(1))
        (tmp_path / "boxes.npz").rename(tmp_path / "a_bbox.npy")
    else:
        (tmp_path / "a_bbox.npy").write_bytes(content)
    with pytest.raises(FormatError, match=message):
        import_prophesee_dat(tmp_path / "a_td.dat", tmp_path / "s.h5")
    assert not (tmp_path / "s.h5").exists()
