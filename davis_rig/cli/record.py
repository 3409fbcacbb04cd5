"""``davis-record``: record a DAVIS346 (or a replayed virtual one) into a session.h5; ``--recover`` after a crash.

Thin front end: the arguments map onto :func:`davis_rig.session.record.record_session` (or
:func:`davis_rig.session.recovery.recover_session`); errors become one message and an exit code in
:mod:`davis_rig.cli.common`. Heavy imports (h5py, pyusb) happen after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

from davis_rig.cli.common import (EXIT_DATA, EXIT_OK, add_quiet, int_in, new_parser, non_negative_float, non_negative_int,
                                   run_main)
from davis_rig.cli.view import add_live_view_arguments, check_live_view_arguments, live_view
from davis_rig.usb.async_bulk import DEFAULT_TRANSFERS

NAME = "davis-record"

EXAMPLES = """\
examples:
  davis-record --out session.h5 --duration 10 --exposure 4000 --frame-interval 40000
  davis-record --out session.h5 --overwrite --fake recordings/sample.davisreplay   # virtual camera replaying a file
  davis-record --recover session.h5       # rebuild session.h5 from session.h5.journal after a crash

Ctrl-C (or SIGTERM: kill, timeout) stops cleanly (the file is closed and complete, exit 0). An existing --out
file is kept (exit 4) unless --overwrite replaces it.
"""


def _register_us(limit_name: str):
    """``type=`` validator of an APS time register, ``0..davis_rig.protocol.config.<limit_name>`` µs.

    The limit is imported when a value is parsed, not when the parser is built, so ``--help`` imports no numpy.
    """

    def check(text: str) -> int:
        from davis_rig.protocol import config

        return int_in(0, getattr(config, limit_name))(text)

    return check


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-record``."""
    parser = new_parser(
        NAME, "Record DVS events, APS frames, special events and IMU samples of a DAVIS346 into a session.h5.",
        EXAMPLES)
    parser.add_argument("--out", metavar="SESSION_H5", help="session file to create")
    parser.add_argument("--duration", type=non_negative_float, metavar="S",
                        help="stop after S seconds (default: until Ctrl-C)")
    parser.add_argument("--exposure", type=_register_us("MAX_EXPOSURE_US"), metavar="US",
                        help="APS exposure, µs, within the register's range (default: camera default)")
    parser.add_argument("--frame-interval", type=_register_us("MAX_FRAME_INTERVAL_US"), metavar="US",
                        help="APS frame interval, µs, within the register's range (default: camera default)")
    parser.add_argument("--serial", metavar="SN", help="open the camera with this serial number")
    parser.add_argument("--fake", metavar="REPLAY",
                        help="use a virtual DAVIS346 that replays this replay file (davis_rig.usb.replay format); "
                             "the recording ends with the replay (or earlier with --duration / Ctrl-C)")
    parser.add_argument("--fake-fast", action="store_true",
                        help="with --fake: serve the replay as fast as possible instead of in real time (a test of the "
                             "host's limit: what the recording cannot keep up with is dropped, as a real camera's "
                             "transfers would be, and counted in the summary)")
    parser.add_argument("--usb-transfers", type=non_negative_int, default=DEFAULT_TRANSFERS, metavar="N",
                        help=f"asynchronous USB transfers kept in flight (default {DEFAULT_TRANSFERS}, like libcaer); "
                             "0 = a thread of synchronous reads")
    parser.add_argument("--no-imu", action="store_true",
                        help="do not record the IMU (accelerometer, gyroscope, temperature; on by default, as in DV)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing session file")
    parser.add_argument("--no-journal", action="store_true",
                        help="do not keep the raw-transfer journal (no crash recovery)")
    add_quiet(parser, help="no live progress line")
    parser.add_argument("--recover", metavar="SESSION_H5",
                        help="rebuild SESSION_H5 from SESSION_H5.journal after a crash and exit")
    add_live_view_arguments(parser)
    return parser


def fake_backend(replay: str, fast: bool = False):
    """A virtual DAVIS346 replaying ``replay``; returns ``(backend, exhausted)``.

    ``exhausted()`` is true once every transfer of the replay has been handed to the host.
    """
    from davis_rig.usb.virtual import VirtualDavis346, VirtualDavis346Backend

    device = VirtualDavis346.from_replay(replay, paced=not fast)

    return VirtualDavis346Backend(device), lambda: device.drained


def open_camera(serial: str | None, backend=None, usb_transfers: int = DEFAULT_TRANSFERS):
    """Open the camera (``backend=None``: real USB) and return the ``Davis346`` (a context manager)."""
    from davis_rig.device.camera import Davis346

    return Davis346.open(serial=serial, backend=backend, usb_transfers=usb_transfers)


def _stop_when(condition, stop: threading.Event, grace_s: float = 0.5) -> threading.Thread:
    """Start a daemon thread that sets ``stop`` ``grace_s`` after ``condition()`` first holds."""

    def watch() -> None:
        while not stop.is_set():
            if condition():
                stop.wait(grace_s)  # let the reader thread pick up the last transfers
                stop.set()
                return
            stop.wait(0.1)

    thread = threading.Thread(target=watch, name="davis-record-replay-end", daemon=True)
    thread.start()
    return thread


def _progress_line(progress) -> None:
    print(
        f"\r{progress.elapsed_s:7.1f} s  {progress.event_rate_hz / 1e6:7.3f} Mev/s  events {progress.events:>12,d}  "
        f"frames {progress.frames:>6d}  dropped transfers {progress.dropped_transfers}  "
        f"decoder errors {progress.decoder_errors}",
        end="",
        file=sys.stderr,
        flush=True,
    )


def _stop_handler(stop: threading.Event, previous: dict):
    """The signal handler of a recording: the first SIGINT / SIGTERM sets ``stop`` (the recording ends cleanly,
    a complete file); a second one, while the recording is still closing (a hung USB request, a slow disk),
    restores the ``previous`` handlers and raises :class:`KeyboardInterrupt` at once: the file keeps its last
    flush and the journal is kept for ``davis-record --recover``."""
    signalled = []

    def handle(signum, frame) -> None:
        if signalled:
            for number, handler in previous.items():
                signal.signal(number, handler)
            raise KeyboardInterrupt
        signalled.append(signum)
        stop.set()

    return handle


def _record(args: argparse.Namespace) -> int:
    from davis_rig.session.record import StopReason, record_session

    stop = threading.Event()
    backend, exhausted = None, None
    if args.fake is not None:
        backend, exhausted = fake_backend(args.fake, args.fake_fast)
        _stop_when(exhausted, stop)  # a replay ends the recording when it has been played
    stop_signals = (signal.SIGINT, signal.SIGTERM)  # Ctrl-C, and kill / timeout / a service manager
    previous: dict = {}
    previous.update({signum: signal.signal(signum, _stop_handler(stop, previous)) for signum in stop_signals})
    try:
        with open_camera(args.serial, backend, args.usb_transfers) as camera, \
                live_view(args, camera) as source:
            if args.no_imu:
                camera.set_imu_enabled(False)
            summary = record_session(
                source,
                args.out,
                duration_s=args.duration,
                exposure_us=args.exposure,
                frame_interval_us=args.frame_interval,
                overwrite=args.overwrite,
                journal=not args.no_journal,
                stop_event=stop,
                progress=None if args.quiet else _progress_line,
            )
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if not args.quiet:
            print(file=sys.stderr)
    rate = summary.events / summary.duration_s / 1e6 if summary.duration_s > 0 else 0.0
    stopped_by = summary.stopped_by
    if stopped_by == StopReason.STOP and exhausted is not None and exhausted():
        stopped_by = "end of replay"
    print(
        f"{summary.path}: {summary.events} events ({rate:.3f} Mev/s), {summary.frames} frames, "
        f"{summary.specials} special events, {summary.imu} IMU samples in {summary.duration_s:.1f} s; "
        f"stopped by {stopped_by}; dropped transfers: {summary.dropped_transfers}"
    )
    return EXIT_OK


def _recover(path: str) -> int:
    from davis_rig.session.recovery import recover_session

    report = recover_session(path)
    if report.kept_original:
        print(f"{report.path}: kept as it is: it holds more than its journal gave back ({report.events} events, "
              f"{report.frames} frames up to its last flush, against the journal's {report.transfers} transfers); "
              "the journal is removed")
    elif report.recovered:
        print(
            f"{report.path}: rebuilt from the journal: {report.transfers} transfers, {report.events} events, "
            f"{report.frames} frames (last event t={report.t_last_us} µs; {report.discarded_bytes} damaged bytes "
            "at the journal's end dropped)"
        )
    elif not report.complete:
        print(f"{NAME}: error: {report.path}: incomplete (the recording was interrupted) and there is no journal to "
              f"rebuild it from (recorded with --no-journal?); it holds {report.events} events and "
              f"{report.frames} frames up to its last flush, nothing more can be recovered", file=sys.stderr)
        return EXIT_DATA
    else:
        print(f"{report.path}: intact, no journal: nothing to recover ({report.events} events, {report.frames} frames)")
    return EXIT_OK


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Cross-option rules (exit 2 with argparse's message), all before the camera is opened."""
    check_live_view_arguments(parser, args)
    if args.recover is not None:
        recording_only = {"--out": args.out, "--view": args.view, "--fake": args.fake, "--duration": args.duration,
                          "--no-imu": args.no_imu, "--no-journal": args.no_journal, "--serial": args.serial}
        for option, value in recording_only.items():
            if value not in (None, False):
                parser.error(f"argument --recover: not allowed with {option} (it rebuilds a file, it records nothing)")
        return
    if args.out is None:
        parser.error("the following arguments are required: --out (or --recover SESSION_H5)")
    if args.fake_fast and args.fake is None:
        parser.error("argument --fake-fast: needs --fake REPLAY")
    if args.fake is not None and os.path.exists(args.out) and os.path.exists(args.fake) \
            and os.path.samefile(args.out, args.fake):
        parser.error(f"argument --out: {args.out} is the --fake replay")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-record``; returns the exit code."""
    return run_main(build_parser(), argv,
                    lambda args: _recover(args.recover) if args.recover is not None else _record(args), check=_check)


if __name__ == "__main__":
    sys.exit(main())
