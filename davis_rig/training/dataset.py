"""Detection datasets in RVT's preprocessed layout: writer, dataset card, per-sequence reader.

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

The chunk samplers of truncated-BPTT training over these sequences are in :mod:`davis_rig.training.batches`.
numpy + h5py only.
"""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from davis_rig.errors import FormatError, MissingDependencyError, ShapeError
from davis_rig.events.histogram import COUNT_CUTOFF, NUM_BINS, WINDOW_US
from davis_rig.types import BBOX_DTYPE, GEN1_CLASSES, RVT_HW

__all__ = [
    "EV_REPR_NAME",
    "NUM_CHANNELS",
    "SPLITS",
    "DatasetWriter",
    "SequenceData",
    "list_sequences",
    "write_dataset_card",
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


def _checked_windows(histograms, window_end_us) -> tuple[np.ndarray, np.ndarray]:
    """The histograms uint8 [T, 20, 240, 304] and their window end times int64 [T] (µs) of one sequence.

    Raises:
        ShapeError: wrong histogram shape/dtype, no window, or times that do not match the windows.
        FormatError: times not strictly increasing.
    """
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
    return hist, ends


def _write_histograms(repr_dir: Path, hist: np.ndarray, ends: np.ndarray, frame_windows: Sequence[int],
                      h5_kwargs: Mapping[str, Any]) -> None:
    """``event_representations.h5`` (compressed with ``h5_kwargs``), ``timestamps_us.npy`` and
    ``objframe_idx_2_repr_idx.npy`` of one sequence into ``repr_dir`` (created)."""
    repr_dir.mkdir(parents=True)
    with _h5py().File(repr_dir / "event_representations.h5", "w") as h5f:
        h5f.create_dataset("data", data=hist, chunks=(1, NUM_CHANNELS, *RVT_HW), **h5_kwargs)
    np.save(repr_dir / "timestamps_us.npy", ends)
    np.save(repr_dir / "objframe_idx_2_repr_idx.npy", np.asarray(frame_windows, dtype=np.int64))


def _write_labels(labels_dir: Path, frame_times_us: np.ndarray, frame_labels: Sequence[np.ndarray]) -> np.ndarray:
    """``labels.npz`` (all boxes + each labelled frame's first box) and ``timestamps_us.npy`` (µs per labelled
    frame) into ``labels_dir`` (created). Returns all boxes, BBOX_DTYPE [K]."""
    labels_dir.mkdir(parents=True)
    counts = [len(boxes) for boxes in frame_labels]
    starts = np.zeros(len(counts), dtype=np.int64)
    if counts:
        starts[1:] = np.cumsum(counts)[:-1]
    all_labels = np.concatenate(frame_labels) if frame_labels else np.zeros(0, BBOX_DTYPE)
    all_labels = np.ascontiguousarray(all_labels.astype(BBOX_DTYPE, copy=False))
    np.savez(labels_dir / "labels.npz", labels=all_labels, objframe_idx_2_label_idx=starts)
    np.save(labels_dir / "timestamps_us.npy", frame_times_us)
    return all_labels


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
        hist, ends = _checked_windows(histograms, window_end_us)
        frame_windows, frame_labels = self._normalise_labels(labels, len(ends))
        name = name if name is not None else f"seq_{len(self._records):05d}"
        seq_dir = self.root / split / name
        if seq_dir.exists():
            if not self.overwrite:
                raise FormatError(f"{seq_dir}: sequence exists (pass overwrite=True to replace)")
            shutil.rmtree(seq_dir)
        _write_histograms(seq_dir / "event_representations_v2" / EV_REPR_NAME, hist, ends, frame_windows,
                          self._h5_kwargs)
        all_labels = _write_labels(seq_dir / "labels_v2", ends[np.asarray(frame_windows, dtype=np.int64)],
                                   frame_labels)
        meta = dict(meta or {})
        with open(seq_dir / "meta.json", "w", encoding="utf-8") as handle:  # last: marks a complete sequence
            json.dump(meta, handle, indent=1, default=_json_default)
        classes = all_labels["class_id"].astype(np.int64)
        size_bytes = sum(p.stat().st_size for p in seq_dir.rglob("*") if p.is_file())
        self._records.append({
            "split": split, "name": name, "windows": len(ends), "labelled_frames": len(frame_windows),
            "empty_frames": int(sum(len(boxes) == 0 for boxes in frame_labels)), "boxes": int(all_labels.shape[0]),
            "boxes_per_class": {GEN1_CLASSES.get(int(c), str(int(c))): int((classes == c).sum())
                                for c in np.unique(classes)},
            "duration_us": int(ends[-1] - ends[0]) + WINDOW_US, "size_bytes": int(size_bytes),
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
        "representation": {"type": "stacked_histogram", "window_us": WINDOW_US, "num_bins": NUM_BINS,
                           "count_cutoff": COUNT_CUTOFF, "channels": NUM_CHANNELS, "height": RVT_HW[0],
                           "width": RVT_HW[1], "dtype": "uint8"},
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
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
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
