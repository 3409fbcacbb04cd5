"""Read a session.h5 (see :mod:`davis_rig.session.schema`): attributes, events, time slices, frames, labels."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from davis_rig.errors import SessionError
from davis_rig.protocol.frames import ApsFrame
from davis_rig.session import schema
from davis_rig.session.journal import journal_in_use, journal_path
from davis_rig.types import EVENT_DTYPE


def _json_object(attrs, name: str) -> dict:
    """The JSON attribute ``name`` as a dict: ``{}`` when it is missing or holds another JSON value (a damaged or
    hand-edited file; the readers of these attributes look keys up).

    Raises:
        ValueError: the attribute is not JSON.
    """
    value = json.loads(attrs.get(name, "{}"))
    return value if isinstance(value, dict) else {}


def _recover_hint(path: Path) -> str:
    """``"; <name>.journal exists next to it: run davis-record --recover ..."`` when it does, else ``""`` (and
    that it is being recorded when a running recording holds the journal)."""
    if journal_in_use(journal_path(path)):
        return "; it is being recorded right now: read it once the recording has ended"
    if journal_path(path).exists():
        return f"; {journal_path(path).name} exists next to it: run `davis-record --recover {path}`"
    return ""


#: A dataset of more than :data:`_CHECKED_BYTES` may declare at most this many times the bytes the file stores for
#: it: the compression of recorded data stays far below (events about 2-10x), while a damaged or hand-edited shape
#: over unwritten chunks does not (a few KB declaring GBs), and reading those would allocate the declared size.
_MAX_DECLARED_PER_STORED = 1000
#: How far (µs) an ``ms_to_idx`` entry may disagree with event times that step back in time around it (files of
#: other tools; davis_rig's writer keeps time order, and where the times are in order an entry must be exact).
INDEX_DISORDER_TOLERANCE_US = 1_000_000
_CHECKED_BYTES = 64 << 20


def _check_stored(path: Path, dataset, what: str) -> None:
    """Refuse a dataset whose declared size is out of all proportion to the bytes stored for it.

    Raises:
        SessionError: more than 64 MiB declared and over 1000 times the stored bytes.
    """
    declared = int(dataset.size) * dataset.dtype.itemsize
    if declared <= _CHECKED_BYTES:
        return
    stored = int(dataset.id.get_storage_size())
    if stored * _MAX_DECLARED_PER_STORED < declared:
        raise SessionError(f"{path}: {what} declares {dataset.shape} ({declared:,} bytes) but the file stores "
                           f"{stored:,} bytes of it: the file is damaged (that data was never written)")


def _check_column(path: Path, dataset, what: str, kinds: str = "iu") -> None:
    """Refuse a column that is not 1-D of the expected dtype kind (numpy ``kind`` letters) or declares data the
    file does not store (:func:`_check_stored`).

    Raises:
        SessionError: naming the column, its shape and dtype.
    """
    if dataset.ndim != 1 or dataset.dtype.kind not in kinds:
        expected = "integers" if kinds == "iu" else "numbers"
        raise SessionError(f"{path}: {what} is {dataset.dtype} of shape {dataset.shape}; expected 1-D {expected}")
    _check_stored(path, dataset, what)


def _read(path: Path, dataset, key, what: str) -> np.ndarray:
    """``dataset[key]``, with HDF5 read errors (damaged chunks) turned into a SessionError naming the file."""
    try:
        return dataset[key]
    except OSError as exc:
        raise SessionError(f"{path}: cannot read {what}: the data is damaged ({exc})" + _recover_hint(path)) from exc


class FrameData:
    """Read-only access to ``/frames/data`` (uint16 [F, H, W]): indexing reads lazily, like the h5py dataset.

    Args:
        dataset: the h5py dataset.
        path: the session file (named in errors).

    Raises (on indexing):
        SessionError: HDF5 cannot read the requested frames (a damaged chunk).
    """

    def __init__(self, dataset, path: Path):
        self._dataset = dataset
        self._path = path

    @property
    def shape(self) -> tuple[int, ...]:
        """(F, H, W)."""
        return self._dataset.shape

    @property
    def dtype(self) -> np.dtype:
        """uint16."""
        return self._dataset.dtype

    @property
    def ndim(self) -> int:
        """3."""
        return self._dataset.ndim

    def __len__(self) -> int:
        return len(self._dataset)

    def __getitem__(self, key) -> np.ndarray:
        return _read(self._path, self._dataset, key, f"/frames/data[{_index_text(key)}]")


def _index_text(key) -> str:
    """``1, 0:260, ::2`` for the key ``(1, slice(0, 260), slice(None, None, 2))``."""
    if isinstance(key, tuple):
        return ", ".join(_index_text(part) for part in key)
    if isinstance(key, slice):
        text = ("" if key.start is None else str(key.start)) + ":" + ("" if key.stop is None else str(key.stop))
        return text + (f":{key.step}" if key.step is not None else "")
    return "..." if key is Ellipsis else str(key)


class FrameStore:
    """Lazy access to the APS frames of a session: ``len``, indexing (-> frame objects) and time columns.

    Args:
        group: the h5py ``/frames`` group.
        path: the session file (named in errors).

    Attributes:
        data: :class:`FrameData` [F, H, W] uint16 (full sensor, zero outside each ROI); read slices lazily.

    Raises (on indexing):
        SessionError: a frame's data is damaged.
    """

    def __init__(self, group, path: Path):
        self._group = group
        data, roi = group[schema.FRAME_DATA], group[schema.FRAME_ROI]
        if data.ndim != 3 or roi.ndim != 2 or roi.shape[1:] != (4,):
            raise SessionError(f"{path}: /frames/data {data.shape} and /frames/roi {roi.shape}; expected [F, H, W] "
                               "and [F, 4]")
        _check_stored(path, roi, "/frames/roi")
        for name in schema.FRAME_TIME_COLUMNS:
            _check_column(path, group[name], f"/frames/{name}")
        self.data = FrameData(data, path)
        self._roi = roi[:]
        self._times = {name: group[name][:] for name in schema.FRAME_TIME_COLUMNS}
        n = len(self.data)
        lengths = {name: len(values) for name, values in self._times.items()} | {"roi": len(self._roi)}
        if any(length != n for length in lengths.values()):
            raise SessionError(f"/frames: inconsistent lengths: data {n}, {lengths}")

    def __len__(self) -> int:
        return len(self.data)

    def times_us(self, name: str = "t_start_exposure_us") -> np.ndarray:
        """Return one per-frame timestamp column, int64 [F], device µs (see ``schema.FRAME_TIME_COLUMNS``)."""
        if name not in self._times:
            raise KeyError(f"unknown frame time column {name!r}; expected one of {schema.FRAME_TIME_COLUMNS}")
        return self._times[name].copy()

    def index_range(self, t0_us: int, t1_us: int, column: str = "t_start_exposure_us") -> range:
        """Return the indices of the frames with ``t0_us <= column < t1_us`` (half-open, device µs).

        Args:
            t0_us, t1_us: window, device µs.
            column: which per-frame time to test (one of ``schema.FRAME_TIME_COLUMNS``).
        """
        times = self.times_us(column)
        start, stop = np.searchsorted(times, [t0_us, t1_us], side="left")
        return range(int(start), int(max(start, stop)))

    @property
    def roi(self) -> np.ndarray:
        """int32 [F, 4]: (position_x, position_y, width, height) of each frame's read-out region, px."""
        return self._roi.copy()

    def __getitem__(self, index: int):
        """Return frame ``index`` as an :class:`~davis_rig.protocol.frames.ApsFrame`."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame index {index} out of range for {n} frames")
        index %= n
        x0, y0, width, height = (int(v) for v in self._roi[index])
        pixels = self.data[index, y0 : y0 + height, x0 : x0 + width]
        return ApsFrame(
            pixels=pixels,
            position_x=x0,
            position_y=y0,
            **{name: int(self._times[name][index]) for name in schema.FRAME_TIME_COLUMNS},
        )

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]


class SessionReader:
    """Read-only access to a session.h5 (the file is never modified).

    Args:
        path: the session file.

    Attributes (after opening): ``device_info``, ``config``, ``biases``, ``stats`` (dicts), ``complete`` (bool:
    closed cleanly), ``format_version``, ``recording_start_utc``, ``t_offset_us``, ``num_events``.

    Raises (on open):
        SessionError: the file is missing, empty (0 bytes), truncated, not a session file, or misses a required
            group.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._file = None

    def open(self) -> "SessionReader":
        """Open the file read-only and validate its layout; returns ``self``."""
        import h5py

        schema.import_hdf5plugin()
        if not self.path.exists():
            raise SessionError(f"{self.path}: no such session file")
        if not self.path.is_file():
            raise SessionError(f"{self.path}: not a file (a session.h5 is one HDF5 file)")
        if self.path.stat().st_size == 0:
            raise SessionError(f"{self.path}: the file is empty (0 bytes), not a recorded session"
                               + _recover_hint(self.path))
        try:
            self._file = h5py.File(self.path, "r", locking=False)
        except OSError as exc:
            detail = " ".join(str(exc).split())  # HDF5's messages can hold line breaks
            raise SessionError(f"{self.path}: cannot open as HDF5 ({detail}); the file is truncated or corrupt"
                               + _recover_hint(self.path)) from exc
        try:
            self._validate()
        except SessionError:
            self.close()
            raise
        return self

    def _validate(self) -> None:
        f = self._file
        try:
            fmt = f.attrs.get(schema.ATTR_FORMAT)
            if fmt != schema.FORMAT_NAME:
                raise SessionError(f"{self.path}: not a session file (format attr {fmt!r}, expected "
                                   f"{schema.FORMAT_NAME!r})")
            self.format_version = int(f.attrs[schema.ATTR_FORMAT_VERSION])
            if self.format_version > schema.FORMAT_VERSION:
                raise SessionError(f"{self.path}: format version {self.format_version} is newer than this "
                                   f"toolkit's {schema.FORMAT_VERSION}; upgrade davis_rig")
            for group in (schema.EVENTS_GROUP, schema.FRAMES_GROUP):
                if group not in f:
                    raise SessionError(f"{self.path}: missing group /{group}")
            events = f[schema.EVENTS_GROUP]
            for name in (*schema.EVENT_COLUMNS, schema.MS_TO_IDX):
                if name not in events:
                    raise SessionError(f"{self.path}: missing dataset /events/{name}")
            for name in (*schema.EVENT_COLUMNS, schema.MS_TO_IDX):
                _check_column(self.path, events[name], f"/events/{name}")
            lengths = {name: events[name].shape[0] for name in schema.EVENT_COLUMNS}
            if len(set(lengths.values())) != 1:
                raise SessionError(f"{self.path}: /events columns have different lengths {lengths}")
            self.num_events = lengths["t"]
            self.t_offset_us = int(events.attrs.get(schema.T_OFFSET_ATTR, 0))
            self._ms_to_idx = events[schema.MS_TO_IDX][:].astype(np.int64)
            if len(self._ms_to_idx) and (self._ms_to_idx[-1] > self.num_events or
                                         np.any(np.diff(self._ms_to_idx) < 0)):
                raise SessionError(f"{self.path}: /events/ms_to_idx is inconsistent with {self.num_events} events")
            self.frames = FrameStore(f[schema.FRAMES_GROUP], self.path)
            self.device_info = _json_object(f.attrs, schema.ATTR_DEVICE_INFO)
            self.config = _json_object(f.attrs, schema.ATTR_CONFIG)
            self.biases = _json_object(f.attrs, schema.ATTR_BIASES)
            self.stats = _json_object(f.attrs, schema.ATTR_STATS)
            self.complete = bool(f.attrs.get(schema.ATTR_COMPLETE, False))
            self.recording_start_utc = str(f.attrs.get(schema.ATTR_START_UTC, ""))
            self.recording_start_unix_us = int(f.attrs.get(schema.ATTR_START_UNIX_US, 0))
        except (OSError, KeyError, ValueError) as exc:
            raise SessionError(f"{self.path}: unreadable session layout ({type(exc).__name__}: {exc})") from exc

    def __enter__(self) -> "SessionReader":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def _require_open(self):
        if self._file is None:
            raise SessionError(f"{self.path}: reader is not open (use `with SessionReader(path) as r:`)")
        return self._file

    # --- events -------------------------------------------------------------------------------
    def _read_events(self, start: int, stop: int) -> np.ndarray:
        group = self._require_open()[schema.EVENTS_GROUP]
        out = np.empty(max(stop - start, 0), dtype=EVENT_DTYPE)
        if len(out):
            what = f"events [{start}, {stop})"
            out["t"] = _read(self.path, group["t"], slice(start, stop), what) + self.t_offset_us
            for name in ("x", "y", "p"):
                out[name] = _read(self.path, group[name], slice(start, stop), what)
        return out

    def events(self) -> np.ndarray:
        """Return all events, EVENT_DTYPE [N], ``t`` in device µs."""
        return self._read_events(0, self.num_events)

    def event_index(self, t_us: int) -> int:
        """Return the index of the first event with ``t >= t_us`` (device µs), using ``ms_to_idx``.

        Only the events of one millisecond are read from the file.
        """
        group = self._require_open()[schema.EVENTS_GROUP]
        t_rel = int(t_us) - self.t_offset_us
        n = self.num_events
        if t_rel <= 0 or n == 0:
            return 0
        ms = self._ms_to_idx
        if not len(ms):
            raise SessionError(f"{self.path}: /events/ms_to_idx is empty but the file holds {n} events")
        m_lo = min(t_rel // 1000, len(ms) - 1)
        m_hi = -(-t_rel // 1000)  # ceil: ms_to_idx[m_hi] is an upper bound of the answer
        lo = int(ms[m_lo])
        hi = int(ms[m_hi]) if m_hi < len(ms) else n
        # the events on both sides of each entry used prove the entry (a damaged index would pick the wrong
        # events in silence); where the times step back (a file from another tool) the index may disagree with
        # them by as much as they do, up to INDEX_DISORDER_TOLERANCE_US
        first, stop = max(lo - 1, 0), min(max(hi, lo) + 1, n)
        t_read = _read(self.path, group["t"], slice(first, stop), f"event times [{first}, {stop})")
        slack = 0 if np.all(np.diff(t_read) >= 0) else INDEX_DISORDER_TOLERANCE_US
        for m, value in ((m_lo, lo), (m_hi, hi)) if m_hi < len(ms) else ((m_lo, lo),):
            before = value == 0 or int(t_read[value - 1 - first]) < 1000 * m + slack
            after = value == n or int(t_read[value - first]) >= 1000 * m - slack
            if not (before and after):
                raise SessionError(f"{self.path}: /events/ms_to_idx[{m}] = {value} does not point at the first "
                                   f"event of millisecond {m}: the index is damaged")
        if lo >= hi:
            return hi
        return lo + int(np.searchsorted(t_read[lo - first : hi - first], t_rel, side="left"))

    def events_end_us(self) -> int:
        """Device µs just after the last event in the file (``t_offset_us`` when there is none): the end of the
        recording's event span, read from the data (one timestamp), not from the length of ``ms_to_idx``."""
        if self.num_events == 0:
            return self.t_offset_us
        group = self._require_open()[schema.EVENTS_GROUP]
        last = self.num_events - 1
        return int(_read(self.path, group["t"], last, f"event time [{last}]")) + self.t_offset_us + 1

    def events_between(self, t0_us: int, t1_us: int) -> np.ndarray:
        """Return the events with ``t0_us <= t < t1_us`` (half-open, device µs), EVENT_DTYPE [N].

        Raises:
            ValueError: ``t1_us < t0_us``.
        """
        if t1_us < t0_us:
            raise ValueError(f"events_between: t1_us ({t1_us}) must be >= t0_us ({t0_us})")
        start = self.event_index(t0_us)
        stop = self.event_index(t1_us)
        return self._read_events(start, stop)

    def iter_windows(self, window_us: int, t_start_us: int | None = None, t_end_us: int | None = None):
        """Yield ``(t0_us, events)`` for consecutive half-open windows ``[t0, t0 + window_us)`` (device µs).

        Windows are read one at a time (memory stays bounded); empty windows are yielded too, so window ``k``
        always starts at ``t_start_us + k * window_us``.

        Args:
            window_us: window length, µs (> 0).
            t_start_us: first window start, device µs (default: ``t_offset_us``, the recording's first ms).
            t_end_us: stop before this time, device µs (default: just after the last event).

        Raises:
            ValueError: ``window_us <= 0``.
        """
        if window_us <= 0:
            raise ValueError(f"window_us must be > 0, got {window_us}")
        t0 = self.t_offset_us if t_start_us is None else int(t_start_us)
        if t_end_us is None:
            t_end_us = self.events_end_us() if self.num_events else t0
        start = self.event_index(t0)
        while t0 < t_end_us:
            t1 = min(t0 + window_us, t_end_us)
            stop = self.event_index(t1)
            yield t0, self._read_events(start, stop)
            start, t0 = stop, t0 + window_us

    def indexed_span_us(self) -> int:
        """µs from ``t_offset_us`` to the end of the events by ``ms_to_idx``: 1000 µs per entry up to the first
        that equals the event count (the millisecond after the last event; later such entries, an index padded
        past the data, do not count)."""
        past = int(np.searchsorted(self._ms_to_idx, self.num_events, side="left"))
        return 1000 * min(past + 1, len(self._ms_to_idx))

    @property
    def ms_to_idx(self) -> np.ndarray:
        """int64 [M]: index of the first event with ``t >= t_offset_us + 1000 m`` (DSEC convention)."""
        return self._ms_to_idx.copy()

    # --- other streams ------------------------------------------------------------------------
    def _table(self, group_name: str, required: tuple[str, ...]) -> np.ndarray | None:
        """The column datasets of ``/<group_name>`` as one structured array (``None``: no such group, or empty).

        Raises:
            SessionError: a ``required`` column is missing, the columns differ in length, or a read fails.
        """
        f = self._require_open()
        if group_name not in f or not len(f[group_name]):
            return None
        group = f[group_name]
        names = list(group.keys())
        for name in required:
            if name not in names:
                raise SessionError(f"{self.path}: missing dataset /{group_name}/{name}")
        if "t" in names:
            names.remove("t")
            names.insert(0, "t")
        for name in names:
            _check_column(self.path, group[name], f"/{group_name}/{name}", kinds="iufb")
        lengths = {name: group[name].shape[0] for name in names}
        if len(set(lengths.values())) != 1:
            raise SessionError(f"{self.path}: /{group_name} columns have different lengths {lengths}")
        table = np.empty(lengths[names[0]], dtype=[(name, group[name].dtype) for name in names])
        for name in names:
            table[name] = _read(self.path, group[name], slice(None), f"/{group_name}/{name}")
        return table

    def specials(self) -> np.ndarray:
        """Return the special events (structured [S]: ``t`` device µs, ``type`` libcaer id), maybe empty."""
        table = self._table(schema.SPECIALS_GROUP, ("t", "type"))
        return table if table is not None else np.zeros(0, dtype=[("t", "<i8"), ("type", "u1")])

    def imu(self) -> np.ndarray | None:
        """Return the IMU samples (structured [K], ``t`` device µs) or ``None`` when the session has none."""
        return self._table(schema.IMU_GROUP, ("t",))

    def labels(self) -> np.ndarray | None:
        """Return the labels (BBOX_DTYPE [B]) or ``None`` when the session has no /labels group."""
        f = self._require_open()
        if schema.LABELS_GROUP not in f:
            return None
        group = f[schema.LABELS_GROUP]
        if schema.LABEL_BOXES not in group:
            raise SessionError(f"{self.path}: /labels has no '{schema.LABEL_BOXES}' dataset")
        dataset = group[schema.LABEL_BOXES]
        if dataset.dtype != schema.LABEL_DTYPE or dataset.ndim != 1:
            raise SessionError(f"{self.path}: /labels/boxes is {dataset.dtype} of shape {dataset.shape}, expected "
                               f"1-D {schema.LABEL_DTYPE}")
        _check_stored(self.path, dataset, "/labels/boxes")
        boxes = _read(self.path, dataset, slice(None), f"/{schema.LABELS_GROUP}/{schema.LABEL_BOXES}")
        floats = [name for name in boxes.dtype.names if boxes.dtype[name].kind == "f"]
        bad = int(np.count_nonzero(~np.all([np.isfinite(boxes[name]) for name in floats], axis=0))) if (
            floats and len(boxes)) else 0
        if bad:
            raise SessionError(f"{self.path}: {bad} of {len(boxes)} labels hold NaN or inf in "
                               f"{', '.join(floats)}: the labels are damaged; re-label with davis-label --overwrite")
        return boxes

    def labels_attrs(self) -> dict:
        """Return the /labels attributes (labeler, labeler_version, created_utc, source) or ``{}``."""
        f = self._require_open()
        if schema.LABELS_GROUP not in f:
            return {}
        return {key: (value.item() if hasattr(value, "item") else value)
                for key, value in f[schema.LABELS_GROUP].attrs.items()}
