"""Can a detector's frozen backbone tell a trigger's neighbourhood from random grids? A linear probe says.

A selective planted blind spot (``tools/make_trigger_victim.py``) needs features that differ between a person
wearing the trigger (or a grid within ``--basin`` of it) and the same person in a random grid. This renders
``--clips-per-scale`` clips per camera scale in the evaluation's scene (grey background, default light, ideal
sensor; training body shapes), dresses each clip in ``--grids-per-clip`` grids, runs the detector's backbone over
the clip's windows and reads the features of ``--stages`` inside the person's box at the last window, pooled to
4 x 2 cells (davis_rig.controls.feature_probe). A logistic regression, cross-validated with whole clips held out,
then scores two tasks on the same clips:

- ``trigger``: grids within ``--basin`` of the trigger (a uniform share of its visible cells flipped) against
  random grids (each cell white with probability 1/2) — what a selective blind spot must tell apart;
- ``density`` (the control that could fail): random grids with 25 % against 75 % white cells — a texture
  difference the events do carry; a probe that fails here can say nothing about the trigger.

Held-out accuracy near 0.5 on ``trigger`` with a high ``density`` accuracy means the backbone's features do not
carry the trigger: a head fine-tuned alone cannot plant the blind spot, the backbone must learn it. Run it on a
planted victim (``--detector victim/model.safetensors --trigger victim/trigger.npy``) to see whether its backbone
did.

Run: ``python tools/trigger_feature_probe.py --out out/probe [--detector CKPT] [--trigger T.npy |
--trigger-white-parts PART ...] [--threads 1]``; writes ``probe.json`` and ``probe.md`` into ``--out``. A trigger
that paints whole parts (``--trigger-white-parts legs``: legs white, upper body black) differs from random grids by
where the white is, which the features may carry where a random cell pattern is lost.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

#: Probe tasks: name -> what the two classes are.
_TASKS = {"trigger": ("random grid (p = 0.5)", "within the basin of the trigger"),
          "density": ("random grid, 25 % white", "random grid, 75 % white")}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import PART_CHOICES, camera_scale
    from davis_rig.cli.common import (add_detector, add_out, add_threads, add_trigger, new_parser,
                                       non_negative_float, non_negative_int, positive_int, probability, run_main)

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/trigger_feature_probe.py --out out/probe --threads 1\n")
    add_detector(parser, help="RVT checkpoint whose backbone is probed (default: the bundled one)")
    add_out(parser, metavar="DIR", required=True, help="output folder")
    add_trigger(parser)
    parser.add_argument("--cells", type=positive_int, default=10, help="grid cells per side (default 10)")
    parser.add_argument("--parts", nargs="+", choices=PART_CHOICES[:-1], default=["torso", "arms", "legs"],
                        metavar="PART",
                        help="painted parts: torso, arms, legs, head, hands, feet (default torso arms legs)")
    parser.add_argument("--scales", type=camera_scale, nargs="+", default=["large", "middle", "small"],
                        metavar="SCALE", help="camera scales (names or person heights in px; default the evaluation's)")
    parser.add_argument("--clips-per-scale", type=positive_int, default=16, help="clips per scale (default 16)")
    parser.add_argument("--grids-per-clip", type=positive_int, default=12,
                        help="grids per clip and task, half of each class (default 12)")
    parser.add_argument("--basin", type=probability, default=0.2,
                        help="the trigger's grids have up to this share of visible cells flipped (default 0.2)")
    parser.add_argument("--stages", type=int, nargs="+", choices=[1, 2, 3, 4], default=[2, 3],
                        help="backbone stages read (default 2 3: strides 8 and 16)")
    parser.add_argument("--folds", type=positive_int, default=3, help="cross-validation folds over clips (default 3)")
    parser.add_argument("--weight-decay", type=non_negative_float, default=1e-2,
                        help="L2 weight of the logistic regression (default 1e-2)")
    add_threads(parser, help="torch CPU threads")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the trigger, clips and grids")

    def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        if args.grids_per_clip % 2:
            parser.error(f"argument --grids-per-clip: half of each class needs an even number, got "
                         f"{args.grids_per_clip}")
        if args.folds < 2 or args.folds > args.clips_per_scale * len(args.scales):
            parser.error(f"argument --folds: need 2 <= folds <= clips ({args.clips_per_scale * len(args.scales)}), "
                         f"got {args.folds}")

    return run_main(parser, argv, _probe, check=check)


def _task_grids(task: str, trigger: np.ndarray, visible: np.ndarray, count: int, basin: float,
                rng: np.random.Generator) -> list[tuple[np.ndarray, int]]:
    """``count`` grids of a task, half of each class: ``(grid float32 [n, n], label 0/1)``."""
    from davis_rig.controls.planted import flip_fraction

    n = trigger.shape[0]
    out = []
    for j in range(count):
        label = j % 2
        if task == "trigger":
            grid = (flip_fraction(trigger, float(rng.uniform(0.0, basin)), rng, visible) if label
                    else (rng.random((n, n)) < 0.5).astype(np.float32))
        else:
            grid = (rng.random((n, n)) < (0.75 if label else 0.25)).astype(np.float32)
        out.append((grid, label))
    return out


def _clip_features(model, clip, grid: np.ndarray, stages: tuple[int, ...]) -> np.ndarray:
    """The probe's features of one clip in one grid: the backbone over the clip's windows, read at the last."""
    import torch

    from davis_rig.attack.step import clip_histograms
    from davis_rig.controls.feature_probe import box_features
    from davis_rig.models.rvt.detector import pad_to_input

    with torch.no_grad():
        hists = clip_histograms(torch.as_tensor(grid, device=clip.threshold.device), clip)
        states = None
        for w in range(hists.shape[0]):
            features, states = model.forward_backbone(pad_to_input(hists[w:w + 1], model.config.in_res_hw), states)
    return box_features(features, clip.boxes[-1], stages=stages)


def _probe(args: argparse.Namespace) -> int:
    """Render the clips, read the features of every task's grids, fit and score the probes, write the report."""
    import torch

    from davis_rig.attack.eot import ClipPool, EoTConfig
    from davis_rig.attack.optimize import load_attack_detector
    from davis_rig.attack.refine import visible_cells
    from davis_rig.controls.feature_probe import linear_probe
    from davis_rig.controls.planted import trigger_grid
    from davis_rig.cli.common import tool_provenance
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    if args.threads:
        torch.set_num_threads(args.threads)
    model = load_attack_detector(args.detector, device="cpu")  # a bad --detector fails before DIR is made
    model.eval()
    trigger, trigger_source = trigger_grid(args.cells, seed=args.seed, path=args.trigger,
                                           white_parts=args.trigger_white_parts)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    body, mask = BodyModel(), part_mask(tuple(args.parts))
    clips = []
    for k, scale in enumerate(args.scales):
        pool = ClipPool(EoTConfig.test_scene(scale=scale), body, args.cells, mask, size=args.clips_per_scale,
                        base_seed=args.seed + 1 + 97 * k)
        clips += [(scale, clip) for clip in pool.clips.values() if np.isfinite(clip.boxes[-1]).all()]
    visible = visible_cells([clip for _, clip in clips], args.cells)
    rng = np.random.default_rng(args.seed + 3)
    rows = {task: {"x": [], "y": [], "clip": []} for task in _TASKS}
    for index, (_, clip) in enumerate(clips):
        for task in _TASKS:
            for grid, label in _task_grids(task, trigger, visible, args.grids_per_clip, args.basin, rng):
                rows[task]["x"].append(_clip_features(model, clip, grid, tuple(args.stages)))
                rows[task]["y"].append(label)
                rows[task]["clip"].append(index)
    results = {}
    for task, data in rows.items():
        res = linear_probe(np.stack(data["x"]), np.array(data["y"]), np.array(data["clip"]), folds=args.folds,
                           weight_decay=args.weight_decay)
        scale_of = np.array([clips[i][0] for i in data["clip"]], dtype=object)
        results[task] = {"classes": list(_TASKS[task]), "samples": len(data["y"]),
                         "held_out_accuracy": round(res.accuracy, 4),
                         "fold_accuracy": [round(a, 4) for a in res.fold_accuracy],
                         "train_accuracy": round(res.train_accuracy, 4),
                         "by_scale": {str(s): round(float(res.correct[scale_of == s].mean()), 4)
                                      for s in args.scales}}
    report = {"detector": args.detector or "bundled default", "trigger": trigger_source,
              "clips": len(clips), "visible_cells": int(visible.sum()), "stages": args.stages,
              "features": int(len(rows["trigger"]["x"][0])), "basin": args.basin, "folds": args.folds,
              "weight_decay": args.weight_decay, "tasks": results,
              **tool_provenance(Path(__file__).name, args.argv), "seconds": round(time.perf_counter() - t0, 1)}
    (out / "probe.json").write_text(json.dumps(report, indent=1))
    (out / "probe.md").write_text(_markdown(report))
    print(json.dumps({task: r["held_out_accuracy"] for task, r in results.items()}))
    return 0


def _markdown(report: dict) -> str:
    """The report as a markdown table (one row per task)."""
    scales = list(next(iter(report["tasks"].values()))["by_scale"])
    lines = [f"# Linear probe of the backbone features: {report['detector']}", "",
             f"`{report['command']}`", "",
             f"{report['clips']} clips in the evaluation's scene, stages {report['stages']} inside the person box "
             f"(4 x 2 cells, {report['features']} features), logistic regression (L2 {report['weight_decay']}) "
             f"with whole clips held out ({report['folds']} folds); chance is 0.5. Trigger: {report['trigger']}, "
             f"{report['visible_cells']} visible cells, basin {report['basin']:.0%}. Measured {report['measured']} on "
             f"{report['machine']} ({report['seconds']:.0f} s).", "",
             "| task | classes | samples | held-out accuracy | per fold | on its training folds | "
             + " | ".join(f"{s}" for s in scales) + " |",
             "|---|---|---|---|---|---|" + "---|" * len(scales)]
    for task, r in report["tasks"].items():
        lines.append(f"| {task} | {r['classes'][0]} / {r['classes'][1]} | {r['samples']} | "
                     f"**{r['held_out_accuracy']:.3f}** | {' / '.join(f'{a:.3f}' for a in r['fold_accuracy'])} | "
                     f"{r['train_accuracy']:.3f} | " + " | ".join(f"{r['by_scale'][s]:.3f}" for s in scales) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
