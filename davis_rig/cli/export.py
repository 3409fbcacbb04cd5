"""``davis-export``: a session.h5 as AEDAT4, Prophesee .dat + _bbox.npy, RVT's preprocessed layout, or tonic .npz.

Thin front end over :func:`davis_rig.interop.export_session`; errors become one message and an exit code in
:mod:`davis_rig.cli.common`.
"""

from __future__ import annotations

import contextlib
import json
import sys

from davis_rig.cli.common import (EXIT_OK, add_out, add_quiet, check_out_folder, new_parser, non_negative_int,
                                   removing_new_empty_dirs, run_main)
from davis_rig.interop.formats import ExportFormat

NAME = "davis-export"

EXAMPLES = """\
examples:
  davis-export walk.h5 --to aedat4 --out walk.aedat4          # every stream, for DV (needs davis_rig[aedat4])
  davis-export walk.h5 --to prophesee-dat --out walk_td.dat    # + walk_bbox.npy, Gen1 style
  davis-export walk.h5 --to npz --out walk.npz --crop          # tonic-style events in the 304x240 crop
  davis-export walk.h5 --to rvt --out mydata                   # -> mydata/test/walk/..., RVT's Gen1 layout
  python validation.py dataset=gen1 dataset.path=mydata checkpoint=rvt-t.ckpt use_test_set=1 \\
      +experiment/gen1=tiny.yaml                               # (in RVT's repository) score it with RVT

Pixels: rvt always crops to RVT's 304x240 Gen1 window; the other formats keep the full sensor (346x260) unless
--crop (or --crop-origin). The window's origin is the labels' crop origin, else the centred one, as davis-eval
uses. Boxes always come in the output's pixels. Times: device µs (aedat4, npz); µs since the session's first
millisecond (prophesee-dat: 32-bit; rvt), the offset kept in the file. Nothing is left behind when it fails."""


def build_parser():
    """Return the argument parser of ``davis-export``."""
    parser = new_parser(NAME, "Export a session.h5 for other tools: DV, Prophesee / Gen1, RVT, tonic.", EXAMPLES)
    parser.add_argument("session", metavar="SESSION_H5", help="the session file")
    parser.add_argument("--to", required=True, choices=[fmt.value for fmt in ExportFormat], help="the output format")
    add_out(parser, required=True,
            help="the output file (aedat4, prophesee-dat: the .dat, npz) or dataset folder (rvt)")
    parser.add_argument("--crop", action="store_true",
                        help="write only the 304x240 RVT window (rvt always does)")
    parser.add_argument("--crop-origin", type=non_negative_int, nargs=2, metavar=("X", "Y"),
                        help="that window's top-left on the sensor, px (implies --crop; default: the labels' crop "
                             "origin, else centred 21 10)")
    parser.add_argument("--split", choices=("train", "val", "test"), default=None,
                        help="rvt: the split folder (default test: RVT's validation.py use_test_set=1)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_quiet(parser)
    return parser


def _check(parser, args) -> None:
    if args.split is not None and args.to != ExportFormat.RVT:
        parser.error("argument --split: applies to --to rvt only")


def _export(args) -> int:
    from davis_rig.interop import export_session

    if args.to == ExportFormat.RVT:
        check_out_folder(args.out)
    bar = None

    def progress(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            from tqdm import tqdm

            bar = tqdm(total=total, desc="events", unit="ev", unit_scale=True, file=sys.stderr)
        bar.update(done - bar.n)

    try:
        with removing_new_empty_dirs(args.out) if args.to == ExportFormat.RVT else contextlib.nullcontext():
            summary = export_session(args.session, args.to, args.out, crop=args.crop,
                                     crop_origin_xy=tuple(args.crop_origin) if args.crop_origin else None,
                                     split=args.split or "test", overwrite=args.overwrite,
                                     progress=None if args.quiet else progress)
    finally:
        if bar is not None:
            bar.close()
    if args.json:
        print(json.dumps(summary.to_json(), indent=1))
        return EXIT_OK
    labels = f", {summary.labels:,} boxes" if summary.labels or summary.labels_left_out else ""
    print(f"{summary.session} -> {', '.join(summary.outputs)} ({summary.format}): {summary.events:,} events{labels}")
    for note in summary.notes:
        print(f"  {note}")
    if summary.not_exported:
        print("  not in this format: " + ", ".join(f"{n:,} {what}" for what, n in summary.not_exported.items()))
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-export``; returns the exit code."""
    return run_main(build_parser(), argv, _export, check=_check,
                    options={"crop_origin_xy": "--crop-origin", "to": "--to", "split": "--split", "out": "--out"})


if __name__ == "__main__":
    sys.exit(main())
