"""RVT-layout dataset: writer ↔ reader round trip, the card, chunk samplers and the resumable batch sampler."""

from __future__ import annotations

import json

import numpy as np
import pytest

from davis_rig.errors import FormatError, ShapeError
from davis_rig.training.batches import (
    RandomChunkDataset,
    ResumableBatchSampler,
    StreamingBatches,
    StreamingTrainLanes,
    collate_chunks,
)
from davis_rig.training.dataset import EV_REPR_NAME, DatasetWriter, SequenceData, list_sequences
from davis_rig.types import BBOX_DTYPE


def _boxes(t_us, rows):
    out = np.zeros(len(rows), BBOX_DTYPE)
    for i, (x, y, w, h) in enumerate(rows):
        out[i] = (t_us, x, y, w, h, 1, 1.0, i)
    return out


def _random_hist(seed, n):
    return np.random.default_rng(seed).integers(0, 11, size=(n, 20, 240, 304), dtype=np.uint8)


@pytest.mark.parametrize("compression", ["blosc-zstd", "gzip", "none"])
def test_round_trip_rvt_layout(tmp_path, compression):
    hist = _random_hist(0, 5)
    ends = np.array([50_000, 100_000, 150_000, 200_000, 250_000])
    labels = [None, _boxes(100_000, [(10, 20, 30, 40)]), np.zeros(0, BBOX_DTYPE), None,
              _boxes(250_000, [(1, 2, 3, 4), (50, 60, 70, 80)])]
    with DatasetWriter(tmp_path / "ds", name="t", compression=compression) as writer:
        seq_dir = writer.add_sequence(hist, ends, labels, {"seed": 7}, split="val", name="a")
    repr_dir = seq_dir / "event_representations_v2" / EV_REPR_NAME
    assert EV_REPR_NAME == "stacked_histogram_dt=50_nbins=10"
    for path in (repr_dir / "event_representations.h5", repr_dir / "timestamps_us.npy",
                 repr_dir / "objframe_idx_2_repr_idx.npy", seq_dir / "labels_v2" / "labels.npz",
                 seq_dir / "labels_v2" / "timestamps_us.npy"):
        assert path.is_file(), path
    with np.load(seq_dir / "labels_v2" / "labels.npz") as data:
        assert data["objframe_idx_2_label_idx"].tolist() == [0, 1, 1]
        assert data["labels"].dtype == BBOX_DTYPE
    seq = SequenceData(seq_dir)
    assert np.array_equal(seq.histograms(0, 5), hist)
    assert np.array_equal(seq.histograms(2, 4), hist[2:4])
    assert seq.window_end_us.tolist() == ends.tolist()
    assert seq.objframe_idx_2_repr_idx.tolist() == [1, 2, 4]
    assert seq.label_timestamps_us.tolist() == [100_000, 150_000, 250_000]
    assert seq.labels_at(0) is None and seq.labels_at(3) is None
    assert seq.labels_at(2).shape == (0,)
    assert np.array_equal(seq.labels_at(1), labels[1]) and np.array_equal(seq.labels_at(4), labels[4])
    seq.close()
    card = json.loads((tmp_path / "ds" / "dataset_card.json").read_text())
    assert card["splits"]["val"] == {"sequences": 1, "windows": 5, "labelled_frames": 3, "empty_frames": 1,
                                     "boxes": 3, "boxes_per_class": {"pedestrian": 3},
                                     "duration_s": pytest.approx(0.25),
                                     "size_bytes": card["splits"]["val"]["size_bytes"], "seeds": [7]}
    assert card["classes"] == {"0": "car", "1": "pedestrian"}
    assert json.loads((seq_dir / "meta.json").read_text()) == {"seed": 7}


def test_labels_as_mapping_and_validation_errors(tmp_path):
    hist = _random_hist(1, 3)
    ends = np.array([50_000, 100_000, 150_000])
    with DatasetWriter(tmp_path / "ds", compression="lzf") as writer:
        path = writer.add_sequence(hist, ends, {2: _boxes(150_000, [(0, 0, 5, 5)])}, name="m")
        assert SequenceData(path).objframe_idx_2_repr_idx.tolist() == [2]
        with pytest.raises(ShapeError):
            writer.add_sequence(hist[:, :10], ends, [None] * 3)
        with pytest.raises(ShapeError):
            writer.add_sequence(hist.astype(np.float32), ends, [None] * 3)
        with pytest.raises(ShapeError):
            writer.add_sequence(hist, ends, [None] * 2)
        with pytest.raises(FormatError):
            writer.add_sequence(hist, ends[::-1], [None] * 3)
        with pytest.raises(FormatError):
            writer.add_sequence(hist, ends, [None] * 3, name="m")
        with pytest.raises(FormatError):
            writer.add_sequence(hist, ends, [None] * 3, split="training")
        with pytest.raises(FormatError):
            writer.add_sequence(hist, ends, {5: _boxes(0, [])})
    with pytest.raises(FormatError):
        writer.add_sequence(hist, ends, [None] * 3)
    with pytest.raises(FormatError):  # refuses to mix into an existing dataset
        DatasetWriter(tmp_path / "ds")
    with pytest.raises(FormatError):
        list_sequences(tmp_path / "ds", "test")


def test_random_chunks_end_at_labelled_windows(moving_boxes_dataset):
    dataset = RandomChunkDataset(moving_boxes_dataset, "train", seq_len=3)
    assert len(dataset) == 4 * 8  # every window of every sequence is labelled
    item = dataset[5]
    seq, start = (int(v) for v in dataset.samples[5])
    assert item["histograms"].shape == (3, 20, 240, 304) and item["is_first"]
    assert np.array_equal(item["histograms"].numpy(), dataset.sequences[seq].histograms(start, start + 3))
    assert item["window"].tolist() == [start, start + 1, start + 2]
    assert all(lab is not None and lab.shape[1] == 5 for lab in item["labels"])
    batch = collate_chunks([dataset[0], dataset[9]])
    assert batch.histograms.shape == (3, 2, 20, 240, 304) and batch.valid.all()
    # the first labelled window (index 0) gets a chunk starting at 0 that still contains it
    assert dataset.samples[0].tolist() == [0, 0]


def test_random_chunks_pad_short_sequences(moving_boxes_dataset):
    dataset = RandomChunkDataset(moving_boxes_dataset, "train", seq_len=10)
    item = dataset[0]
    assert item["valid"].tolist() == [True] * 8 + [False] * 2
    assert item["labels"][8] is None and item["histograms"][8:].sum() == 0


def test_streaming_covers_every_window_once(moving_boxes_dataset):
    stream = StreamingBatches(moving_boxes_dataset, "train", seq_len=3, batch_size=2)
    seen = {}
    firsts = []
    for batch in stream:
        for lane, seq in enumerate(batch.sequence):
            if seq < 0:
                continue
            windows = batch.window[:, lane][batch.valid[:, lane]].tolist()
            seen.setdefault(seq, []).extend(windows)
            firsts.append((seq, bool(batch.is_first[lane]), windows[0]))
    assert {k: v for k, v in seen.items()} == {s: list(range(8)) for s in range(4)}
    assert all(first == (window == 0) for _, first, window in firsts)
    assert len(stream) == 6  # 2 sequences per lane × ceil(8 / 3) chunks


def test_resumable_sampler_continues_exactly():
    sampler = ResumableBatchSampler(10, 3, seed=5)
    it = iter(sampler)
    head = [next(it) for _ in range(4)]  # crosses an epoch (3 batches per epoch)
    state = sampler.state_dict()
    tail = [next(it) for _ in range(5)]
    other = ResumableBatchSampler(10, 3, seed=5)
    other.load_state_dict(state)
    it2 = iter(other)
    assert [next(it2) for _ in range(5)] == tail
    assert sorted(sum(head[:3], [])) == sorted(set(sum(head[:3], [])))  # no repeats within an epoch
    small = iter(ResumableBatchSampler(2, 4))
    assert len(next(small)) == 4


def test_streaming_train_lanes_play_whole_sequences_and_resume(moving_boxes_dataset):
    sequences = [SequenceData(p) for p in list_sequences(moving_boxes_dataset, "train")]
    lanes = StreamingTrainLanes(sequences, seq_len=3, num_lanes=2, seed=1)
    played = {0: [], 1: []}
    states = []
    for _ in range(12):  # 3 chunks per 8-window sequence -> 4 sequences per lane = one full pass
        states.append(lanes.state_dict())
        for item in lanes.next_items():
            windows = item["window"][item["valid"]].tolist()
            if item["is_first"]:
                played[item["lane"]].append((item["sequence"], []))
            played[item["lane"]][-1][1].extend(windows)
    for lane in (0, 1):
        assert sorted(seq for seq, _ in played[lane]) == [0, 1, 2, 3]  # every sequence once per pass
        assert all(windows == list(range(8)) for _, windows in played[lane])
    other = StreamingTrainLanes(sequences, seq_len=3, num_lanes=2, seed=1)
    other.load_state_dict(states[5])
    lanes.load_state_dict(states[5])
    a, b = lanes.next_items(), other.next_items()
    assert [(i["sequence"], i["window"].tolist(), i["is_first"]) for i in a] == [
        (i["sequence"], i["window"].tolist(), i["is_first"]) for i in b]


def test_labels_to_tensor_clips_to_frame_and_drops_small():
    from davis_rig.training.batches import labels_to_tensor

    boxes = _boxes(0, [(-10, 5, 30, 40), (300, 230, 20, 20), (100, 100, 2, 50)])
    out = labels_to_tensor(boxes, min_side_px=2.5)
    # clipped to [0, 303] x [0, 239] (RVT clamp_to_frame_); the 2 px wide box is dropped
    assert out.tolist() == [[1.0, 0.0, 5.0, 20.0, 40.0], [1.0, 300.0, 230.0, 3.0, 9.0]]
    assert labels_to_tensor(None) is None


@pytest.mark.parametrize("damage", ["truncated labels", "empty timestamps"])
def test_damaged_sequence_files_are_a_format_error(tmp_path, damage):
    from davis_rig.errors import FormatError

    ends = np.array([50_000, 100_000])
    with DatasetWriter(tmp_path / "ds", name="t") as writer:
        seq_dir = writer.add_sequence(_random_hist(0, 2), ends, [None, _boxes(100_000, [(1, 2, 3, 4)])], {},
                                      split="val", name="a")
    if damage == "truncated labels":
        labels = seq_dir / "labels_v2" / "labels.npz"
        labels.write_bytes(labels.read_bytes()[:20])
    else:
        (seq_dir / "event_representations_v2" / EV_REPR_NAME / "timestamps_us.npy").write_bytes(b"")
    with pytest.raises(FormatError, match="unreadable sequence files"):
        SequenceData(seq_dir)
