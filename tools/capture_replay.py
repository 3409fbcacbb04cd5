"""Record a replay file (raw USB transfers + device read-outs) from a DAVIS346 through the normal transport.

Usage::

    python tools/capture_replay.py recordings/scene.davisreplay --duration-s 10 [--serial 00000123]
        [--exposure-us 8000] [--frame-interval-us 33333] [--imu]

The camera is opened with :meth:`davis_rig.device.camera.Davis346.open`, gets libcaer's default configuration
plus the given settings, is started, and every raw bulk transfer is written with its host time by
:class:`davis_rig.usb.replay.ReplayWriter` (format: ``firmware_notes/replay_format.md``). Replay it with
``VirtualDavis346.from_replay(path)``. Ctrl-C stops early and still closes the file cleanly.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path
from typing import Any, Callable

from davis_rig.device.camera import Davis346
from davis_rig.usb.replay import ReplayHeader, ReplayWriter


def capture_replay(
    path: str,
    *,
    duration_s: float,
    serial: str | None = None,
    backend: Any = None,
    exposure_us: int | None = None,
    frame_interval_us: int | None = None,
    imu: bool = False,
    sleep: Callable[[float], Any] = time.sleep,
    clock: Callable[[], float] = time.monotonic,
    until: Callable[[], bool] | None = None,
) -> dict[str, int]:
    """Record ``duration_s`` seconds of raw transfers into a replay file.

    Args:
        path: output replay file (overwritten).
        duration_s: recording time, s (after start).
        serial: camera serial; ``None`` = the first DAVIS.
        backend: pyusb backend (``None`` = libusb-1.0).
        exposure_us: APS exposure, µs (default: libcaer's 4000).
        frame_interval_us: APS frame interval, µs (default: libcaer's 40000).
        imu: also start the IMU.
        sleep: sleep function for the start waits.
        clock: monotonic clock, s.
        until: optional early stop, polled between reads (e.g. a virtual camera's ``drained``).

    Returns:
        Counters: ``records``, ``bytes``, ``transfers``, ``dropped_transfers``, ``events``, ``frames``.

    Raises:
        DavisRigError: opening or streaming failed (the file written so far stays valid).
    """
    with Davis346.open(serial=serial, backend=backend, sleep=sleep) as cam:
        cam.send_default_config()
        if exposure_us is not None:
            cam.set_exposure(exposure_us)
        if frame_interval_us is not None:
            cam.set_frame_interval(frame_interval_us)
        cam.set_imu_enabled(imu)
        with ReplayWriter(path, _replay_header(cam)) as writer:
            cam.add_raw_listener(writer.write)
            cam.start()
            counts = _count_until(cam, clock() + duration_s, clock, until)
            stats = cam.stats
            return {
                "records": writer.records,
                "bytes": writer.bytes,
                "transfers": stats.transfers,
                "dropped_transfers": stats.dropped_transfers,
                **counts,
            }


def _replay_header(cam: Davis346) -> ReplayHeader:
    """The replay header of a configured camera: its read-outs, settings and the start time."""
    info = cam.info.to_dict()
    return ReplayHeader(
        device_info=info["device_info"],
        serial=info["serial"],
        firmware_version=info["firmware_version"],
        logic_version=info["logic_version"],
        logic_patch=info["logic_patch"],
        clocks=info["clocks"],
        extra={
            "tool": "tools/capture_replay.py",
            "features": info["features"],
            "product_id": info["product_id"],
            "chip_id": info["chip_id"],
            "exposure_us": cam.exposure_us,
            "frame_interval_us": cam.frame_interval_us,
            "producers": cam.producers,
            "started_utc": dt.datetime.now(dt.timezone.utc).isoformat(),
        },
    )


def _count_until(cam: Davis346, deadline: float, clock: Callable[[], float],
                 until: Callable[[], bool] | None) -> dict[str, int]:
    """Read a started camera until ``deadline`` (``clock()`` s) or ``until()``, stop it and read what was read
    before the stop (its raw listener writes the transfers); returns the ``events`` and ``frames`` decoded."""
    counts = {"events": 0, "frames": 0}

    def count(chunk) -> None:
        counts["events"] += len(chunk.events)
        counts["frames"] += len(chunk.frames)

    try:
        while clock() < deadline and not (until is not None and until()):
            chunk = cam.read(timeout_s=0.2)
            if chunk is not None:
                count(chunk)
    finally:
        cam.stop()
        while (chunk := cam.read(timeout_s=0.2)) is not None:  # what was read before the stop
            count(chunk)
    return counts


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit code."""
    from davis_rig.cli.common import new_parser, non_negative_int, positive_float, run_main

    parser = new_parser(Path(__file__).name, __doc__.split("\n\n")[0],
                        "examples:\n  python tools/capture_replay.py recordings/scene.davisreplay --duration-s 10\n\n"
                        "Ctrl-C stops early and still closes the replay file cleanly (exit 130).\n")
    parser.add_argument("path", help="output replay file, e.g. recordings/scene.davisreplay")
    parser.add_argument("--duration-s", type=positive_float, default=10.0,
                        help="recording time in seconds (default 10)")
    parser.add_argument("--serial", default=None, help="camera serial number (default: first DAVIS found)")
    parser.add_argument("--exposure-us", type=non_negative_int, default=None, help="APS exposure in µs (default 4000)")
    parser.add_argument("--frame-interval-us", type=non_negative_int, default=None,
                        help="APS frame interval in µs (default 40000)")
    parser.add_argument("--imu", action="store_true", help="also record IMU samples")
    return run_main(parser, argv, _capture)


def _capture(args: argparse.Namespace) -> int:
    try:
        counts = capture_replay(
            args.path,
            duration_s=args.duration_s,
            serial=args.serial,
            exposure_us=args.exposure_us,
            frame_interval_us=args.frame_interval_us,
            imu=args.imu,
        )
    except KeyboardInterrupt:
        print(f"{Path(__file__).name}: interrupted; the replay file was closed cleanly", file=sys.stderr)
        return 130
    print(
        f"wrote {args.path}: {counts['records']} records, {counts['bytes']} bytes, "
        f"{counts['events']} events, {counts['frames']} frames, {counts['dropped_transfers']} dropped transfers"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
