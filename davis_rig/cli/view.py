"""``davis-view``: play, pause and scrub recordings in a local web page (events, APS, labels, RVT boxes, misses), or
export the view as MP4/GIF; also the live view of ``davis-record --view`` (:func:`add_live_view_arguments`,
:func:`live_view`).

Thin front end over :mod:`davis_rig.viewer`; errors become one message and an exit code in
:mod:`davis_rig.cli.common`. Heavy imports happen after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import contextlib
import socket
import sys
import threading
from pathlib import Path

from davis_rig.cli.common import (EXIT_OK, add_detector, add_int8, add_quiet, add_threads, add_threshold,
                                   check_int8, detector_onnx, int_in, new_parser, non_negative_float, non_negative_int, positive_float,
                                   positive_int, probability, run_main)

NAME = "davis-view"
#: Default TCP port of the page (DAVIS346).
DEFAULT_PORT = 8346

EXAMPLES = """\
examples:
  davis-view session.h5                          # http://127.0.0.1:8346/ ; RVT boxes scored on the fly
  davis-view a.h5 b.h5 --detections report/      # the boxes of a davis-eval --out report/ run
  davis-view walk.h5 --export walk.mp4 --start 2 --end 12      # write the view as a video instead
  davis-view walk.h5 --host 0.0.0.0 --allow-remote             # other machines, with the printed token
  ssh -L 8346:localhost:8346 labpc   # then open http://localhost:8346/ here (the viewer runs on labpc)

The page: play/pause (space), scrub, step (arrows), layers, the confidence threshold, jump to the windows where
the detector missed the labelled person (n / p) and to the SeqASR sequences it missed entirely (the attack's
successes, counted as davis-eval counts them), export a window range as GIF/MP4. One displayed frame is one
50 ms RVT window (davis-eval's grid). Ctrl-C stops the server.
"""


def _layers(text: str) -> frozenset:
    """``type=`` validator of ``--layers``: a comma list of the render layers."""
    from davis_rig.viewer.render import LAYERS

    names = {name.strip() for name in text.split(",") if name.strip()}
    unknown = names - set(LAYERS)
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown layer(s) {', '.join(sorted(unknown))}; expected a comma list "
                                         f"of {', '.join(LAYERS)}")
    return frozenset(names)


def _add_server_arguments(parser: argparse.ArgumentParser, *, host_option: str, port_option: str) -> None:
    parser.add_argument(host_option, default="127.0.0.1", metavar="HOST",
                        help="address of the page (default 127.0.0.1: this machine only; use SSH port forwarding to "
                             "look from elsewhere); another address needs --allow-remote")
    parser.add_argument(port_option, type=int_in(0, 65535), default=DEFAULT_PORT, metavar="PORT",
                        help=f"TCP port of the page (default {DEFAULT_PORT}; 0 = any free port)")
    parser.add_argument("--allow-remote", action="store_true",
                        help=f"allow a non-loopback {host_option}: every request then needs the random token printed "
                             "with the address")


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-view``."""
    from davis_rig.evaluation.physical import PAPER_THRESHOLDS, EvalSettings

    defaults = EvalSettings()
    parser = new_parser(NAME, "Look at recordings: events, APS frames, labels and RVT boxes in a local web page.",
                        EXAMPLES)
    parser.add_argument("sessions", nargs="+", metavar="SESSION_H5", help="session files (addressed by index)")
    parser.add_argument("--detections", metavar="RUN", default=None,
                        help="show the boxes of a davis-eval --out RUN folder (or one <name>.detections.npz) "
                             "instead of scoring")
    add_detector(parser, metavar="RVT_ONNX",
                 help="RVT step ONNX to score the windows with, on the fly (default: the bundled detector)")
    add_int8(parser)
    parser.add_argument("--no-detector", action="store_true", help="no RVT boxes (nothing is scored)")
    add_threshold(parser, default=None,
                  help="confidence thresholds offered on the page (default: davis-eval's "
                       f"{' '.join(f'{t:g}' for t in PAPER_THRESHOLDS)})")
    add_threads(parser, help="onnxruntime threads of the on-the-fly scoring (default: its choice)")
    parser.add_argument("--crop-origin", type=non_negative_int, nargs=2, metavar=("X", "Y"),
                        help="crop origin (default: the one stored with the labels, else centred; as davis-eval)")
    parser.add_argument("--seq-len", type=positive_int, default=defaults.seq_len, metavar="N",
                        help=f"windows per SeqASR sequence for the attack's successes (default {defaults.seq_len}, "
                             "as davis-eval)")
    parser.add_argument("--skip-first-ms", type=non_negative_float, default=defaults.skip_first_us / 1000,
                        metavar="MS", help="labels in the first MS ms need no detection (default "
                                           f"{defaults.skip_first_us // 1000}, as davis-eval)")
    _add_server_arguments(parser, host_option="--host", port_option="--port")
    parser.add_argument("--export", metavar="VIDEO", default=None,
                        help="write the view as VIDEO (.mp4 or .gif) and exit instead of serving the page")
    parser.add_argument("--session", type=non_negative_int, default=0, metavar="I",
                        help="with --export: which recording (index among SESSION_H5, default 0)")
    parser.add_argument("--start", type=non_negative_float, default=0.0, metavar="S",
                        help="with --export: from S seconds after the recording's start (default 0)")
    parser.add_argument("--end", type=positive_float, default=None, metavar="S",
                        help="with --export: up to S seconds after the start (default: the end)")
    parser.add_argument("--fps", type=positive_float, default=None, metavar="F",
                        help="with --export: video frames per second (default: real time, one frame per window)")
    parser.add_argument("--layers", type=_layers, default=None, metavar="L,...",
                        help="with --export: layers to draw (default all: events,aps,labels,detections,crop)")
    parser.add_argument("--overwrite", action="store_true", help="with --export: replace an existing VIDEO")
    add_quiet(parser, help="print nothing but errors")
    return parser


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Cross-option rules (exit 2 with argparse's message)."""
    from davis_rig.events.crop import crop_origin_error
    from davis_rig.viewer.server import is_loopback

    check_int8(parser, args)
    if args.crop_origin is not None and (message := crop_origin_error(args.crop_origin)):
        parser.error(f"argument --crop-origin: {message}")
    if args.no_detector and (args.detector is not None or args.detections is not None or args.threshold
                             or args.int8):
        parser.error("argument --no-detector: not allowed with --detector, --int8, --detections or --threshold")
    if args.detections is not None and (args.detector is not None or args.int8):
        parser.error("argument --detections: not allowed with --detector or --int8 (the boxes come from the "
                     "report)")
    if args.detections is not None and args.threshold is not None:
        parser.error("argument --threshold: with --detections the report's thresholds are offered")
    if not args.allow_remote and not is_loopback(args.host):
        parser.error(f"argument --host: {args.host} is not this machine's loopback; add --allow-remote to listen "
                     "there (every request then needs the printed token)")
    if args.export is None:
        for option, given in (("--session", args.session != 0), ("--start", args.start != 0.0),
                              ("--end", args.end is not None), ("--layers", args.layers is not None),
                              ("--overwrite", args.overwrite)):
            if given:
                parser.error(f"argument {option}: only with --export")
    else:
        from davis_rig.viewer.export import VideoFormat

        if VideoFormat.of(args.export) is None:
            parser.error(f"argument --export: expected a {VideoFormat.expected()} file, got {args.export!r}")
        if args.session >= len(args.sessions):
            parser.error(f"argument --session: {args.session} is not an index of the {len(args.sessions)} "
                         "SESSION_H5 given")
        if args.end is not None and args.end <= args.start:
            parser.error(f"argument --end: {args.end:g} s is not after --start {args.start:g} s")


def _detector_path(args: argparse.Namespace) -> Path:
    """The RVT step ONNX to score with (``--detector``, else the bundled one; ``--int8``: its int8 graph)."""
    from davis_rig.errors import FormatError

    path = detector_onnx(args)
    if not path.is_file():
        raise FormatError(f"{path}: no such RVT step ONNX")
    if path.suffix.lower() != ".onnx":
        raise FormatError(f"{path}: davis-view scores with onnxruntime and needs an RVT step ONNX (export weights "
                          "with tools/convert_checkpoint.py --onnx)")
    return path


def _open_views(args: argparse.Namespace, stack: contextlib.ExitStack):
    """Open every recording and attach its detection source; returns ``(views, on-the-fly sources)``."""
    from davis_rig.evaluation.physical import PAPER_THRESHOLDS
    from davis_rig.viewer.detections import OnTheFlyDetections, StoredDetections, find_stored_detections
    from davis_rig.viewer.recording import RecordingView

    crop = tuple(args.crop_origin) if args.crop_origin is not None else None
    views = [stack.enter_context(RecordingView(path, crop_origin_xy=crop)) for path in args.sessions]
    scoring = []
    if args.detections is not None:
        for view in views:
            stored, file = find_stored_detections(Path(args.detections), view.path)
            view.detections = StoredDetections(stored, file, view.window_end_us, view.crop_origin_xy)
    elif not args.no_detector:
        from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

        runner = RVTOnnxRunner(_detector_path(args), intra_op_threads=args.threads)
        thresholds = args.threshold if args.threshold is not None else PAPER_THRESHOLDS
        for view in views:
            view.detections = OnTheFlyDetections(view.path, runner, view.window_end_us, view.window_us,
                                                 view.crop_origin_xy, thresholds)
            scoring.append(view.detections)
    return views, scoring


def _export(args: argparse.Namespace, view) -> int:
    from davis_rig.viewer.export import export_video
    from davis_rig.viewer.render import LAYERS

    start = min(int(args.start * 1e6 // view.window_us), view.num_windows - 1)
    stop = view.num_windows if args.end is None else min(-(-int(args.end * 1e6) // view.window_us), view.num_windows)
    threshold = view.detections.thresholds[-1] if view.detections is not None else None
    path = export_video(view, args.export, start=start, stop=max(stop, start + 1), fps=args.fps,
                        layers=args.layers if args.layers is not None else LAYERS, threshold=threshold,
                        overwrite=args.overwrite)
    if not args.quiet:
        fps = args.fps if args.fps is not None else 1e6 / view.window_us
        print(f"{path}: windows {start}..{max(stop, start + 1) - 1} of {view.path.name} at {fps:g} fps")
    return EXIT_OK


def _serve(args: argparse.Namespace, views) -> int:
    from davis_rig.evaluation.physical import EvalSettings
    from davis_rig.viewer.server import ViewerServer
    from davis_rig.viewer.sessions_app import SessionsApp

    settings = EvalSettings(seq_len=args.seq_len, skip_first_us=round(args.skip_first_ms * 1000))
    server = ViewerServer(SessionsApp(views, settings), host=args.host, port=args.port,
                          allow_remote=args.allow_remote)
    with _bound(server, "--port"):
        print(f"{NAME}: {len(views)} recording(s) at {server.url}  (Ctrl-C stops)", file=sys.stderr, flush=True)
        threading.Event().wait()  # until Ctrl-C (KeyboardInterrupt leaves through the with blocks)
    return EXIT_OK


@contextlib.contextmanager
def _bound(server, port_option: str):
    """Enter ``server``; a port that cannot be bound is a usage error (``ConfigError``) naming ``port_option``."""
    from davis_rig.errors import ConfigError

    try:
        server.__enter__()
    except socket.gaierror as exc:  # the host name does not resolve: not the port's fault
        raise ConfigError("host", f"cannot listen on {server.host!r}: no such host ({exc.strerror or exc})") from exc
    except OSError as exc:
        raise ConfigError(port_option, f"cannot listen on {server.host}:{server.requested_port} ({exc.strerror or exc}); "
                                       f"pick another {port_option} (0 = any free port)") from exc
    try:
        yield server
    finally:
        server.__exit__(None, None, None)


def _view(args: argparse.Namespace) -> int:
    from davis_rig.viewer.detections import DetectionWorker

    with contextlib.ExitStack() as stack:
        views, scoring = _open_views(args, stack)
        stack.enter_context(DetectionWorker(scoring if args.export is None else
                                            [s for s in scoring if s.session == views[args.session].path]))
        if args.export is not None:
            return _export(args, views[args.session])
        try:
            return _serve(args, views)
        except KeyboardInterrupt:
            if not args.quiet:
                print(f"{NAME}: stopped", file=sys.stderr)
            return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-view``; returns the exit code."""
    return run_main(build_parser(), argv, _view, check=_check, options={"--port": "--port", "host": "--host"})


# --- the live view of davis-record ----------------------------------------------------------------
def add_live_view_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the live view (``--view`` and what it needs) on another command's parser (davis-record)."""
    group = parser.add_argument_group("live view (--view)")
    group.add_argument("--view", action="store_true",
                       help="show the recording live in a local web page: event frames, the latest APS frame, the "
                            "304x240 crop, RVT boxes with scores, event rate, drops, detector latency")
    add_detector(group, metavar="RVT_ONNX", help="with --view: RVT step ONNX (default: the bundled detector)")
    group.add_argument("--int8", action="store_true",
                       help="with --view: the bundled detector's int8 graph (about 1.5x faster, scores close to "
                            "fp32's)")
    group.add_argument("--no-detector", action="store_true", help="with --view: no RVT boxes")
    group.add_argument("--threshold", type=probability, default=0.1, metavar="T",
                       help="with --view: RVT confidence threshold (default 0.1)")
    group.add_argument("--threads", type=positive_int, default=None, metavar="N",
                       help="with --view: onnxruntime threads of the detector (default 2; 1 on a machine of 2 cores "
                            "or fewer, so that the recording keeps a core)")
    group.add_argument("--view-fps", type=positive_float, default=25.0, metavar="F",
                       help="with --view: display frames per second (default 25)")
    _add_server_arguments(group, host_option="--view-host", port_option="--view-port")


def check_live_view_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Cross-option rules of :func:`add_live_view_arguments` (exit 2 with argparse's message)."""
    from davis_rig.viewer.server import is_loopback

    if not args.view:
        for option, given in (("--detector", args.detector is not None), ("--int8", args.int8),
                              ("--no-detector", args.no_detector), ("--allow-remote", args.allow_remote), ("--view-host", args.view_host != "127.0.0.1"),
                              ("--view-port", args.view_port != DEFAULT_PORT)):
            if given:
                parser.error(f"argument {option}: only with --view")
    if args.no_detector and (args.detector is not None or args.int8):
        parser.error(f"argument --no-detector: not allowed with {'--detector' if args.detector else '--int8'}")
    check_int8(parser, args)
    if not args.allow_remote and not is_loopback(args.view_host):
        parser.error(f"argument --view-host: {args.view_host} is not this machine's loopback; add --allow-remote")


@contextlib.contextmanager
def live_view(args: argparse.Namespace, camera, prog: str = "davis-record"):
    """With ``--view``: start the live view and its page in a child process
    (:class:`~davis_rig.viewer.live_process.LiveViewProcess`; the address, with the token when one is needed, is
    printed on stderr even with ``--quiet``), and yield the camera to record from (tapped); without: yield
    ``camera`` unchanged.

    Raises:
        ConfigError: the page's port cannot be bound (names ``--view-port``).
        FormatError / MissingDependencyError: the detector cannot be loaded (before the recording starts).
    """
    if not args.view:
        yield camera
        return
    from davis_rig.viewer.live import TappedCamera
    from davis_rig.viewer.live_process import LiveViewProcess

    detector = None if args.no_detector else _detector_path(args)
    view = LiveViewProcess(detector=detector, threshold=args.threshold, threads=args.threads, fps=args.view_fps,
                           host=args.view_host, port=args.view_port, allow_remote=args.allow_remote,
                           stats=lambda: camera.stats)
    with view:
        print(f"{prog}: live view at {view.url}", file=sys.stderr, flush=True)
        yield TappedCamera(camera, view.tap)


if __name__ == "__main__":
    sys.exit(main())
