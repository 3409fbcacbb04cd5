"""Export a labelled session in RVT's preprocessed Gen1 layout, so RVT's own ``validation.py`` can score it.

One session becomes one sequence folder ``OUT/<split>/<name>/`` (the layout of RVT's
``scripts/genx/preprocess_dataset.py``, read by its ``data/genx_utils`` loaders and by
:class:`davis_rig.training.dataset.SequenceData`)::

    event_representations_v2/stacked_histogram_dt=50_nbins=10/
        event_representations.h5     "data": uint8 [N, 20, 240, 304], Blosc-zstd (RVT's settings), one window
                                     per HDF5 chunk
        timestamps_us.npy            int64 [N]: window ends, µs since the session's first millisecond
        objframe_idx_2_repr_idx.npy  int64 [F]: the window of each labelled frame
    labels_v2/
        labels.npz                   "labels": BBOX_DTYPE [K] (t in the same µs), "objframe_idx_2_label_idx": int64 [F]
        timestamps_us.npy            int64 [F]: the time of each labelled frame
    meta.json                        the session, crop, time base and window settings (davis_rig's extension)

Gen1 geometry: the events are cropped to the 304x240 window (the labels' crop origin, else centred) — RVT's Gen1
models take nothing else. The windows and histograms are exactly those ``davis-eval`` scores (the same code:
windows ending every 50 ms from the session's first millisecond, both ends inclusive, RVT's timestamp
correction, 10 bins, cutoff 10). RVT's loader keeps one labelled frame per window and wants every labelled frame
to hold boxes of one time stamp, so a window that holds several label times (APS labels are 40 ms apart, the
windows 50 ms) keeps the latest one; the others are counted in the summary. Boxes are written as stored (RVT
clamps them to the frame when it loads them). RVT's evaluation skips the first 0.5 s of every sequence.

Run RVT on it: ``python validation.py dataset=gen1 dataset.path=OUT checkpoint=... use_test_set=1
+experiment/gen1=tiny.yaml`` for ``--split test`` (``use_test_set=0`` for ``val``).
There is no RVT-layout import: histograms do not give the events back.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from davis_rig import __version__
from davis_rig.errors import ConfigError, FormatError
from davis_rig.evaluation.windows import label_windows, labelled_window_grid
from davis_rig.events.histogram import COUNT_CUTOFF, NUM_BINS, WINDOW_US
from davis_rig.interop.source import ExportSource
from davis_rig.interop.summary import ExportSummary
from davis_rig.session.staging import STAGING_SUFFIX
from davis_rig.training.dataset import EV_REPR_NAME, NUM_CHANNELS, SPLITS
from davis_rig.types import RVT_HW

__all__ = ["export_rvt", "labelled_frames"]

#: Windows histogrammed per read of the session (20 x 1.46 MB of histograms in memory).
CHUNK_WINDOWS = 20


def labelled_frames(labels: np.ndarray, window_end_us: np.ndarray, window_us: int = WINDOW_US):
    """Choose RVT's labelled frames: per window, the boxes of the latest label time inside it.

    Args:
        labels: BBOX_DTYPE [B], any order.
        window_end_us: int64 [N] window ends, same clock as ``labels["t"]``.
        window_us: window length, µs (a label at ``t`` belongs to the window with ``end − window_us < t ≤ end``).

    Returns:
        ``(frame_labels, frame_window, frame_t_us, frame_start)``: the kept boxes sorted by time (BBOX_DTYPE [K]);
        the window of each frame (int64 [F], increasing); each frame's time (int64 [F]); each frame's first index
        into ``frame_labels`` (int64 [F]).
    """
    labels = labels[np.argsort(labels["t"], kind="stable")]
    window = label_windows(labels, window_end_us, window_us)
    t = labels["t"].astype(np.int64)
    inside = window >= 0
    # labels are time-sorted, so a window's last label (in the reversed order: its first) has its latest time
    frame_window, last = np.unique(window[inside][::-1], return_index=True)
    frame_t = t[inside][::-1][last]
    latest_of_window = np.zeros(len(labels), dtype=np.int64)
    latest_of_window[inside] = frame_t[np.searchsorted(frame_window, window[inside])]
    frame_labels = labels[inside & (t == latest_of_window)]
    frame_start = np.searchsorted(frame_labels["t"].astype(np.int64), frame_t, side="left").astype(np.int64)
    return frame_labels, frame_window.astype(np.int64), frame_t, frame_start


def _check_request(source: ExportSource, out: Path, split: str, name: str | None,
                   overwrite: bool) -> tuple[str, np.ndarray, Path]:
    """Check :func:`export_rvt`'s arguments; returns the sequence name, the session's labels and the folder.

    Raises:
        ConfigError, FormatError: as :func:`export_rvt` tells.
    """
    if split not in SPLITS:
        raise ConfigError("split", f"expected one of {', '.join(SPLITS)}, got {split!r}")
    name = name or source.path.stem
    if not name or name.startswith(".") or "/" in name or os.sep in name:
        raise ConfigError("name", f"expected a plain folder name, got {name!r}")
    if not source.crop:
        raise FormatError("the RVT export needs the 304x240 crop: open the source with crop=True")
    labels = source.labels()
    if labels is None or not len(labels):
        raise FormatError(f"{source.path}: no labels; RVT's layout needs labelled frames (run davis-label first)")
    seq_dir = out / split / name
    if seq_dir.exists() and not overwrite:
        raise FormatError(f"{seq_dir}: sequence exists (pass --overwrite to replace it)")
    return name, labels, seq_dir


def _write_histograms(path: Path, source: ExportSource, ends: np.ndarray,
                      progress: Callable[[int, int], None] | None) -> int:
    """Write the stacked histograms of the windows ending at ``ends`` (device µs) as RVT's
    ``event_representations.h5``; returns the session events read."""
    import h5py

    from davis_rig.evaluation.windows import event_chunks
    from davis_rig.session.schema import import_hdf5plugin

    hdf5plugin = import_hdf5plugin()
    events_read = 0
    with h5py.File(path, "w") as h5f:
        shape = (NUM_CHANNELS, *RVT_HW)
        data = h5f.create_dataset("data", shape=(0, *shape), maxshape=(None, *shape), dtype="u1",
                                  chunks=(1, *shape), **hdf5plugin.Blosc(cname="zstd", clevel=1,
                                                                        shuffle=hdf5plugin.Blosc.SHUFFLE))
        for chunk_ends, hists, _, n_read in event_chunks(source.reader, ends, source.origin_xy, window_us=WINDOW_US,
                                                         chunk_windows=CHUNK_WINDOWS):
            start = data.shape[0]
            data.resize(start + len(chunk_ends), axis=0)
            data[start:] = hists
            events_read += n_read
            if progress is not None:
                progress(events_read, source.num_events)
    return events_read


def _summary(source: ExportSource, seq_dir: Path, meta: dict, labels: np.ndarray, frame_labels: np.ndarray,
             frame_window: np.ndarray, ends: np.ndarray, events_read: int, split: str, name: str) -> ExportSummary:
    """The :class:`ExportSummary` of a written sequence (``meta``: its meta.json)."""
    reader, t0 = source.reader, meta["t_offset_us"]
    label_times = meta["label_times"]
    left_out = label_times - len(frame_window)
    notes = [f"RVT's Gen1 input is {RVT_HW[1]}x{RVT_HW[0]}: the events are cropped at {tuple(source.origin_xy)}",
             f"{len(ends)} windows of {WINDOW_US // 1000} ms ending every {WINDOW_US // 1000} ms from the session's "
             f"first millisecond (device µs {t0}, time 0 of the files), as davis-eval scores them"]
    if left_out:
        notes.append(f"{left_out} of {label_times} label times share a window with a later one and are left out "
                     "(RVT's layout holds one labelled frame per window)")
    not_exported = {"frames": len(reader.frames), "specials": len(reader.specials()),
                    "imu": 0 if (imu := reader.imu()) is None else len(imu)}
    return ExportSummary(
        format="rvt", session=str(source.path), outputs=(str(seq_dir),), events=events_read, events_read=events_read,
        labels=len(frame_labels), labels_left_out=len(labels) - len(frame_labels), frame_hw=RVT_HW,
        origin_xy=tuple(source.origin_xy), t_offset_us=t0,
        not_exported={k: v for k, v in not_exported.items() if v}, notes=tuple(notes),
        extra={"windows": len(ends), "labelled_windows": len(frame_window), "label_times": label_times,
               "label_times_left_out": left_out, "split": split, "sequence": name})


def export_rvt(source: ExportSource, out: str | os.PathLike, *, split: str = "test", name: str | None = None,
               overwrite: bool = False, progress: Callable[[int, int], None] | None = None) -> ExportSummary:
    """Write the session as the sequence ``out/<split>/<name>`` (module docstring).

    Args:
        source: an :class:`~davis_rig.interop.source.ExportSource` opened with ``crop=True``.
        out: the dataset folder (created; other sequences in it are kept).
        split: ``"train"``, ``"val"`` or ``"test"`` (RVT's validation reads ``val``, or ``test`` with
            ``use_test_set=1``).
        name: the sequence folder name; default the session file's stem.
        overwrite: replace a sequence of that name.
        progress: called with (session events read so far, session events) after each chunk of windows.

    Returns:
        An :class:`~davis_rig.interop.summary.ExportSummary` (``extra``: windows, labelled_windows, label_times,
        label_times_left_out, split, sequence).

    Raises:
        ConfigError: ``split`` (field ``split``) is not a split name, or ``name`` (field ``name``) is not a plain
            folder name.
        FormatError: the session has no labels, or the sequence exists (without ``overwrite``).
    """
    out = Path(out)
    name, labels, seq_dir = _check_request(source, out, split, name, overwrite)
    t0 = source.t_offset_us
    labels, ends = labelled_window_grid(source.reader, labels, WINDOW_US, source.path)
    frame_labels, frame_window, frame_t, frame_start = labelled_frames(labels, ends)
    frame_labels = frame_labels.copy()
    frame_labels["t"] = frame_labels["t"].astype(np.int64) - t0

    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{name}{STAGING_SUFFIX}"
    if tmp.exists():
        shutil.rmtree(tmp)  # a leftover of an export that was killed: it was never a sequence
    repr_dir = tmp / "event_representations_v2" / EV_REPR_NAME
    labels_dir = tmp / "labels_v2"
    try:
        repr_dir.mkdir(parents=True)
        labels_dir.mkdir()
        events_read = _write_histograms(repr_dir / "event_representations.h5", source, ends, progress)
        np.save(repr_dir / "timestamps_us.npy", ends - t0)
        np.save(repr_dir / "objframe_idx_2_repr_idx.npy", frame_window)
        np.savez(labels_dir / "labels.npz", labels=frame_labels, objframe_idx_2_label_idx=frame_start)
        np.save(labels_dir / "timestamps_us.npy", frame_t - t0)
        meta = {"source": str(source.path), "toolkit_version": __version__, "t_offset_us": t0,
                "crop_origin_xy": list(source.origin_xy), "window_us": WINDOW_US, "num_bins": NUM_BINS,
                "count_cutoff": COUNT_CUTOFF, "windows": len(ends), "labelled_windows": len(frame_window),
                "label_times": int(len(np.unique(labels["t"]))), "boxes": len(frame_labels),
                "labels_attrs": source.labels_attrs}
        with open(tmp / "meta.json", "w", encoding="utf-8") as handle:
            json.dump(meta, handle, indent=1, default=str)
        seq_dir.parent.mkdir(exist_ok=True)
        if seq_dir.exists():
            shutil.rmtree(seq_dir)
        os.replace(tmp, seq_dir)
    except BaseException:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp)
        raise
    return _summary(source, seq_dir, meta, labels, frame_labels, frame_window, ends, events_read, split, name)
