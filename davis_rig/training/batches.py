"""Chunks of preprocessed sequences for truncated BPTT (RVT's ``random``, ``stream`` and ``mixed`` sampling).

- :class:`RandomChunkDataset` (+ :func:`collate_chunks`, :class:`ResumableBatchSampler`): random-access chunks of
  L windows ending at a labelled window, the recurrent state reset for every sample (``sampling: random``);
- :class:`StreamingBatches`: whole sequences in chunks of L windows over B lanes (``sampling: stream``, validation);
- :class:`StreamingTrainLanes`: endless, resumable streaming lanes for training (the stream half of ``mixed``).

Every chunk is a :class:`ChunkBatch` (time-major) or an item of :func:`collate_chunks`; labels are converted by
:func:`labels_to_tensor`. The sequences are read through :class:`~davis_rig.training.dataset.SequenceData`.
torch is imported lazily.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from davis_rig._lazy import optional_import
from davis_rig.errors import FormatError
from davis_rig.training.dataset import NUM_CHANNELS, SequenceData, list_sequences
from davis_rig.types import RVT_HW

__all__ = [
    "ChunkBatch",
    "RandomChunkDataset",
    "ResumableBatchSampler",
    "StreamingBatches",
    "StreamingTrainLanes",
    "collate_chunks",
    "labels_to_tensor",
]


def _torch():
    return optional_import("torch", "training")


def labels_to_tensor(boxes: np.ndarray | None, *, min_side_px: float = 0.0):
    """Convert Prophesee boxes into the training format float32 [K, 5] ``(class, x, y, w, h)`` (px, top-left).

    Boxes are clipped to the 304×240 frame (RVT ``clamp_to_frame_``); boxes with a side ≤ ``min_side_px`` after
    clipping are dropped. ``None`` (unlabelled window) stays ``None``.
    """
    torch = _torch()
    if boxes is None:
        return None
    height, width = RVT_HW
    x1 = np.clip(boxes["x"].astype(np.float32), 0, width - 1)
    y1 = np.clip(boxes["y"].astype(np.float32), 0, height - 1)
    x2 = np.clip((boxes["x"] + boxes["w"]).astype(np.float32), 0, width - 1)
    y2 = np.clip((boxes["y"] + boxes["h"]).astype(np.float32), 0, height - 1)
    out = np.stack([boxes["class_id"].astype(np.float32), x1, y1, x2 - x1, y2 - y1], axis=1).reshape(-1, 5)
    keep = (out[:, 3] > min_side_px) & (out[:, 4] > min_side_px)
    return torch.from_numpy(np.ascontiguousarray(out[keep]))



@dataclass
class ChunkBatch:
    """A batch of sequence chunks for truncated BPTT.

    Attributes:
        histograms: uint8 tensor [L, B, 20, 240, 304].
        labels: L lists of B entries: float32 [K, 5] ``(class, x, y, w, h)`` or ``None`` (no supervision).
        is_first: bool tensor [B]: the chunk starts a sequence (reset the recurrent state).
        valid: bool tensor [L, B]: the window exists (padding at sequence ends is False).
        window_end_us: int64 tensor [L, B] (−1 for padding).
        sequence: B sequence indices (into the dataset's sequence list; −1 for an exhausted lane).
        window: int64 tensor [L, B] window indices within the sequence (−1 for padding).
    """

    histograms: Any
    labels: list[list[Any]]
    is_first: Any
    valid: Any
    window_end_us: Any
    sequence: list[int]
    window: Any




def _streaming_start(seq: SequenceData, seq_len: int) -> int:
    """First window a stream plays of ``seq`` (RVT): ``L − 1`` windows before its first labelled one, at least 0."""
    labelled = seq.labelled_windows()
    return max(int(labelled[0]) - (seq_len - 1), 0) if labelled.size else 0


def _chunk_item(seq: SequenceData, seq_index: int, start: int, seq_len: int, min_side_px: float,
                is_first: bool) -> dict[str, Any]:
    """Windows ``[start, start + L)`` of ``seq`` as an item of :func:`collate_chunks`, zero-padded past its end
    (``valid`` False, window and end time −1, no labels)."""
    torch = _torch()
    stop = min(start + seq_len, seq.num_windows)
    n = stop - start
    hist = np.zeros((seq_len, NUM_CHANNELS, *RVT_HW), dtype=np.uint8)
    hist[:n] = seq.histograms(start, stop)
    windows = np.full(seq_len, -1, dtype=np.int64)
    windows[:n] = np.arange(start, stop)
    ends = np.full(seq_len, -1, dtype=np.int64)
    ends[:n] = seq.window_end_us[start:stop]
    labels = [labels_to_tensor(seq.labels_at(w), min_side_px=min_side_px) if w >= 0 else None
              for w in windows.tolist()]
    return {"histograms": torch.from_numpy(hist), "labels": labels, "is_first": is_first,
            "valid": torch.from_numpy(windows >= 0), "window_end_us": torch.from_numpy(ends),
            "sequence": seq_index, "window": torch.from_numpy(windows)}


class RandomChunkDataset:
    """Random-access chunks of L consecutive windows ending at a labelled window (RVT ``sampling: random``).

    Every labelled window ``r`` of every sequence is one sample: windows ``[r − L + 1, r]`` (shifted right to
    start at 0 when the sequence has fewer windows before ``r``, so the chunk still contains ``r``; sequences
    shorter than L are zero-padded at the end with ``valid`` False). The recurrent state starts from zero for
    every sample (``is_first`` True), as in RVT's random sampling.

    A ``torch.utils.data.Dataset``-compatible map-style dataset (``__len__``/``__getitem__``).

    Args:
        root: dataset folder.
        split: split name.
        seq_len: chunk length L (windows).
        min_side_px: drop label boxes with a side ≤ this after clipping to the frame.

    Raises:
        FormatError: no sequence or no labelled window in the split.
    """

    def __init__(self, root: str | Path, split: str = "train", seq_len: int = 21, *, min_side_px: float = 0.0):
        if seq_len < 1:
            raise ValueError(f"seq_len: expected ≥ 1, got {seq_len}")
        self.seq_len = int(seq_len)
        self.min_side_px = float(min_side_px)
        self.sequences = [SequenceData(p) for p in list_sequences(root, split)]
        if not self.sequences:
            raise FormatError(f"{Path(root) / split}: no sequences")
        samples = []
        for seq_index, seq in enumerate(self.sequences):
            for window in seq.labelled_windows().tolist():
                start = max(0, min(window - self.seq_len + 1, seq.num_windows - self.seq_len))
                samples.append((seq_index, start))
        if not samples:
            raise FormatError(f"{Path(root) / split}: no labelled window")
        self.samples = np.asarray(samples, dtype=np.int64)

    def __len__(self) -> int:
        return int(self.samples.shape[0])

    def __getitem__(self, index: int) -> dict[str, Any]:
        seq_index, start = (int(v) for v in self.samples[index])
        return _chunk_item(self.sequences[seq_index], seq_index, start, self.seq_len, self.min_side_px, True)


def collate_chunks(items: Sequence[Mapping[str, Any]]) -> ChunkBatch:
    """Stack samples of :class:`RandomChunkDataset` into a time-major :class:`ChunkBatch`."""
    torch = _torch()
    seq_len = len(items[0]["labels"])
    return ChunkBatch(
        histograms=torch.stack([item["histograms"] for item in items], dim=1),
        labels=[[item["labels"][t] for item in items] for t in range(seq_len)],
        is_first=torch.tensor([bool(item["is_first"]) for item in items]),
        valid=torch.stack([item["valid"] for item in items], dim=1),
        window_end_us=torch.stack([item["window_end_us"] for item in items], dim=1),
        sequence=[int(item["sequence"]) for item in items],
        window=torch.stack([item["window"] for item in items], dim=1),
    )


class StreamingBatches:
    """Stream whole sequences in chunks of L windows over B parallel lanes (RVT ``sampling: stream``).

    Sequences are dealt round-robin to the lanes; each lane plays its sequences one after the other, every
    sequence from window ``max(first_labelled − (L − 1), 0)`` (RVT's streaming start) to its end. A lane's chunk
    that starts a sequence has ``is_first`` True (reset the state); a lane whose sequences are exhausted, and the
    tail after a sequence's end, are padding (``valid`` False). A chunk never spans two sequences.

    Args:
        root: dataset folder.
        split: split name.
        seq_len: chunk length L.
        batch_size: lanes B.
        min_side_px: as :func:`labels_to_tensor`.
        sequences: use these already-open sequences instead of listing ``root``/``split``.
    """

    def __init__(self, root: str | Path | None, split: str = "val", seq_len: int = 21, batch_size: int = 1, *,
                 min_side_px: float = 0.0, sequences: Sequence[SequenceData] | None = None):
        self.seq_len = int(seq_len)
        self.batch_size = int(batch_size)
        self.min_side_px = float(min_side_px)
        self.sequences = list(sequences) if sequences is not None else [
            SequenceData(p) for p in list_sequences(root, split)]
        if self.seq_len < 1 or self.batch_size < 1:
            raise ValueError(f"seq_len and batch_size must be ≥ 1, got {seq_len}, {batch_size}")

    def _lane_chunks(self, lane: int) -> list[tuple[int, int, int, bool]]:
        chunks = []
        for seq_index in range(lane, len(self.sequences), self.batch_size):
            seq = self.sequences[seq_index]
            first = _streaming_start(seq, self.seq_len)
            for k, start in enumerate(range(first, seq.num_windows, self.seq_len)):
                chunks.append((seq_index, start, min(start + self.seq_len, seq.num_windows), k == 0))
        return chunks

    def __len__(self) -> int:
        return max((len(self._lane_chunks(lane)) for lane in range(self.batch_size)), default=0)

    def __iter__(self) -> Iterator[ChunkBatch]:
        torch = _torch()
        lanes = [self._lane_chunks(lane) for lane in range(self.batch_size)]
        steps = max((len(c) for c in lanes), default=0)
        length, batch = self.seq_len, self.batch_size
        for step in range(steps):
            hist = np.zeros((length, batch, NUM_CHANNELS, *RVT_HW), dtype=np.uint8)
            windows = np.full((length, batch), -1, dtype=np.int64)
            ends = np.full((length, batch), -1, dtype=np.int64)
            labels: list[list[Any]] = [[None] * batch for _ in range(length)]
            is_first = np.zeros(batch, dtype=bool)
            sequence = [-1] * batch
            for lane, chunks in enumerate(lanes):
                if step >= len(chunks):
                    continue
                seq_index, start, stop, first = chunks[step]
                seq = self.sequences[seq_index]
                n = stop - start
                hist[:n, lane] = seq.histograms(start, stop)
                windows[:n, lane] = np.arange(start, stop)
                ends[:n, lane] = seq.window_end_us[start:stop]
                for t in range(n):
                    labels[t][lane] = labels_to_tensor(seq.labels_at(start + t), min_side_px=self.min_side_px)
                is_first[lane] = first
                sequence[lane] = seq_index
            yield ChunkBatch(histograms=torch.from_numpy(hist), labels=labels, is_first=torch.from_numpy(is_first),
                             valid=torch.from_numpy(windows >= 0), window_end_us=torch.from_numpy(ends),
                             sequence=sequence, window=torch.from_numpy(windows))


class ResumableBatchSampler:
    """Shuffled batches of sample indices with a position that can be saved and restored exactly.

    Epoch ``e`` uses the permutation drawn from ``seed + e``; incomplete last batches are dropped (when the
    dataset has fewer samples than one batch, indices wrap around so every batch is full).

    Args:
        num_samples: dataset length.
        batch_size: samples per batch.
        seed: base seed.
    """

    def __init__(self, num_samples: int, batch_size: int, seed: int = 0):
        if num_samples < 1 or batch_size < 1:
            raise ValueError(f"num_samples and batch_size must be ≥ 1, got {num_samples}, {batch_size}")
        self.num_samples = int(num_samples)
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.epoch = 0
        self.position = 0  # batches already handed out in this epoch

    @property
    def batches_per_epoch(self) -> int:
        return max(self.num_samples // self.batch_size, 1)

    def _epoch_batches(self, epoch: int) -> np.ndarray:
        rng = np.random.default_rng(self.seed + epoch)
        order = rng.permutation(self.num_samples)
        needed = self.batches_per_epoch * self.batch_size
        if needed > order.shape[0]:
            order = np.resize(order, needed)
        return order[:needed].reshape(self.batches_per_epoch, self.batch_size)

    def state_dict(self) -> dict[str, int]:
        return {"epoch": self.epoch, "position": self.position, "seed": self.seed}

    def load_state_dict(self, state: Mapping[str, int]) -> None:
        self.epoch, self.position = int(state["epoch"]), int(state["position"])
        self.seed = int(state.get("seed", self.seed))

    def __iter__(self) -> Iterator[list[int]]:
        while True:
            batches = self._epoch_batches(self.epoch)
            while self.position < batches.shape[0]:
                batch = batches[self.position].tolist()
                self.position += 1
                yield batch
            self.epoch += 1
            self.position = 0

    def __len__(self) -> int:  # an "infinite" sampler; DataLoader only needs a length hint
        return 2**62


class StreamingTrainLanes:
    """Endless streaming lanes for training (the ``stream`` half of RVT's ``mixed`` sampling), resumable.

    Each lane plays the sequences in its own shuffled order (a new permutation per lane and pass), each
    sequence from ``max(first_labelled − (L − 1), 0)`` to its end in chunks of L windows; the recurrent state
    is carried between a lane's consecutive chunks and reset when the lane starts a sequence (``is_first``).
    The last chunk of a sequence is zero-padded (``valid`` False).

    Args:
        sequences: the training sequences.
        seq_len: chunk length L.
        num_lanes: lanes (the stream part of the batch).
        seed: base seed of the lane permutations.
        min_side_px: as :func:`labels_to_tensor`.
    """

    def __init__(self, sequences: Sequence[SequenceData], seq_len: int, num_lanes: int, seed: int = 0,
                 min_side_px: float = 0.0):
        if not sequences or num_lanes < 1 or seq_len < 1:
            raise ValueError("StreamingTrainLanes: needs sequences, num_lanes ≥ 1 and seq_len ≥ 1")
        self.sequences = list(sequences)
        self.seq_len = int(seq_len)
        self.num_lanes = int(num_lanes)
        self.seed = int(seed)
        self.min_side_px = float(min_side_px)
        # per lane: [pass, position in the pass's permutation, next window start (−1 = start a new sequence)]
        self.lanes = [[0, 0, -1] for _ in range(self.num_lanes)]

    def _order(self, lane: int, epoch: int) -> np.ndarray:
        return np.random.default_rng((self.seed, lane, epoch)).permutation(len(self.sequences))

    def state_dict(self) -> dict[str, Any]:
        return {"seed": self.seed, "lanes": [list(lane) for lane in self.lanes]}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        lanes = [list(map(int, lane)) for lane in state["lanes"]]
        if len(lanes) != self.num_lanes:
            raise FormatError(f"stream state has {len(lanes)} lanes, this sampler {self.num_lanes}")
        self.seed, self.lanes = int(state["seed"]), lanes

    def next_items(self) -> list[dict[str, Any]]:
        """One chunk per lane, as items of :func:`collate_chunks` (plus ``"lane"``)."""
        items = []
        for lane_index, lane in enumerate(self.lanes):
            epoch, position, start = lane
            seq_index = int(self._order(lane_index, epoch)[position])
            seq = self.sequences[seq_index]
            is_first = start < 0
            if is_first:
                start = _streaming_start(seq, self.seq_len)
            stop = min(start + self.seq_len, seq.num_windows)
            item = _chunk_item(seq, seq_index, start, self.seq_len, self.min_side_px, is_first)
            items.append({**item, "lane": lane_index})
            if stop >= seq.num_windows:  # sequence done: next one (next pass after the last)
                position += 1
                if position >= len(self.sequences):
                    epoch, position = epoch + 1, 0
                lane[:] = [epoch, position, -1]
            else:
                lane[:] = [epoch, position, stop]
        return items
