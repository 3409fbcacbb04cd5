"""Export -> import gives the session back: one suite every format with an import must pass (full sensor and crop)."""

from __future__ import annotations

import numpy as np
import pytest

from davis_rig.events.crop import crop_events
from davis_rig.interop import export_session
from davis_rig.session import SessionReader
from davis_rig.session.labels import labels_crop_origin
from davis_rig.types import RVT_HW

#: Box coordinates moved onto the sensor and back come back to within the float32 spacing below 512 px.
SHIFT_TOL_PX = float(np.spacing(np.float32(512)))


def _import(fmt: str, src, dst):
    if fmt == "prophesee-dat":
        from davis_rig.session.prophesee import import_prophesee_dat

        return import_prophesee_dat(src, dst)
    if fmt == "npz":
        from davis_rig.session.npz import import_npz

        return import_npz(src, dst)
    pytest.importorskip("dv_processing", reason="AEDAT4 needs the optional dv-processing package")
    from davis_rig.session.aedat4 import import_aedat4

    return import_aedat4(src, dst)


OUT_NAMES = {"aedat4": "x.aedat4", "prophesee-dat": "x_td.dat", "npz": "x.npz"}


@pytest.mark.parametrize("crop", [False, True], ids=["sensor", "crop"])
@pytest.mark.parametrize("fmt", ["aedat4", "prophesee-dat", "npz"])
def test_export_import_round_trip(tmp_path, rich_session, labels_origin, fmt, crop, monkeypatch):
    if fmt == "aedat4":
        pytest.importorskip("dv_processing", reason="AEDAT4 needs the optional dv-processing package")
    # small pieces: the chunked read and write paths run many times
    monkeypatch.setattr("davis_rig.interop.source.CHUNK_EVENTS", 3000)
    monkeypatch.setattr("davis_rig.session.prophesee.IMPORT_CHUNK_EVENTS", 2500)
    monkeypatch.setattr("davis_rig.session.npz.IMPORT_CHUNK_EVENTS", 2500)
    path, events, labels = rich_session
    out = tmp_path / OUT_NAMES[fmt]
    summary = export_session(path, fmt, out, crop=crop)
    expected = events
    if crop:
        inside = crop_events(events, labels_origin)
        expected = inside.copy()
        expected["x"] += labels_origin[0]
        expected["y"] += labels_origin[1]
        assert summary.frame_hw == RVT_HW and summary.origin_xy == labels_origin
    assert summary.events == len(expected) and summary.events_read == len(events)
    assert summary.labels == len(labels)
    assert not list(tmp_path.glob("*.partial*")), "no temporary file may remain"

    back = tmp_path / "back.h5"
    _import(fmt, out, back)
    with SessionReader(back) as reader:
        np.testing.assert_array_equal(reader.events(), expected)
        got = reader.labels()
        attrs = reader.labels_attrs()
        assert reader.device_info["serial"] == "RICH0001"
        assert tuple(reader.frames.data.shape[1:]) == (260, 346)  # back on the DAVIS346 sensor
        if fmt == "aedat4":
            _check_aedat4_streams(reader, path, crop, labels_origin)
    assert labels_crop_origin(attrs) == labels_origin
    assert attrs["labeler"] == "test-labeler" and attrs["source"] == "hand made"
    for name in ("t", "class_id", "class_confidence", "track_id"):
        np.testing.assert_array_equal(got[name], labels[name])
    # exact when the output's pixels are the labels' own crop; within float32 spacing when moved onto the sensor;
    # AEDAT4 keeps the corners, so its w / h always come back through a float32 difference
    exact_xy = crop
    for name in ("x", "y", "w", "h"):
        if (name in "xy" and exact_xy) or (name in "wh" and fmt != "aedat4"):
            np.testing.assert_array_equal(got[name], labels[name])
        else:
            np.testing.assert_allclose(got[name], labels[name], rtol=0, atol=SHIFT_TOL_PX)


def _check_aedat4_streams(reader, original_path, crop: bool, labels_origin) -> None:
    with SessionReader(original_path) as original:
        assert len(reader.frames) == len(original.frames)
        for name in ("t_start_exposure_us", "t_end_exposure_us"):
            np.testing.assert_array_equal(reader.frames.times_us(name), original.frames.times_us(name))
        if crop:
            x0, y0 = labels_origin
            window = (slice(y0, y0 + RVT_HW[0]), slice(x0, x0 + RVT_HW[1]))
            np.testing.assert_array_equal(reader.frames.data[:, window[0], window[1]],
                                          original.frames.data[:, window[0], window[1]])
        else:
            np.testing.assert_array_equal(reader.frames.data[:], original.frames.data[:])
            np.testing.assert_array_equal(reader.frames.roi, original.frames.roi)
        specials = original.specials()
        mapped = specials[specials["type"] != 0]  # TIMESTAMP_WRAP has no DV trigger type
        np.testing.assert_array_equal(reader.specials(), mapped)
        imu_back, imu = reader.imu(), original.imu()
        for name in imu.dtype.names:
            np.testing.assert_array_equal(imu_back[name], imu[name])


def test_dat_and_npz_files_read_by_the_reference_layouts(tmp_path, rich_session, labels_origin):
    """The files as their own ecosystems read them: Prophesee's record layout and masks, tonic's event type."""
    path, events, labels = rich_session
    export_session(path, "prophesee-dat", tmp_path / "x_td.dat")
    with open(tmp_path / "x_td.dat", "rb") as f:  # Prophesee's dat_events_tools.parse_header / load_td_data
        header = []
        while (line := f.readline()).startswith(b"% "):
            header.append(line.decode())
        f.seek(sum(len(h.encode()) for h in header))
        ev_type, ev_size = np.frombuffer(f.read(2), np.uint8)
        records = np.fromfile(f, dtype=[("t", "u4"), ("_", "i4")])
    assert (ev_type, ev_size) == (12, 8)
    assert "% Width 346\n" in header and "% Height 260\n" in header
    assert header[0] == "% Data file containing CD events\n"
    x = records["_"] & 16383
    y = (records["_"] & 268419072) >> 14
    p = (records["_"] & 268435456) >> 28
    with SessionReader(path) as reader:
        t_offset = reader.t_offset_us
    np.testing.assert_array_equal(records["t"].astype(np.int64) + t_offset, events["t"])
    np.testing.assert_array_equal(x, events["x"])
    np.testing.assert_array_equal(y, events["y"])
    np.testing.assert_array_equal(p, events["p"])
    boxes = np.load(tmp_path / "x_bbox.npy")
    np.testing.assert_array_equal(boxes["t"].astype(np.int64) + t_offset, labels["t"].astype(np.int64))
    np.testing.assert_allclose(boxes["x"], labels["x"] + labels_origin[0], atol=SHIFT_TOL_PX, rtol=0)

    export_session(path, "npz", tmp_path / "x.npz", crop=True)
    data = np.load(tmp_path / "x.npz")
    tonic_events_struct = np.dtype([("x", np.int16), ("y", np.int16), ("t", np.int64), ("p", bool)])
    assert data["events"].dtype == tonic_events_struct
    assert tuple(data["sensor_size"]) == (RVT_HW[1], RVT_HW[0], 2)
    inside = crop_events(events, labels_origin)
    np.testing.assert_array_equal(data["events"]["t"], inside["t"])
    np.testing.assert_array_equal(data["events"]["p"], inside["p"] == 1)
    np.testing.assert_array_equal(data["labels"], labels)  # the labels' own crop: untouched
