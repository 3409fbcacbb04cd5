"""What an export wrote (every exporter returns one :class:`ExportSummary`)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

__all__ = ["ExportSummary"]


@dataclass(frozen=True)
class ExportSummary:
    """The result of one export.

    Attributes:
        format: the format name (``aedat4``, ``prophesee-dat``, ``rvt``, ``npz``).
        session: the session file read.
        outputs: the files or folders written.
        events: events written (after any crop; ``rvt``: the events read into its histograms); events_read: events
            of the session.
        labels: boxes written; labels_left_out: boxes of the session not written (the note says why).
        frame_hw: (height, width) of the output's pixels; origin_xy: the sensor pixel of its ``(0, 0)``.
        t_offset_us: device µs subtracted from every time (0 when times stay device µs).
        not_exported: what the session holds that the format cannot carry (``{"frames": 15, ...}``).
        notes: one sentence per decision the user should know (crop, time base, labels left out).
        extra: format-specific numbers (RVT: windows, labelled windows).
    """

    format: str
    session: str
    outputs: tuple[str, ...]
    events: int
    events_read: int
    labels: int
    labels_left_out: int
    frame_hw: tuple[int, int]
    origin_xy: tuple[int, int]
    t_offset_us: int
    not_exported: dict = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """A JSON-ready dict of every field."""
        return json.loads(json.dumps(asdict(self)))
