"""Detection datasets in RVT's preprocessed layout: writer, per-sequence reader, chunk samplers for TBPTT.

On-disk layout (the one RVT's ``data/genx_utils`` reads, so a preprocessed Gen1 folder also works)::

    ROOT/
      dataset_card.json                       (written by DatasetWriter; optional for reading)
      train/ val/ test/                       (splits)
        SEQUENCE/
          event_representations_v2/stacked_histogram_dt=50_nbins=10/
            event_representations.h5          dataset "data": uint8 [N, 20, 240, 304], compressed
            timestamps_us.npy                 int64 [N]: window end times, µs
            objframe_idx_2_repr_idx.npy       int64 [F]: window index of each labelled frame
          labels_v2/
            labels.npz                        "labels": BBOX_DTYPE [K]; "objframe_idx_2_label_idx": int64 [F]
            timestamps_us.npy                 int64 [F]: time of each labelled frame, µs
          meta.json                           (davis_rig extension: the generator's per-sequence metadata)

The labels of labelled frame ``f`` are ``labels[objframe_idx_2_label_idx[f] : objframe_idx_2_label_idx[f + 1]]``
(the last frame runs to the end). A labelled frame may hold zero boxes (a window known to contain no object, e.g.
an empty synthetic scene); windows that are not a labelled frame carry no supervision.

Torch-facing parts (:class:`RandomChunkDataset`, :class:`StreamingBatches`) import torch lazily.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from davis_rig.errors import FormatError, MissingDependencyError, ShapeError
from davis_rig.types import BBOX_DTYPE, GEN1_CLASSES, RVT_HW

__all__ = [
    "EV_REPR_NAME",
    "SPLITS",
    "DatasetWriter",
    "SequenceData",
    "list_sequences",
    "RandomChunkDataset",
    "StreamingBatches",
    "StreamingTrainLanes",
    "ResumableBatchSampler",
    "ChunkBatch",
    "collate_chunks",
    "labels_to_tensor",
]

#: RVT's representation folder name (``dataset.ev_repr_name`` of the Gen1 experiment config).
EV_REPR_NAME = "stacked_histogram_dt=50_nbins=10"
#: Other spellings accepted when reading (e.g. a file system where '=' was replaced).
_EV_REPR_ALIASES = (EV_REPR_NAME, "stacked_histogram_dt50_nbins10")
#: Dataset splits, as in RVT's preprocessed Gen1 folder.
SPLITS = ("train", "val", "test")
#: Channels of one stacked histogram (2 polarities × 10 bins).
NUM_CHANNELS = 20
DATASET_CARD_FORMAT = "davis_rig-dataset-card/1"


def _h5py():
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - h5py is a core dependency
        raise MissingDependencyError("datasets need h5py: pip install h5py") from exc
    try:  # registers the Blosc filter RVT's preprocessing uses; optional for gzip files
        import hdf5plugin  # noqa: F401
    except ImportError:  # pragma: no cover
        pass
    return h5py


def _compression_kwargs(compression: str) -> dict[str, Any]:
    if compression == "blosc-zstd":
        try:
            import hdf5plugin
        except ImportError:
            compression = "gzip"
        else:
            return dict(hdf5plugin.Blosc(cname="zstd", clevel=1, shuffle=hdf5plugin.Blosc.SHUFFLE))
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 1}
    if compression == "lzf":
        return {"compression": "lzf"}
    if compression == "none":
        return {}
    raise ValueError(f"compression: expected 'blosc-zstd', 'gzip', 'lzf' or 'none', got {compression!r}")


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


# ---------------------------------------------------------------------------------------------------- writer
class DatasetWriter:
    """Write sequences of stacked histograms and box labels in RVT's layout, plus a dataset card.

    A context manager: ``close()`` (or leaving the ``with`` block) writes ``dataset_card.json`` with the counts
    (sequences, windows, labelled frames, boxes per class and split), sizes on disk, and the seeds and
    metadata passed to :meth:`add_sequence`.

    Args:
        root: dataset folder (created).
        name: dataset name for the card.
        description: free text for the card (how the data were made).
        overwrite: allow writing into a folder that already holds sequences.
        compression: ``"blosc-zstd"`` (RVT's choice, via hdf5plugin), ``"gzip"``, ``"lzf"`` or ``"none"``.
        card_extra: more JSON-able entries for the card (generator version, scene parameters, ...).

    Example:
        >>> with DatasetWriter(tmp_path / "ds", name="demo") as writer:  # doctest: +SKIP
        ...     writer.add_sequence(hist, ends_us, labels, meta={"seed": 1}, split="train")
    """

    def __init__(
        self,
        root: str | Path,
        *,
        name: str = "davis_rig-synthetic",
        description: str = "",
        overwrite: bool = False,
        compression: str = "blosc-zstd",
        card_extra: Mapping[str, Any] | None = None,
    ):
        self.root = Path(root)
        self.name = name
        self.description = description
        self.overwrite = overwrite
        self.compression = compression
        self.card_extra = dict(card_extra or {})
        self._h5_kwargs = _compression_kwargs(compression)
        self._records: list[dict[str, Any]] = []
        self._closed = False
        if self.root.exists() and not overwrite and any(
            (self.root / split).is_dir() and any((self.root / split).iterdir()) for split in SPLITS
        ):
            raise FormatError(f"{self.root}: already holds sequences (pass overwrite=True to add or replace)")
        self.root.mkdir(parents=True, exist_ok=True)

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def add_sequence(
        self,
        histograms: np.ndarray,
        window_end_us,
        labels: Sequence[np.ndarray | None] | Mapping[int, np.ndarray],
        meta: Mapping[str, Any] | None = None,
        *,
        split: str = "train",
        name: str | None = None,
    ) -> Path:
        """Write one sequence.

        Args:
            histograms: uint8 [T, 20, 240, 304] stacked histograms (``events.histogram.stacked_histograms``).
            window_end_us: int [T], strictly increasing window end times, µs.
            labels: per window, a BBOX_DTYPE array (this window is a labelled frame; may be empty = no object)
                or ``None`` (no supervision); or a mapping ``{window index: BBOX_DTYPE array}``. Box times are
                set to the window's end time; boxes are in the 304×240 frame (x, y = top-left corner, px).
            meta: JSON-able per-sequence metadata (seed, scene parameters, clothing, distance...), saved to
                ``meta.json`` and summarised in the card.
            split: ``"train"``, ``"val"`` or ``"test"``.
            name: sequence folder name; default ``seq_{index:05d}``.

        Returns:
            The sequence folder.

        Raises:
            ShapeError: wrong histogram shape/dtype or lengths that do not match.
            FormatError: unknown split, non-increasing times, bad label arrays, an existing sequence name, or a
                closed writer.
        """
        if self._closed:
            raise FormatError("DatasetWriter: add_sequence after close()")
        if split not in SPLITS:
            raise FormatError(f"split: expected one of {SPLITS}, got {split!r}")
        hist = np.asarray(histograms)
        if hist.dtype != np.uint8 or hist.ndim != 4 or hist.shape[1:] != (NUM_CHANNELS, *RVT_HW):
            raise ShapeError(
                f"histograms: expected uint8 [T, {NUM_CHANNELS}, {RVT_HW[0]}, {RVT_HW[1]}], got {hist.dtype} "
                f"{tuple(hist.shape)}"
            )
        num_windows = int(hist.shape[0])
        ends = np.asarray(window_end_us).astype(np.int64)
        if ends.shape != (num_windows,):
            raise ShapeError(f"window_end_us: expected shape ({num_windows},), got {ends.shape}")
        if num_windows == 0:
            raise ShapeError("histograms: a sequence needs at least one window")
        if num_windows > 1 and np.any(np.diff(ends) <= 0):
            raise FormatError("window_end_us: must be strictly increasing")
        frame_windows, frame_labels = self._normalise_labels(labels, num_windows)
        name = name if name is not None else f"seq_{len(self._records):05d}"
        seq_dir = self.root / split / name
        if seq_dir.exists():
            if not self.overwrite:
                raise FormatError(f"{seq_dir}: sequence exists (pass overwrite=True to replace)")
            shutil.rmtree(seq_dir)
        repr_dir = seq_dir / "event_representations_v2" / EV_REPR_NAME
        labels_dir = seq_dir / "labels_v2"
        repr_dir.mkdir(parents=True)
        labels_dir.mkdir(parents=True)

        h5py = _h5py()
        with h5py.File(repr_dir / "event_representations.h5", "w") as h5f:
            h5f.create_dataset("data", data=hist, chunks=(1, NUM_CHANNELS, *RVT_HW), **self._h5_kwargs)
        np.save(repr_dir / "timestamps_us.npy", ends)
        objframe_idx_2_repr_idx = np.asarray(frame_windows, dtype=np.int64)
        np.save(repr_dir / "objframe_idx_2_repr_idx.npy", objframe_idx_2_repr_idx)

        counts = [len(boxes) for boxes in frame_labels]
        starts = np.zeros(len(counts), dtype=np.int64)
        if counts:
            starts[1:] = np.cumsum(counts)[:-1]
        all_labels = np.concatenate(frame_labels) if frame_labels else np.zeros(0, BBOX_DTYPE)
        all_labels = np.ascontiguousarray(all_labels.astype(BBOX_DTYPE, copy=False))
        np.savez(labels_dir / "labels.npz", labels=all_labels, objframe_idx_2_label_idx=starts)
        np.save(labels_dir / "timestamps_us.npy", ends[objframe_idx_2_repr_idx])
        meta = dict(meta or {})
        with open(seq_dir / "meta.json", "w", encoding="utf-8") as handle:
            json.dump(meta, handle, indent=1, default=_json_default)

        classes = all_labels["class_id"].astype(np.int64)
        size_bytes = sum(p.stat().st_size for p in seq_dir.rglob("*") if p.is_file())
        self._records.append({
            "split": split, "name": name, "windows": num_windows, "labelled_frames": len(frame_windows),
            "empty_frames": int(sum(c == 0 for c in counts)), "boxes": int(all_labels.shape[0]),
            "boxes_per_class": {GEN1_CLASSES.get(int(c), str(int(c))): int((classes == c).sum())
                                for c in np.unique(classes)},
            "duration_us": int(ends[-1] - ends[0]) + 50_000, "size_bytes": int(size_bytes),
            "seed": meta.get("seed"), "meta": meta,
        })
        return seq_dir

    @staticmethod
    def _normalise_labels(labels, num_windows: int) -> tuple[list[int], list[np.ndarray]]:
        if isinstance(labels, Mapping):
            items = sorted((int(k), v) for k, v in labels.items())
        else:
            if len(labels) != num_windows:
                raise ShapeError(f"labels: expected {num_windows} entries (one per window), got {len(labels)}")
            items = [(i, v) for i, v in enumerate(labels) if v is not None]
        windows, arrays = [], []
        for index, boxes in items:
            if not 0 <= index < num_windows:
                raise FormatError(f"labels: window index {index} outside [0, {num_windows})")
            boxes = np.asarray(boxes)
            if boxes.dtype.names is None or not set(BBOX_DTYPE.names) <= set(boxes.dtype.names) or boxes.ndim != 1:
                raise FormatError(f"labels[{index}]: expected a BBOX_DTYPE [K] array, got {boxes.dtype} {boxes.shape}")
            windows.append(index)
            arrays.append(boxes[list(BBOX_DTYPE.names)].astype(BBOX_DTYPE))
        return windows, arrays

    def close(self) -> Path:
        """Write ``dataset_card.json`` (idempotent) and return its path."""
        path = self.root / "dataset_card.json"
        if self._closed:
            return path
        self._closed = True
        write_dataset_card(self.root, self._records, name=self.name, description=self.description,
                           compression=self.compression, extra=self.card_extra)
        return path


def write_dataset_card(
    root: Path,
    records: Sequence[Mapping[str, Any]],
    *,
    name: str,
    description: str,
    compression: str,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Summarise per-sequence records into ``ROOT/dataset_card.json`` (the dataset card template).

    Args:
        root: dataset folder.
        records: one dict per sequence (keys as written by :meth:`DatasetWriter.add_sequence`).
        name, description, compression: card header entries.
        extra: more JSON-able entries (generator, scene parameter ranges, ...).

    Returns:
        The card path.
    """
    splits: dict[str, dict[str, Any]] = {}
    for record in records:
        entry = splits.setdefault(record["split"], {
            "sequences": 0, "windows": 0, "labelled_frames": 0, "empty_frames": 0, "boxes": 0,
            "boxes_per_class": {}, "duration_s": 0.0, "size_bytes": 0, "seeds": []})
        entry["sequences"] += 1
        for key in ("windows", "labelled_frames", "empty_frames", "boxes", "size_bytes"):
            entry[key] += int(record[key])
        entry["duration_s"] += record["duration_us"] / 1e6
        for cls, count in record["boxes_per_class"].items():
            entry["boxes_per_class"][cls] = entry["boxes_per_class"].get(cls, 0) + count
        if record.get("seed") is not None:
            entry["seeds"].append(record["seed"])
    card = {
        "format": DATASET_CARD_FORMAT,
        "name": name,
        "description": description,
        "layout": "RVT preprocessed (event_representations_v2/" + EV_REPR_NAME + ", labels_v2)",
        "representation": {"type": "stacked_histogram", "window_us": 50_000, "num_bins": 10, "count_cutoff": 10,
                            "channels": NUM_CHANNELS, "height": RVT_HW[0], "width": RVT_HW[1], "dtype": "uint8"},
        "classes": {str(k): v for k, v in GEN1_CLASSES.items()},
        "compression": compression,
        "splits": splits,
        "sequences": [{k: v for k, v in r.items() if k != "meta"} for r in records],
        **dict(extra or {}),
    }
    path = Path(root) / "dataset_card.json"
    with open(path, "w", encoding="utf-8") as handle:
        json.dump(card, handle, indent=1, default=_json_default)
    return path


# ---------------------------------------------------------------------------------------------------- reader
def _repr_dir(seq_dir: Path) -> Path:
    for alias in _EV_REPR_ALIASES:
        candidate = seq_dir / "event_representations_v2" / alias
        if candidate.is_dir():
            return candidate
    raise FormatError(f"{seq_dir}: no event_representations_v2/{EV_REPR_NAME} folder")


def list_sequences(root: str | Path, split: str | None = "train") -> list[Path]:
    """Sequence folders of one split (sorted by name).

    Args:
        root: dataset folder (with ``train/``, ``val/``, ``test/``), or a split folder when ``split`` is None.
        split: split name, or ``None`` to list ``root`` itself.

    Returns:
        Folders that contain ``event_representations_v2`` and ``labels_v2``.

    Raises:
        FormatError: the split folder does not exist.
    """
    base = Path(root) if split is None else Path(root) / split
    if not base.is_dir():
        raise FormatError(f"{base}: no such split folder (expected {Path(root)}/{{{','.join(SPLITS)}}})")
    return sorted(p for p in base.iterdir()
                  if (p / "event_representations_v2").is_dir() and (p / "labels_v2").is_dir())


class SequenceData:
    """Random access to one preprocessed sequence (histograms read lazily from the h5 file).

    Args:
        path: the sequence folder.

    Attributes:
        window_end_us: int64 [N] window end times, µs.
        objframe_idx_2_repr_idx: int64 [F] window index of every labelled frame.
        label_timestamps_us: int64 [F] times of the labelled frames, µs.

    Raises:
        FormatError: missing files or inconsistent indices.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        repr_dir = _repr_dir(self.path)
        self.h5_path = repr_dir / "event_representations.h5"
        if not self.h5_path.is_file():
            raise FormatError(f"{self.h5_path}: missing")
        try:
            self.window_end_us = np.load(repr_dir / "timestamps_us.npy").astype(np.int64)
            self.objframe_idx_2_repr_idx = np.load(repr_dir / "objframe_idx_2_repr_idx.npy").astype(np.int64)
            with np.load(self.path / "labels_v2" / "labels.npz") as data:
                self._labels = data["labels"]
                self._label_starts = data["objframe_idx_2_label_idx"].astype(np.int64)
        except (OSError, KeyError, ValueError) as exc:
            raise FormatError(f"{self.path}: unreadable sequence files ({exc})") from exc
        ts_path = self.path / "labels_v2" / "timestamps_us.npy"
        self.label_timestamps_us = (np.load(ts_path).astype(np.int64) if ts_path.is_file()
                                    else self.window_end_us[self.objframe_idx_2_repr_idx])
        num_frames = self.objframe_idx_2_repr_idx.shape[0]
        if self._label_starts.shape[0] != num_frames:
            raise FormatError(f"{self.path}: {num_frames} labelled frames but {self._label_starts.shape[0]} "
                              "label start indices")
        self.num_windows = int(self.window_end_us.shape[0])
        if num_frames and (self.objframe_idx_2_repr_idx.min() < 0
                           or self.objframe_idx_2_repr_idx.max() >= self.num_windows):
            raise FormatError(f"{self.path}: objframe_idx_2_repr_idx outside [0, {self.num_windows})")
        self._label_stops = np.append(self._label_starts[1:], self._labels.shape[0]).astype(np.int64)
        self._frame_of_window = np.full(self.num_windows, -1, dtype=np.int64)
        self._frame_of_window[self.objframe_idx_2_repr_idx] = np.arange(num_frames)
        self._h5 = None

    def __len__(self) -> int:
        return self.num_windows

    def __getstate__(self):  # picklable for DataLoader workers (the h5 handle is reopened there)
        state = dict(self.__dict__)
        state["_h5"] = None
        return state

    def close(self) -> None:
        """Close the h5 file if open."""
        if self._h5 is not None:
            self._h5.close()
            self._h5 = None

    def histograms(self, start: int, stop: int) -> np.ndarray:
        """uint8 [stop − start, 20, 240, 304] histograms of windows ``[start, stop)``."""
        if not 0 <= start <= stop <= self.num_windows:
            raise FormatError(f"{self.path}: windows [{start}, {stop}) outside [0, {self.num_windows}]")
        if self._h5 is None:
            self._h5 = _h5py().File(self.h5_path, "r")
        data = self._h5["data"][start:stop]
        return np.asarray(data, dtype=np.uint8)

    def is_labelled(self, window: int) -> bool:
        """Whether window ``window`` is a labelled frame."""
        return bool(self._frame_of_window[window] >= 0)

    def labelled_windows(self) -> np.ndarray:
        """int64 [F] indices of the labelled windows (sorted)."""
        return np.sort(self.objframe_idx_2_repr_idx)

    def labels_at(self, window: int) -> np.ndarray | None:
        """BBOX_DTYPE [K] boxes of window ``window``, or ``None`` if it is not a labelled frame."""
        frame = int(self._frame_of_window[window])
        if frame < 0:
            return None
        return self._labels[self._label_starts[frame]:self._label_stops[frame]].copy()

    def all_labels(self) -> np.ndarray:
        """All boxes of the sequence, BBOX_DTYPE, sorted by time (stable)."""
        labels = self._labels.astype(BBOX_DTYPE)
        return labels[np.argsort(labels["t"], kind="stable")]


def labels_to_tensor(boxes: np.ndarray | None, *, min_side_px: float = 0.0):
    """Convert Prophesee boxes into the training format float32 [K, 5] ``(class, x, y, w, h)`` (px, top-left).

    Boxes are clipped to the 304×240 frame (RVT ``clamp_to_frame_``); boxes with a side ≤ ``min_side_px`` after
    clipping are dropped. ``None`` (unlabelled window) stays ``None``.
    """
    import torch

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


# ---------------------------------------------------------------------------------------------------- torch side
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


def _torch():
    try:
        import torch
    except ImportError as exc:
        raise MissingDependencyError("training needs torch: pip install 'davis_rig[torch]'") from exc
    return torch


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
        torch = _torch()
        seq_index, start = (int(v) for v in self.samples[index])
        seq = self.sequences[seq_index]
        stop = min(start + self.seq_len, seq.num_windows)
        hist = np.zeros((self.seq_len, NUM_CHANNELS, *RVT_HW), dtype=np.uint8)
        hist[: stop - start] = seq.histograms(start, stop)
        windows = np.full(self.seq_len, -1, dtype=np.int64)
        windows[: stop - start] = np.arange(start, stop)
        ends = np.full(self.seq_len, -1, dtype=np.int64)
        ends[: stop - start] = seq.window_end_us[start:stop]
        labels = [labels_to_tensor(seq.labels_at(w), min_side_px=self.min_side_px) if w >= 0 else None
                  for w in windows.tolist()]
        return {"histograms": torch.from_numpy(hist), "labels": labels, "is_first": True,
                "valid": torch.from_numpy(windows >= 0), "window_end_us": torch.from_numpy(ends),
                "sequence": seq_index, "window": torch.from_numpy(windows)}


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
            labelled = seq.labelled_windows()
            first = max(int(labelled[0]) - (self.seq_len - 1), 0) if labelled.size else 0
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


def dataset_summary(root: str | Path) -> dict[str, Any]:
    """Counts per split read back from the files (sequences, windows, labelled frames, boxes)."""
    summary: dict[str, Any] = {}
    for split in SPLITS:
        if not (Path(root) / split).is_dir():
            continue
        seqs = [SequenceData(p) for p in list_sequences(root, split)]
        summary[split] = {
            "sequences": len(seqs),
            "windows": int(sum(s.num_windows for s in seqs)),
            "labelled_frames": int(sum(s.objframe_idx_2_repr_idx.shape[0] for s in seqs)),
            "boxes": int(sum(s.all_labels().shape[0] for s in seqs)),
        }
        for s in seqs:
            s.close()
    return summary


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

    def _first_window(self, seq: SequenceData) -> int:
        labelled = seq.labelled_windows()
        return max(int(labelled[0]) - (self.seq_len - 1), 0) if labelled.size else 0

    def state_dict(self) -> dict[str, Any]:
        return {"seed": self.seed, "lanes": [list(lane) for lane in self.lanes]}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        lanes = [list(map(int, lane)) for lane in state["lanes"]]
        if len(lanes) != self.num_lanes:
            raise FormatError(f"stream state has {len(lanes)} lanes, this sampler {self.num_lanes}")
        self.seed, self.lanes = int(state["seed"]), lanes

    def next_items(self) -> list[dict[str, Any]]:
        """One chunk per lane, as items of :func:`collate_chunks` (plus ``"lane"``)."""
        torch = _torch()
        items = []
        for lane_index, lane in enumerate(self.lanes):
            epoch, position, start = lane
            seq_index = int(self._order(lane_index, epoch)[position])
            seq = self.sequences[seq_index]
            is_first = start < 0
            if is_first:
                start = self._first_window(seq)
            stop = min(start + self.seq_len, seq.num_windows)
            n = stop - start
            hist = np.zeros((self.seq_len, NUM_CHANNELS, *RVT_HW), dtype=np.uint8)
            hist[:n] = seq.histograms(start, stop)
            windows = np.full(self.seq_len, -1, dtype=np.int64)
            windows[:n] = np.arange(start, stop)
            ends = np.full(self.seq_len, -1, dtype=np.int64)
            ends[:n] = seq.window_end_us[start:stop]
            labels = [labels_to_tensor(seq.labels_at(w), min_side_px=self.min_side_px) if w >= 0 else None
                      for w in windows.tolist()]
            items.append({"histograms": torch.from_numpy(hist), "labels": labels, "is_first": is_first,
                          "valid": torch.from_numpy(windows >= 0), "window_end_us": torch.from_numpy(ends),
                          "sequence": seq_index, "window": torch.from_numpy(windows), "lane": lane_index})
            if stop >= seq.num_windows:  # sequence done: next one (next pass after the last)
                position += 1
                if position >= len(self.sequences):
                    epoch, position = epoch + 1, 0
                lane[:] = [epoch, position, -1]
            else:
                lane[:] = [epoch, position, stop]
        return items
