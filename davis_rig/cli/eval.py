"""``davis-eval``: AP and SeqASR of RVT (ONNX) on labelled physical recordings, one column per recording.

Thin front end over :func:`davis_rig.evaluation.physical.evaluate_sessions` and
:func:`davis_rig.evaluation.report.write_report`; errors become one message and an exit code in
:mod:`davis_rig.cli._common`. Heavy imports happen after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import sys

from davis_rig.cli._common import EXIT_OK, run_command

NAME = "davis-eval"

EPILOG = """\
examples:
  davis-eval walk.h5 --model rvt_b.onnx                          # the paper's thresholds 0.001 0.01 0.1 0.25
  davis-eval case1.h5 case2.h5 ours.h5 --model rvt_b.onnx --names "Case1,Case2,Ours" --report out/
  davis-eval walk.h5 --model rvt_b.onnx --threshold 0.25 --seq-len 10 --skip-first-ms 0
  davis-eval walk.h5 --skip-first-ms 0 --seq-len 5              # short recording: keep all labels, shorter sequences

The sessions need /labels (davis-label). Prints the Table-3 style markdown table; --report DIR also writes
report.json (every number and setting), table.md, ap_seqasr.png and an annotated GIF per recording.
Exit codes: 0 ok, 1 error, 2 bad arguments, 4 file or model problem, 5 missing dependency.
"""


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-eval``."""
    parser = argparse.ArgumentParser(
        prog=NAME, description="Score labelled DAVIS346 sessions with an RVT step ONNX: AP and SeqASR per threshold.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sessions", nargs="+", metavar="SESSION_H5", help="labelled session files (one column each)")
    parser.add_argument("--model", default=None, metavar="RVT_ONNX",
                        help="RVT step ONNX (export_step_onnx); default: the bundled detector")
    parser.add_argument("--threshold", type=float, nargs="+", default=None, metavar="T",
                        help="confidence threshold(s) (default: 0.001 0.01 0.1 0.25)")
    parser.add_argument("--seq-len", type=int, default=10, help="windows per SeqASR sequence (default 10)")
    parser.add_argument("--seq-stride", type=int, default=None,
                        help="windows between sequence starts (default: --seq-len, non-overlapping)")
    parser.add_argument("--skip-first-ms", type=float, default=500.0, metavar="MS",
                        help="drop the labels/detections of the first MS ms, like the too small boxes: for AP and "
                             "for the SeqASR sequences, which are cut from the remaining labels (RVT: 500; 0 keeps "
                             "all)")
    parser.add_argument("--time-tol-ms", type=float, default=0.0, metavar="MS",
                        help="AP matches a label with the detections stamped within +-MS ms of it (default 0, the "
                             "right setting here: each window's own detections; > 0 pools the detections of "
                             "neighbouring windows, whose copies then count as false positives; Prophesee "
                             "matching, meant for detections at sparse times)")
    parser.add_argument("--crop-origin", type=int, nargs=2, metavar=("X", "Y"),
                        help="crop origin (default: the one stored with the labels, else centred)")
    parser.add_argument("--names", default=None, help="comma-separated column names (default: file names)")
    parser.add_argument("--report", default=None, metavar="DIR", help="write report.json, table.md, plot and GIFs")
    parser.add_argument("--no-plot", action="store_true", help="with --report: no plot")
    parser.add_argument("--gif-seconds", type=float, default=10.0,
                        help="with --report: length of the annotated GIF per recording (0: none; default 10)")
    parser.add_argument("--gif-threshold", type=float, default=None, metavar="T",
                        help="with --report: draw the detections of this threshold in the GIFs (one of --threshold; "
                             "default the highest)")
    parser.add_argument("--coco-backend", default="faster_coco_eval", choices=["faster_coco_eval", "pycocotools"])
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime threads")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def _warn_no_sequences(results, args: argparse.Namespace) -> None:
    """On stderr: why a recording's SeqASR is n/a (no labelled run of --seq-len windows) and how to get one."""
    for result in results:
        metrics = next(iter(result.metrics.values()), {})
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


def _eval(args: argparse.Namespace) -> int:
    from davis_rig.evaluation.physical import PAPER_THRESHOLDS, EvalSettings, evaluate_sessions
    from davis_rig.evaluation.report import markdown_table, write_report

    gif_windows = int(args.gif_seconds * 20) if args.report else 0
    settings = EvalSettings(
        thresholds=tuple(args.threshold) if args.threshold else PAPER_THRESHOLDS, seq_len=args.seq_len,
        seq_stride=args.seq_stride, crop_origin_xy=tuple(args.crop_origin) if args.crop_origin else None,
        skip_first_us=int(round(args.skip_first_ms * 1000)) if args.skip_first_ms > 0 else None,
        time_tol_us=int(round(args.time_tol_ms * 1000)),
        coco_backend=args.coco_backend, intra_op_threads=args.threads, gif_windows=gif_windows)
    names = [n.strip() for n in args.names.split(",")] if args.names else None
    progress = None
    if not args.quiet:
        from tqdm import tqdm

        def progress(total, desc):
            return tqdm(total=total, desc=desc, unit="window", file=sys.stderr)

    results, scores = evaluate_sessions(args.sessions, args.model, settings, names=names, progress=progress)
    _warn_no_sequences(results, args)
    print(markdown_table(results), end="")
    if args.report:
        written = write_report(results, scores, settings, args.report, plot=not args.no_plot, gif=gif_windows > 0,
                               gif_threshold=args.gif_threshold)
        print(f"report: {', '.join(str(p) for p in written.values())}")
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-eval``; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.names and len(args.names.split(",")) != len(args.sessions):
        parser.print_usage(sys.stderr)
        print(f"{NAME}: error: --names has {len(args.names.split(','))} names for {len(args.sessions)} sessions",
              file=sys.stderr)
        return 2
    if args.seq_len < 1 or (args.seq_stride is not None and args.seq_stride < 1):
        print(f"{NAME}: error: --seq-len and --seq-stride must be >= 1", file=sys.stderr)
        return 2
    if args.skip_first_ms < 0:
        print(f"{NAME}: error: --skip-first-ms must be >= 0, got {args.skip_first_ms:g}", file=sys.stderr)
        return 2
    if args.time_tol_ms < 0:
        print(f"{NAME}: error: --time-tol-ms must be >= 0, got {args.time_tol_ms:g}", file=sys.stderr)
        return 2
    if args.threshold and any(not 0 <= t <= 1 for t in args.threshold):
        print(f"{NAME}: error: thresholds must be in [0, 1], got {args.threshold}", file=sys.stderr)
        return 2
    if args.gif_threshold is not None:
        from davis_rig.evaluation.physical import PAPER_THRESHOLDS

        scored = args.threshold or PAPER_THRESHOLDS
        if args.gif_threshold not in scored:
            print(f"{NAME}: error: --gif-threshold {args.gif_threshold:g} is not one of the scored thresholds "
                  f"{', '.join(f'{t:g}' for t in scored)}", file=sys.stderr)
            return 2
    return run_command(NAME, lambda: _eval(args))


if __name__ == "__main__":
    sys.exit(main())
