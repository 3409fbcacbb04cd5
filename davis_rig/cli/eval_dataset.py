"""``davis-eval-dataset``: score a detector on a dataset split (held-out synthetic test by default).

Thin front end over :func:`davis_rig.training.evaluate.evaluate_split`: prints a markdown table (pedestrian AP,
AP50, SeqASR per threshold) for all sequences, each clothing and each clothing/scale subset; ``--json`` writes
the full record. torch is imported after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from davis_rig.cli._common import EXIT_USAGE, run_command

NAME = "davis-eval-dataset"

EPILOG = """\
examples:
  davis-eval-dataset data/synth                                   # bundled detector, test split, SeqASR@0.25
  davis-eval-dataset data/synth --weights rvt-t.ckpt --threshold 0.1 0.25 --json scores.json
  davis-eval-dataset data/gen1_preprocessed --split val --seq-len 10

AP: COCO mAP@[.5:.95] of the pedestrian class, RVT/Gen1 protocol (confidence 0.001, NMS 0.45, Prophesee box
filter, first --skip-first-ms of every sequence ignored). SeqASR ("paper" mode): labelled windows after the
skip form runs cut into non-overlapping --seq-len sequences; a sequence is detected if any of its windows has a
pedestrian box at the threshold. Exit codes: 0 ok, 1 error, 2 bad arguments, 4 file problem, 5 missing dependency.
"""


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-eval-dataset``."""
    parser = argparse.ArgumentParser(
        prog=NAME, description="Score an RVT detector on a dataset split: AP, AP50 and SeqASR per subset.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data_dir", metavar="DATA_DIR", help="dataset folder (train/ val/ test/)")
    parser.add_argument("--weights", default=None,
                        help="RVT checkpoint (.safetensors, .ckpt, .pt, incl. a davis-train checkpoints/last.pt); "
                             "default: the bundled detector")
    parser.add_argument("--split", default="test", help="split to score (default: test)")
    parser.add_argument("--threshold", type=float, nargs="+", default=[0.25], metavar="T",
                        help="SeqASR confidence threshold(s) (default: 0.25)")
    parser.add_argument("--seq-len", type=int, default=3, help="windows per SeqASR sequence (default: 3)")
    parser.add_argument("--skip-first-ms", type=float, default=500.0,
                        help="ignore the first MS of every sequence (RVT protocol: 500)")
    parser.add_argument("--lanes", type=int, default=8, help="sequences streamed side by side (default: 8)")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--json", type=Path, default=None, help="write the full result as JSON here")
    return parser


def _run(args: argparse.Namespace) -> int:
    from davis_rig.training.evaluate import SplitScoreConfig, evaluate_split, format_scores

    config = SplitScoreConfig(split=args.split, seqasr_thresholds=tuple(args.threshold), seq_len=args.seq_len,
                              skip_first_us=int(round(args.skip_first_ms * 1000)), lanes=args.lanes)
    result = evaluate_split(args.data_dir, args.weights, config=config, device=args.device)
    print(f"{result['weights']} on {Path(args.data_dir) / args.split} ({result['time_s']} s)")
    print(format_scores(result))
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-eval-dataset``; returns the exit code."""
    args = build_parser().parse_args(argv)
    if args.seq_len < 1 or args.lanes < 1 or args.skip_first_ms < 0 or not all(0 < t < 1 for t in args.threshold):
        print(f"{NAME}: error: need --seq-len >= 1, --lanes >= 1, --skip-first-ms >= 0, thresholds in (0, 1)",
              file=sys.stderr)
        return EXIT_USAGE
    return run_command(NAME, lambda: _run(args))


if __name__ == "__main__":
    sys.exit(main())
