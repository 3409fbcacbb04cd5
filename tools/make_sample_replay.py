"""Make the bundled replay file ``recordings/sample.davisreplay`` from ``recordings/sample.h5``.

The synthetic scene's events and APS frames are encoded into the exact DAVIS346 word stream and served by a
virtual DAVIS346 (USB transfers of <= 1 ms of data, like the camera's early-packet delay); the raw transfers are
captured through the normal pyusb transport by :func:`tools.capture_replay.capture_replay` — exactly what a
capture from a real camera produces. ``davis-record --fake recordings/sample.davisreplay --out session.h5`` then
replays it through the whole capture path.

Run: ``python tools/make_sample_replay.py [--session recordings/sample.h5] [--out recordings/sample.davisreplay]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))  # tools/ is a folder of scripts, not a package
from capture_replay import capture_replay  # noqa: E402

from davis_rig.protocol.layout import SensorLayout  # noqa: E402
from davis_rig.session.reader import SessionReader  # noqa: E402
from davis_rig.usb.sources import EncodedSource  # noqa: E402
from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend  # noqa: E402


def make_sample_replay(session_path: Path, out_path: Path) -> dict[str, int]:
    """Encode a session's events and frames and capture them as a replay file through the virtual camera.

    Args:
        session_path: a session.h5.
        out_path: replay file to write (overwritten).

    Returns:
        The capture counters of :func:`capture_replay` (records, bytes, events, frames, dropped transfers).
    """
    with SessionReader(session_path) as session:
        events = session.events()  # device µs
        frames = [session.frames[i] for i in range(len(session.frames))]
        layout = SensorLayout.from_mapping(session.device_info["layout"])
        serial = session.device_info.get("serial", "SYNTH001")
    source = EncodedSource(events, frames, layout=layout)
    device = VirtualDavis346(layout=layout, source=source, serial=serial)
    return capture_replay(
        str(out_path),
        duration_s=600.0,
        backend=VirtualDavis346Backend(device),
        sleep=lambda _s: None,
        until=lambda: device.drained,
    )


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit code."""
    from davis_rig.cli.common import new_parser, run_main

    parser = new_parser(Path(__file__).name, __doc__.split("\n\n")[0],
                        "examples:\n  python tools/make_sample_replay.py --session recordings/sample.h5 "
                        "--out recordings/sample.davisreplay\n")
    parser.add_argument("--session", type=Path, default=Path("recordings/sample.h5"), help="the session to encode")
    parser.add_argument("--out", type=Path, default=Path("recordings/sample.davisreplay"), help="the replay to write")
    return run_main(parser, argv, _make)


def _make(args: argparse.Namespace) -> int:
    counts = make_sample_replay(args.session, args.out)
    print(f"wrote {args.out}: {counts['records']} transfers, {counts['bytes']} bytes, {counts['events']} events, "
          f"{counts['frames']} frames, {counts['dropped_transfers']} dropped transfers")
    return 0 if counts["dropped_transfers"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
