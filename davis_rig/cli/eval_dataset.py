"""``davis-eval-dataset``: score a detector on a dataset split (held-out synthetic test by default).

Thin front end over :func:`davis_rig.training.evaluate.evaluate_split`: prints a markdown table (pedestrian AP,
AP50, SeqASR per threshold) for all sequences, each clothing and each clothing/scale subset; ``--out`` writes
the full record as JSON. torch is imported after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from davis_rig.cli.common import (EXIT_OK, add_detector, add_out, add_quiet, add_threads, add_threshold, new_parser,
                                   non_negative_float, positive_int, run_main)
from davis_rig.metrics.ap import SKIP_FIRST_US

NAME = "davis-eval-dataset"

EXAMPLES = """\
examples:
  davis-eval-dataset data/synth                                   # bundled detector, test split, SeqASR@0.25
  davis-eval-dataset data/synth --detector rvt-t.ckpt --threshold 0.1,0.25 --out scores.json
  davis-eval-dataset data/gen1_preprocessed --split val --seq-len 10
  davis-eval-dataset data/synth --detector rvt_int8.onnx --threads 2      # an exported (e.g. int8) step graph

AP: COCO mAP@[.5:.95] of the pedestrian class, RVT/Gen1 protocol (confidence 0.001, NMS 0.45, Prophesee box
filter, first --skip-first-ms of every sequence ignored). SeqASR ("paper" mode): labelled windows after the
skip form runs cut into non-overlapping --seq-len sequences; a sequence is detected if any of its windows has a
pedestrian box at the threshold. The JSON file is written only when the scoring is complete.
"""

#: SplitScoreConfig field -> the option that sets it (names the option in a ConfigError).
OPTIONS = {"seqasr_thresholds": "--threshold", "seq_len": "--seq-len", "skip_first_us": "--skip-first-ms",
           "lanes": "--lanes"}


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-eval-dataset``."""
    parser = new_parser(NAME, "Score an RVT detector on a dataset split: AP, AP50 and SeqASR per subset.", EXAMPLES)
    parser.add_argument("data_dir", metavar="DATA_DIR", help="dataset folder (train/ val/ test/)")
    add_detector(parser, aliases=("--weights",),
                 help="RVT checkpoint (.safetensors, .ckpt, .pt, incl. a davis-train checkpoints/last.pt) or "
                      "step graph (.onnx, fp32 or davis-quantize's int8, run by onnxruntime); default: the bundled "
                      "detector")
    parser.add_argument("--split", default="test", help="split to score (default: test)")
    add_threshold(parser, default=(0.25,), help="SeqASR confidence threshold(s), in (0, 1)")
    parser.add_argument("--seq-len", type=positive_int, default=3, help="windows per SeqASR sequence (default: 3)")
    parser.add_argument("--skip-first-ms", type=non_negative_float, default=SKIP_FIRST_US / 1000, metavar="MS",
                        help=f"ignore the first MS of every sequence (RVT protocol: {SKIP_FIRST_US // 1000})")
    parser.add_argument("--lanes", type=positive_int, default=8, help="sequences streamed side by side (default: 8)")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    add_out(parser, metavar="JSON", aliases=("--json",), type=Path, help="write the full result as JSON here")
    add_threads(parser, help="torch (or onnxruntime, for an .onnx) CPU threads (default: the library's choice)")
    add_quiet(parser, help="no progress bar")
    return parser


def _run(args: argparse.Namespace) -> int:
    from davis_rig.training.evaluate import SplitScoreConfig, evaluate_split, format_scores

    config = SplitScoreConfig(split=args.split, seqasr_thresholds=tuple(args.threshold), seq_len=args.seq_len,
                              skip_first_us=int(round(args.skip_first_ms * 1000)), lanes=args.lanes)
    if args.threads is not None:
        import torch

        torch.set_num_threads(args.threads)
    progress = None
    if not args.quiet:
        from tqdm import tqdm

        def progress(total, desc):
            return tqdm(total=total, desc=desc, unit="window", file=sys.stderr)

    result = evaluate_split(args.data_dir, args.detector, config=config, device=args.device, progress=progress,
                            threads=args.threads)
    print(f"{result['weights']} on {Path(args.data_dir) / args.split} ({result['time_s']} s)")
    print(format_scores(result))
    if args.out is not None:
        _write_atomically(args.out, json.dumps(result, indent=1) + "\n")
    return EXIT_OK


def _write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file beside it: the file is complete or absent."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    try:
        partial.write_text(text, encoding="utf-8")
        partial.replace(path)
    finally:
        partial.unlink(missing_ok=True)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-eval-dataset``; returns the exit code."""
    return run_main(build_parser(), argv, _run, options=OPTIONS)


if __name__ == "__main__":
    sys.exit(main())
