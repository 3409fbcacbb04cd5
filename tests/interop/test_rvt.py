"""RVT export: the files RVT's loaders read, with davis-eval's windows and RVT's exact histograms and label rules."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.events.crop import crop_events
from davis_rig.events.histogram import stacked_histograms
from davis_rig.interop import export_session
from davis_rig.interop.rvt import labelled_frames
from davis_rig.session import SessionReader
from davis_rig.training.dataset import EV_REPR_NAME, SequenceData, list_sequences
from davis_rig.types import BBOX_DTYPE


def test_layout_histograms_and_labels(tmp_path, rich_session, labels_origin, monkeypatch):
    monkeypatch.setattr("davis_rig.interop.rvt.CHUNK_WINDOWS", 3)  # several reads, windows spanning them
    path, events, labels = rich_session
    summary = export_session(path, "rvt", tmp_path / "ds", split="val")
    seq = tmp_path / "ds" / "val" / "rich"
    assert summary.outputs == (str(seq),) and summary.origin_xy == labels_origin
    assert list_sequences(tmp_path / "ds", "val") == [seq]
    assert sorted(p.name for p in (tmp_path / "ds").iterdir()) == ["val"]  # nothing else where RVT looks

    with SessionReader(path) as reader:
        t0 = reader.t_offset_us
    repr_dir = seq / "event_representations_v2" / EV_REPR_NAME
    ends = np.load(repr_dir / "timestamps_us.npy")
    assert ends.dtype == np.int64 and np.all(np.diff(ends) == 50_000) and ends[0] == 50_000
    assert ends[-1] >= max(int(events["t"][-1]), int(labels["t"].max())) - t0  # past the last event and label
    with h5py.File(repr_dir / "event_representations.h5", "r") as f:
        data = f["data"]
        assert data.dtype == np.uint8 and data.shape == (len(ends), 20, 240, 304) and data.chunks == (1, 20, 240, 304)
        hists = data[:]
    expected = stacked_histograms(crop_events(events, labels_origin), ends + t0)
    np.testing.assert_array_equal(hists, expected)

    # RVT's loader: objframe_idx_2_label_idx.numel() == np.unique(labels['t']).size; one frame per window
    npz = np.load(seq / "labels_v2" / "labels.npz")
    rvt_labels, starts = npz["labels"], npz["objframe_idx_2_label_idx"]
    frame_windows = np.load(repr_dir / "objframe_idx_2_repr_idx.npy")
    frame_t = np.load(seq / "labels_v2" / "timestamps_us.npy")
    assert starts.dtype == np.int64 and frame_windows.dtype == np.int64 and rvt_labels.dtype == BBOX_DTYPE
    assert len(starts) == len(np.unique(rvt_labels["t"])) == len(frame_windows) == len(frame_t)
    assert np.all(np.diff(frame_windows) > 0)
    for f, (start, stop) in enumerate(zip(starts, np.append(starts[1:], len(rvt_labels)))):
        assert np.all(rvt_labels["t"][start:stop] == frame_t[f])
        end = ends[frame_windows[f]]
        assert end - 50_000 < frame_t[f] <= end  # the label lies in its window (davis-eval's rule)
    # 40 ms labels in 50 ms windows: every window with labels keeps exactly its latest label time
    label_t = np.unique(labels["t"].astype(np.int64)) - t0
    window_of = np.searchsorted(ends, label_t, side="left")
    latest = {w: t for w, t in zip(window_of, label_t)}
    np.testing.assert_array_equal(frame_t, [latest[w] for w in sorted(latest)])
    assert summary.extra["label_times_left_out"] == len(label_t) - len(latest) > 0
    kept = labels[np.isin(labels["t"].astype(np.int64) - t0, frame_t)]
    kept = kept[np.argsort(kept["t"], kind="stable")]
    np.testing.assert_array_equal(rvt_labels["x"], kept["x"])  # the labels' own crop: untouched
    np.testing.assert_array_equal(rvt_labels["t"].astype(np.int64), kept["t"].astype(np.int64) - t0)

    meta = json.loads((seq / "meta.json").read_text())
    assert meta["t_offset_us"] == t0 and meta["crop_origin_xy"] == list(labels_origin)
    sequence = SequenceData(seq)  # davis_rig's own RVT-layout reader
    assert len(sequence) == len(ends) and sequence.is_labelled(int(frame_windows[0]))
    np.testing.assert_array_equal(sequence.histograms(0, 2), expected[:2])


def test_labelled_frames_keeps_the_latest_time_per_window():
    labels = np.zeros(6, BBOX_DTYPE)
    labels["t"] = [130, 20, 40, 40, 60, 500]  # windows (0, 50], (50, 100], (100, 150]; 500 is outside
    labels["x"] = [6, 1, 2, 3, 4, 5]
    frame_labels, frame_window, frame_t, frame_start = labelled_frames(labels, np.array([50, 100, 150]), 50)
    assert frame_window.tolist() == [0, 1, 2] and frame_t.tolist() == [40, 60, 130]
    assert frame_labels["x"].tolist() == [2, 3, 4, 6] and frame_start.tolist() == [0, 2, 3]


def test_refusals_and_nothing_left_behind(tmp_path, rich_session, monkeypatch):
    path, _, _ = rich_session
    export_session(path, "rvt", tmp_path / "ds")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with pytest.raises(FormatError, match="sequence exists"):
        export_session(path, "rvt", tmp_path / "ds")

    def broken(*args, **kwargs):
        yield from ()
        raise OSError("disk full")

    monkeypatch.setattr("davis_rig.evaluation.windows.event_chunks", broken)
    with pytest.raises(OSError, match="disk full"):
        export_session(path, "rvt", tmp_path / "ds", overwrite=True)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # the old sequence is intact


def test_a_session_without_labels_is_refused(tmp_path, rich_session):
    from davis_rig.session import SessionWriter

    with SessionWriter(tmp_path / "bare.h5") as writer:
        with SessionReader(rich_session[0]) as reader:
            writer.append_events(reader.events())
    with pytest.raises(FormatError, match="no labels"):
        export_session(tmp_path / "bare.h5", "rvt", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()
