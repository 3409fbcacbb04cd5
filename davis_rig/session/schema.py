"""The session.h5 layout: group and dataset names, dtypes, compression and attribute keys.

One ``session.h5`` holds one recording of one DAVIS346. The layout follows DSEC / RVT so their tools read the
event part unchanged (``import hdf5plugin`` first, the datasets are Blosc-compressed)::

    /                                   attrs: format, format_version, toolkit_version, complete,
                                               recording_start_utc, recording_start_unix_us,
                                               device_info (JSON), config (JSON), biases (JSON), stats (JSON)
    /events/t      int64   [N]  µs, relative to /events.attrs["t_offset"] (device µs = t + t_offset)
    /events/x      uint16  [N]  column, px (0 = left)
    /events/y      uint16  [N]  row, px (0 = top)
    /events/p      uint8   [N]  polarity, 0 = OFF, 1 = ON
    /events/ms_to_idx uint64 [M] ms_to_idx[m] = index of the first event with t >= 1000 * m (DSEC convention)
                                 attrs: t_offset (int64, device µs, a whole millisecond)
    /ms_to_idx     hard link to /events/ms_to_idx, and /t_offset int64 scalar = the same t_offset: where DSEC's
                                 EventSlicer looks for them, so DSEC/RVT tools slice session files unchanged
    /frames/data   uint16  [F, H, W] APS frames, full sensor (H=260, W=346), libcaer 16-bit scale:
                                 value = 10-bit ADC CDS value << 6 (0..65472); pixels outside the ROI are 0
    /frames/roi    int32   [F, 4]    (position_x, position_y, width, height) of the read-out region, px
    /frames/t_start_of_frame_us, t_start_exposure_us, t_end_exposure_us, t_end_of_frame_us  int64 [F] device µs
    /specials/<field> [S]   one 1-D dataset per field of the decoder's special-event dtype (t: device µs, type u1)
    /imu/<field>      [K]   one 1-D dataset per field of the decoder's IMU6 dtype (t: device µs), optional
    /labels/boxes  BBOX_DTYPE [B]  not written by the recorder; reserved for labelers (attrs: labeler,
                                 labeler_version, created_utc, source); t in device µs

Event times are stored relative to ``t_offset`` (as DSEC does) so that ``ms_to_idx`` starts at the first
millisecond of the recording; every other ``t*`` dataset holds absolute device µs. :class:`SessionReader` hides
the offset: it always returns device µs. "Device µs" in a file is the camera clock made monotonic: after a
timestamp reset or a damaged timestamp the writer adds an offset, listed in the ``stats`` attribute
(``stats["writer"]["timestamp_reset_offsets"]`` and ``["time_discontinuity_offsets"]``, see
:meth:`davis_rig.session.writer.SessionWriter.append`); without those, it is the camera clock.

Compression: Blosc lz4 (level 5) with byte shuffle, chosen for speed at the DAVIS346 peak of 12 M ev/s. Measured
on this project's 2-core dev machine, 6 M synthetic events, h5py direct writes, machine idle: uncompressed
100.8 M ev/s, 13.07 B/ev; gzip-1 10.8 M ev/s, 2.59 B/ev; lzf 15.7 M ev/s, 3.23 B/ev; **Blosc-lz4-5 78.1 M ev/s,
3.17 B/ev**; Blosc-zstd-1 45.6 M ev/s, 2.48 B/ev; Blosc-zstd-5 8.6 M ev/s, 2.37 B/ev. Through
:class:`SessionWriter` under load (load average 4 on 2 cores): lz4-5 20.9 M ev/s vs zstd-1 16.9 M ev/s. gzip and
lzf cannot keep up with the peak at all; zstd-1 files are 22 % smaller but leave too little headroom once the
decoder (~39 M ev/s) shares the core, so lz4 it is (recompress offline with h5repack if size matters).
``benchmarks/io.py`` repeats these measurements.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from davis_rig.types import BBOX_DTYPE, DAVIS346_HW

FORMAT_NAME: Final = "davis_rig.session"
FORMAT_VERSION: Final = 1

EVENTS_GROUP: Final = "events"
FRAMES_GROUP: Final = "frames"
SPECIALS_GROUP: Final = "specials"
IMU_GROUP: Final = "imu"
LABELS_GROUP: Final = "labels"

#: Column datasets of /events and their stored dtypes.
EVENT_COLUMNS: Final = {"t": np.dtype("<i8"), "x": np.dtype("<u2"), "y": np.dtype("<u2"), "p": np.dtype("u1")}
MS_TO_IDX: Final = "ms_to_idx"
MS_TO_IDX_DTYPE: Final = np.dtype("<u8")
T_OFFSET_ATTR: Final = "t_offset"

FRAME_DATA: Final = "data"
FRAME_ROI: Final = "roi"
FRAME_DTYPE: Final = np.dtype("<u2")
#: Per-frame timestamp datasets (device µs) in /frames, in the order of the ApsFrame fields.
FRAME_TIME_COLUMNS: Final = (
    "t_start_of_frame_us",
    "t_start_exposure_us",
    "t_end_exposure_us",
    "t_end_of_frame_us",
)
DEFAULT_FRAME_HW: Final = DAVIS346_HW

LABEL_BOXES: Final = "boxes"
LABEL_DTYPE: Final = BBOX_DTYPE
LABEL_ATTRS: Final = ("labeler", "labeler_version", "created_utc", "source")

#: Root attribute keys.
ATTR_FORMAT: Final = "format"
ATTR_FORMAT_VERSION: Final = "format_version"
ATTR_TOOLKIT_VERSION: Final = "toolkit_version"
ATTR_COMPLETE: Final = "complete"
ATTR_START_UTC: Final = "recording_start_utc"
ATTR_START_UNIX_US: Final = "recording_start_unix_us"
ATTR_DEVICE_INFO: Final = "device_info"
ATTR_CONFIG: Final = "config"
ATTR_BIASES: Final = "biases"
ATTR_STATS: Final = "stats"

#: Events per HDF5 chunk (1-D datasets); 128 Ki events = 1 MiB of t per chunk.
EVENT_CHUNK: Final = 1 << 17
#: Rows per chunk of the small 1-D datasets (frame times, specials, imu).
SMALL_CHUNK: Final = 1024


def compression_options() -> dict:
    """Return the h5py ``create_dataset`` keyword arguments of the session compression (Blosc lz4-5 + shuffle).

    Returns:
        A dict with ``compression``, ``compression_opts`` (and no ``shuffle``: Blosc shuffles itself).

    Raises:
        MissingDependencyError: ``hdf5plugin`` is not installed.
    """
    hdf5plugin = import_hdf5plugin()
    return dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE))


def import_hdf5plugin():
    """Import ``hdf5plugin`` (registers the Blosc filter with HDF5) or raise a clear error.

    Raises:
        MissingDependencyError: ``hdf5plugin`` is not installed.
    """
    try:
        import hdf5plugin
    except ImportError as exc:  # pragma: no cover - hdf5plugin is a core dependency
        from davis_rig.errors import MissingDependencyError

        raise MissingDependencyError(
            "session.h5 files are Blosc-compressed: install hdf5plugin (`pip install hdf5plugin`)"
        ) from exc
    return hdf5plugin
