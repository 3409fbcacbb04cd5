"""``davis-attack optimize``, ``evaluate`` and ``reproduce``: argument parsers and actions (one API call each).

:mod:`davis_rig.cli.attack` owns the ``davis-attack`` entry point and its subparsers; it registers these
subcommands with :func:`add_optimize_parser`, :func:`add_evaluate_parser` and :func:`add_reproduce_parser`. Heavy
imports (torch, the scene) happen inside the actions so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys

from davis_rig.cli.common import (
    PART_CHOICES,
    SCALE_NAMES,
    add_detector,
    add_out,
    add_quiet,
    add_threads,
    add_threshold,
    camera_scale,
    device_name,
    epilog,
    name_and_path,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    probability,
    resolve_device,
)

OPTIMIZE_EPILOG = """\
examples:
  davis-attack optimize --out runs/n10 --cells 10               # paper: 11,500 steps, full body, bundled detector
  davis-attack optimize --out runs/n10 --cells 10 --resume                # continue runs/n10/checkpoints/last.pt
  davis-attack optimize --out runs/torso --cells 10 --parts torso --detector rvt-b.ckpt
  torchrun --nproc_per_node 4 -m davis_rig.cli.attack optimize --out runs/n10_ddp --clips-per-step 8   # DDP

RUN_DIR gets log.jsonl (loss, obj, cls, alpha per step; validation SeqASR), snapshots/step_*.png, checkpoints/
last.pt, best_texture.npy/png + best.json (best validation SeqASR) and texture.npy/png (final). Ctrl-C or SIGTERM
finishes the current step, writes the checkpoint and exits 130; --resume then continues from that very step
(the same losses as a run that was never stopped). Under torchrun
(WORLD_SIZE > 1) the process group is initialised from the environment: nccl on CUDA, gloo on CPU.
"""

REPRODUCE_EPILOG = """\
examples:
  davis-attack reproduce --table 1 --out repro_cpu/ --grids 10 --iterations 300 --lr 1e-2   # CPU-sized budget
  davis-attack reproduce --table 1 --out repro/ --iterations 11500                            # paper budget
  davis-attack reproduce --table 2 --out repro/ --iterations 11500      # reuses Table 1's 10x10 full-body run
  davis-attack reproduce --table 2 --out repro/ --combinations legs torso+legs --headings 2 --phases 0

Runs go to DIR/runs/<n>x<n>_<parts>/ and are resumed when present: a second call continues where one stopped, and
Table 2's full-body run is Table 1's 10x10 run when both tables use the same DIR and the same budget flags (a run
resumes only with the settings it was started with: --iterations and --refine-passes/--refine-clips may change,
--lr and the others may not; use another DIR for another budget). Then DIR/table<k>.md/json/png and
DIR/reproduce_table<k>.json (budget, detector, seconds per step, best validation per run).
"""

EVALUATE_EPILOG = """\
examples:
  davis-attack evaluate --table 1 --out docs/table1 --texture 60=runs/n60/best_texture.npy ... \\
      --texture 10=runs/n10/best_texture.npy
  davis-attack evaluate --table 2 --out docs/table2 --texture torso=runs/torso/best_texture.npy ... \\
      --texture torso+arms+legs=runs/n10/best_texture.npy
  davis-attack evaluate --out eval/ --texture mine=texture.png --visualise

Table 1: white, black, random 60x60 baselines and the given textures (KEY = grid size), thresholds 0.001 0.01 0.1
0.25. Table 2: textures per body-part combination (KEY = parts joined by '+'), threshold 0.25. Without --table:
any named textures (KEY = a name) on --parts. Writes <stem>.md, <stem>.json, <stem>.png (+ event frames and a GIF
with --visualise). Events come from the exact simulator (--events official_relaxed: the official code's relaxed
counts instead, to compare with the paper's numbers).
"""


#: Binarization schedules of ``--alpha-schedule`` (:data:`davis_rig.attack.texture.ALPHA_SCHEDULES`).
ALPHA_SCHEDULE_CHOICES = ("linear", "cosine", "step", "hard", "soft")
#: Named starting textures of ``--start`` (:data:`davis_rig.attack.texture.TEXTURE_STARTS` but ``"grid"``,
#: which ``--start PATH`` gives).
START_CHOICES = ("random", "white", "black")
#: Learning-rate schedules of ``--lr-schedule`` (:data:`davis_rig.attack.lr_schedule.LR_SCHEDULES`).
LR_SCHEDULE_CHOICES = ("cosine_restarts", "constant")
#: Library field -> the option that sets it: a :class:`~davis_rig.errors.ConfigError` names the option.
CONFIG_OPTIONS = {
    "grid_n": "--cells", "iterations": "--iterations", "clips_per_step": "--clips-per-step",
    "pool_size": "--pool-size", "refresh_every": "--refresh-every", "lr": "--lr", "lr_min": "--lr-min",
    "lr_period": "--lr-period", "alpha_schedule": "--alpha-schedule", "binarize": "--binarize",
    "start": "--start", "start_grid": "--start",
    "validate_every": "--validate-every", "num_validation_clips": "--val-clips", "checkpoint_every": "--checkpoint-every",
    "box_margin_px": "--box-margin", "refine_passes": "--refine-passes", "refine_clips": "--refine-clips",
    "playback_speed": "--playback-speed", "thresholds": "--threshold", "device": "--device", "parts": "--parts",
    "scales": "--scales", "n_cells": "--cells", "shape_index": "--shape", "ease": "--ease", "texture_mm": "--size-mm",
    "cell_mm": "--cell-mm", "detector_step": "--detector-step",
}  # fmt: skip


#: Largest --cells (:data:`davis_rig.attack.texture.MAX_CELLS`).
MAX_CELLS = 256


def _cells(text: str) -> int:
    """``--cells``: grid cells per side, an integer in [1, :data:`MAX_CELLS`]."""
    value = positive_int(text)
    if value > MAX_CELLS:
        raise argparse.ArgumentTypeError(f"expected an integer in [1, {MAX_CELLS}], got {text!r}")
    return value


def _combination(text: str) -> tuple[str, ...]:
    """``--combinations``: paintable parts joined by '+' (torso, arms, legs)."""
    parts = tuple(text.split("+"))
    if not all(p in PART_CHOICES[:3] for p in parts) or len(set(parts)) != len(parts):
        raise argparse.ArgumentTypeError(f"expected parts from torso, arms, legs joined by '+', got {text!r}")
    return parts


def _common_run_args(parser: argparse.ArgumentParser) -> None:
    """--detector, --device, --threads, --quiet (hidden --no-progress) and the motion sources."""
    add_detector(parser, metavar="CKPT", help="RVT checkpoint (.ckpt/.pt/.safetensors, official RVT included); "
                                              "default: the bundled detector")
    parser.add_argument("--device", type=device_name, default="auto",
                        help="auto (CUDA if available), cpu, cuda, cuda:1 ...")
    add_threads(parser, help="CPU threads of torch (default: torch's)")
    add_quiet(parser, help="no progress output on stderr")
    mocap = parser.add_mutually_exclusive_group()
    mocap.add_argument("--amass", default=None, metavar="DIR",
                       help="AMASS CMU folder: optimize draws train-split motions, evaluate uses test-split motions "
                            "(default: the body shapes' walk cycles)")
    mocap.add_argument("--bvh", default=None, metavar="DIR",
                       help="CMU BVH folder (DIR/<subject>/<subject>_<trial>.bvh): as --amass, same trial split")
    parser.add_argument("--max-trials", type=positive_int, default=None, metavar="N",
                        help="with --amass or --bvh: use the first N trials of the split")


def _budget_args(p: argparse.ArgumentParser) -> None:
    """The optimisation budget and settings shared by ``optimize`` and ``reproduce``."""
    p.add_argument("--iterations", type=positive_int, default=11_500,
                   help="optimisation steps (default: 11500); may change on resume, but the alpha schedule then runs "
                        "over the new total: extending a finished 300-step run to 11500 drops alpha from 1 back "
                        "to about 0.03")
    p.add_argument("--clips-per-step", type=positive_int, default=1,
                   help="EoT clips per step over all ranks (default: 1)")
    p.add_argument("--pool-size", type=positive_int, default=32, help="pre-rasterized clips in the pool (default: 32)")
    p.add_argument("--refresh-every", type=positive_int, default=50,
                   help="pool refresh period in steps (default: 50)")
    p.add_argument("--lr", type=positive_float, default=1e-4, help="Adam learning rate (default: 1e-4)")
    p.add_argument("--lr-schedule", choices=LR_SCHEDULE_CHOICES, default="cosine_restarts",
                   help="cosine_restarts (default, the official code's: cosine from --lr down to --lr-min over "
                        "--lr-period steps, then a warm restart) or constant (--lr at every step)")
    p.add_argument("--lr-min", type=non_negative_float, default=1e-7, help="floor of the cosine (default: 1e-7)")
    p.add_argument("--lr-period", type=positive_int, default=None, metavar="STEPS",
                   help="steps of one cosine (default: --iterations, one cosine over the run as the official "
                        "11,500-step run)")
    p.add_argument("--alpha-schedule", choices=ALPHA_SCHEDULE_CHOICES, default="linear",
                   help="binarization schedule: linear (paper), cosine, step, hard, soft")
    p.add_argument("--binarize", choices=("threshold", "sample"), default="threshold",
                   help="hard part of the binarization: threshold (default, the paper: white where u > 0.5) or "
                        "sample (each cell white with probability u, a new draw every step: the straight-through "
                        "gradient taken at grids around u; validation and the texture kept still round u)")
    p.add_argument("--start", default="random", metavar="{random,white,black,PATH}",
                   help="starting texture: random (default, the official initialisation), plain white / black "
                        "(the generator's cells start at 0.95 / 0.05; steps of the same size as from the random start) "
                        "or a black/white n x n grid file (.npy / image, e.g. a planted trigger with cells flipped); "
                        "a start other than random is validated at step 0, so the run never returns worse on "
                        "validation")
    p.add_argument("--validate-every", type=positive_int, default=1000,
                   help="validation period in steps (default: 1000)")
    p.add_argument("--checkpoint-every", type=positive_int, default=None, metavar="STEPS",
                   help="write checkpoints/last.pt every STEPS steps (default: every 5 minutes of work); a "
                        "checkpoint is also written after the last step of a call and on Ctrl-C / SIGTERM, "
                        "which then stops with exit code 130")
    p.add_argument("--val-clips", type=positive_int, default=64,
                   help="validation clips (default: 64), each scored as trained and as tested")
    p.add_argument("--test-sensor-probability", type=probability, default=0.5, metavar="P",
                   help="share of the training and validation clips whose sensor is the evaluation's ideal one "
                        "(theta 0.2, no mismatch, no noise) instead of the EoT's noisy sensors (default 0.5; 0: the "
                        "former EoT)")
    p.add_argument("--box-margin", type=non_negative_float, default=None, metavar="PX",
                   help="score only anchors within PX of the person's box (default: all anchors, paper)")
    p.add_argument("--loss-anchors", choices=["all", "person"], default="all",
                   help="anchors the loss scores: all (paper; on the detectors trained here > 98 %% of it is the "
                        "background anchors' p_ped) or person (the anchors whose cell overlaps the person's box)")
    p.add_argument("--loss", choices=["mean", "top"], default="mean",
                   help="mean: obj and p_ped averaged over all scored anchors (paper); top: the highest-confidence "
                        "anchor per window and clip (stronger signal on detectors with busy backgrounds)")
    p.add_argument("--v2e-gradient", choices=["relaxed", "ste"], default="relaxed",
                   help="backward of the event counts: relaxed-count surrogate (default) or the paper's "
                        "straight-through floor (ste); the forward counts are the same (docs/attack.md)")
    p.add_argument("--precision", choices=["fp32", "bf16"], default="fp32",
                   help="detector autocast: bf16 is faster on recent GPUs (default fp32)")
    p.add_argument("--detector-step", choices=["eager", "cuda_graph", "compile"], default="eager",
                   help="how the detector part of a step runs: eager (default), cuda_graph (recorded once and "
                        "replayed, CUDA only: RVT-B step 103 -> 22 ms on an H200) or compile (torch.compile); "
                        "the loss is the same within the GPU's summation-order noise")
    p.add_argument("--refine-passes", type=non_negative_int, default=0,
                   help="after the last step, sweeps of greedy cell flips starting from the best of the best "
                        "texture, plain white and plain black, each flip scored as validation selects (the clips' own sensors) "
                        "(default 0: none, the paper)")
    p.add_argument("--refine-clips", type=positive_int, default=8,
                   help="EoT clips that score the refinement's flips (default 8)")
    p.add_argument("--select-by", choices=["seqasr", "score"], default="seqasr",
                   help="best texture on validation, scored as trained: seqasr (paper: SeqASR, then mean top "
                        "score) or score (mean top score alone; finer with few validation clips)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of init, dropout, pool and sampling")


SCENES = ("toolkit", "official")


def scene_kind_args(p: argparse.ArgumentParser) -> None:
    """``--scene``, ``--events``, ``--walk`` and ``--playback-speed``: the kind of scene and event model a command
    renders, scores (and trains on); shared by ``optimize``, ``evaluate``, ``reproduce``, ``search`` and the
    controls tool."""
    p.add_argument("--scene", choices=SCENES, default="toolkit",
                   help="toolkit (default): grey background, walking across, and for training the toolkit's EoT "
                        "(lights, backgrounds, placement, sensor noise); official: the official code's renders "
                        "(blank white background, its light, walking in place, camera jitter only)")
    p.add_argument("--events", choices=["exact", "official_relaxed"], default="exact",
                   help="event model of training, validation and evaluation: exact (default; quantized events as a "
                        "camera delivers them) or official_relaxed (the official code's continuous counts x 10/27 "
                        "in training and test, as the paper's numbers were made; not events; training takes the "
                        "straight-through gradient of the relaxed counts, replacing --v2e-gradient, and one "
                        "threshold per clip: no per-pixel threshold mismatch)")
    p.add_argument("--walk", choices=["natural", "bundled"], default="natural",
                   help="the walk of training and test scenes without --amass/--bvh: natural (default: the gait "
                        "generator's 1.3 m/s, ~2 steps/s, feet on the ground in every frame) or bundled (the body "
                        "asset's cycle: 0.53 m/s, 1.2 steps/s, crouched; the walk of every table measured before)")
    p.add_argument("--playback-speed", type=positive_float, default=1.0,
                   help="motion seconds per clip second in training and test (default 1: real time; the official "
                        "code's 10 frames of 120 fps motion per 50 ms window are 1.667)")


def _scene_args(p: argparse.ArgumentParser) -> None:
    """The test scenes and thresholds shared by ``evaluate`` and ``reproduce``."""
    scene_kind_args(p)
    add_threshold(p, aliases=("--thresholds",),
                  help="confidence threshold (default: 0.001, 0.01, 0.1, 0.25 for Table 1 and named textures, "
                       "0.25 for Table 2)")
    p.add_argument("--scales", type=camera_scale, nargs="+", default=list(SCALE_NAMES), metavar="SCALE",
                   help="camera scales: large, middle, small or a person height in px (default: all three names)")
    p.add_argument("--headings", type=int, choices=[1, 2, 4], default=4,
                   help="person headings per shape: 1, 2 or 4 (default 4)")
    p.add_argument("--phases", type=non_negative_float, nargs="+", default=[0.0, 0.5], metavar="S",
                   help="start times into the walk (s, default 0 0.5)")


_HEADINGS_RAD = {1: (math.pi / 2,), 2: (math.pi / 2, -math.pi / 2), 4: (math.pi / 2, -math.pi / 2, 0.0, math.pi)}


def _eval_config(args, default_thresholds):
    from davis_rig.attack.evaluate import EvalConfig

    make = EvalConfig.official if args.scene == "official" else EvalConfig
    return make(scales=tuple(args.scales), thresholds=tuple(args.threshold or default_thresholds),
                headings_rad=_HEADINGS_RAD[args.headings], phases=tuple(args.phases), events=args.events,
                playback_speed=args.playback_speed, walk=args.walk)


def _subparser(subparsers, name: str, help: str, description: str, examples: str) -> argparse.ArgumentParser:
    return subparsers.add_parser(name, help=help, description=description, epilog=epilog(examples),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)


def add_optimize_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``optimize`` on a subparsers object; the action is stored as ``func``."""
    p = _subparser(subparsers, "optimize", "optimise an adversarial texture (EoT, resumable, DDP)",
                   "Optimise a black/white adversarial texture against a frozen RVT.", OPTIMIZE_EPILOG)
    add_out(p, required=True, metavar="RUN_DIR", help="run folder")
    p.add_argument("--cells", type=_cells, default=10,
                   help="grid cells per side n (paper: 10 ... 60; default 10)")
    p.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                   help="painted body parts: torso, arms, legs, head, hands, feet (default: torso arms legs); "
                        "'all' = whole body without mask")
    _budget_args(p)
    scene_kind_args(p)
    p.add_argument("--max-steps", type=positive_int, default=None,
                   help="stop after N steps in this call (then --resume)")
    p.add_argument("--resume", action="store_true",
                   help="continue RUN_DIR/checkpoints/last.pt at the step it holds (a clean new run when RUN_DIR "
                        "holds no run); without it RUN_DIR must not hold a run")
    _common_run_args(p)
    p.set_defaults(func=optimize_command, check=_check_optimize)
    return p


def add_evaluate_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``evaluate`` on a subparsers object; the action is stored as ``func``."""
    p = _subparser(subparsers, "evaluate", "digital evaluation: AP and SeqASR, Tables 1 and 2",
                   "Score textures with the paper's digital protocol (exact simulator).", EVALUATE_EPILOG)
    add_out(p, required=True, metavar="DIR", help="output folder")
    p.add_argument("--table", type=int, choices=[1, 2], default=None, help="reproduce Table 1 or Table 2")
    p.add_argument("--texture", type=name_and_path, action="append", default=[], metavar="NAME=PATH",
                   help="texture file (.npy/.png, n x n or upsampled map); repeatable")
    p.add_argument("--cells", type=positive_int, default=None, metavar="N",
                   help="grid cells per side of every --texture that is an upsampled map (default: detected)")
    p.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                   help="painted parts (Table 1 / named): torso, arms, legs, head, hands, feet, or all")
    _scene_args(p)
    p.add_argument("--visualise", action="store_true", help="also write event frames with boxes and a GIF")
    _common_run_args(p)
    p.set_defaults(func=evaluate_command, check=_check_evaluate)
    return p


def add_reproduce_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``reproduce`` on a subparsers object; the action is stored as ``func``."""
    p = _subparser(subparsers, "reproduce", "optimize every texture of Table 1 or 2, then evaluate the table",
                   "Reproduce the paper's Table 1 or 2 with an explicit budget.", REPRODUCE_EPILOG)
    p.add_argument("--table", type=int, choices=[1, 2], required=True, help="Table 1 (grid sizes) or 2 (body parts)")
    add_out(p, required=True, metavar="DIR", help="output folder (runs/ + table files)")
    p.add_argument("--grids", type=_cells, nargs="+", default=None, metavar="N",
                   help="Table 1 grid sizes (default: 60 50 40 30 20 10)")
    p.add_argument("--combinations", type=_combination, nargs="+", default=None, metavar="PARTS",
                   help="Table 2 part combinations joined by '+', e.g. legs torso+legs (default: all 7)")
    _budget_args(p)
    _scene_args(p)
    _common_run_args(p)
    p.set_defaults(func=reproduce_command, check=_check_budget)
    return p


def _check_budget(parser: argparse.ArgumentParser, args) -> None:
    """Options of ``optimize`` and ``reproduce`` that must agree (checked before anything is loaded)."""
    if args.clips_per_step > args.pool_size:
        parser.error(f"argument --clips-per-step: {args.clips_per_step} exceeds --pool-size {args.pool_size}")
    if args.lr_min > args.lr:
        parser.error(f"argument --lr-min: {args.lr_min:g} exceeds --lr {args.lr:g}")


def _check_optimize(parser: argparse.ArgumentParser, args) -> None:
    _check_budget(parser, args)
    _check_parts(parser, args)


def _check_parts(parser: argparse.ArgumentParser, args) -> None:
    if "all" in args.parts and len(args.parts) > 1:
        parser.error("argument --parts: 'all' (the whole body) cannot be combined with other parts")


def _check_evaluate(parser: argparse.ArgumentParser, args) -> None:
    _check_parts(parser, args)
    keys = [key for key, _ in args.texture]
    if len(set(keys)) != len(keys):
        parser.error(f"argument --texture: a KEY is given twice in {keys}")
    if args.table == 1 and not all(k.isdigit() and int(k) >= 1 for k in keys):
        parser.error(f"argument --texture: Table 1 keys are grid sizes (e.g. 10=path), got {keys}")
    if args.table is None and not keys:
        parser.error("argument --texture: give at least one --texture NAME=PATH (or --table 1 / 2)")
    if args.table == 2:
        if not keys:
            parser.error("argument --texture: Table 2 scores textures per part combination: give at least one "
                         "--texture PARTS=PATH (e.g. torso+legs=best.npy)")
        for key in keys:
            try:
                _combination(key)
            except argparse.ArgumentTypeError as exc:
                parser.error(f"argument --texture: Table 2 keys are part combinations: {exc}")


def _init_distributed(device):
    """Process group from torchrun's environment (WORLD_SIZE > 1); returns the rank's device."""
    import torch

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return device
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device.type == "cuda":
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
    torch.distributed.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return device


def _eot_config(args):
    """The EoT distribution of ``--scene``, ``--events``, ``--walk``, ``--playback-speed`` and
    ``--test-sensor-probability`` (:class:`~davis_rig.attack.eot.EoTConfig`)."""
    from davis_rig.attack.eot import EoTConfig

    make = EoTConfig.official if args.scene == "official" else EoTConfig
    # official_relaxed trains on the relaxed counts themselves (their own gradient, no surrogate needed); they take
    # one threshold per clip, so the EoT's per-pixel threshold mismatch is off
    relaxed = args.events == "official_relaxed"
    return make(playback_speed=args.playback_speed, test_sensor_probability=args.test_sensor_probability,
                walk=args.walk, **({"threshold_sigma": 0.0} if relaxed else {}))


def _attack_config(args, grid_n: int, parts):
    from davis_rig.attack.optimize import AttackConfig

    relaxed = args.events == "official_relaxed"
    eot = _eot_config(args)
    return AttackConfig(eot=eot, grid_n=grid_n, parts=parts, iterations=args.iterations,
                        clips_per_step=args.clips_per_step, pool_size=args.pool_size,
                        refresh_every=args.refresh_every, lr=args.lr, lr_schedule=args.lr_schedule,
                        lr_min=args.lr_min, lr_period=args.lr_period, alpha_schedule=args.alpha_schedule,
                        binarize=args.binarize, **_start(args.start, grid_n), validate_every=args.validate_every,
                        num_validation_clips=args.val_clips,
                        checkpoint_every=args.checkpoint_every,
                        box_margin_px=args.box_margin, loss_anchors=args.loss_anchors, loss_reduction=args.loss,
                        v2e_mode="official_relaxed" if relaxed else "dvs",
                        v2e_gradient="ste" if relaxed else args.v2e_gradient, events=args.events,
                        precision=args.precision, detector_step=args.detector_step,
                        refine_passes=args.refine_passes,
                        refine_clips=args.refine_clips, select_by=args.select_by,
                        seed=args.seed)


def _start(start: str, grid_n: int) -> dict:
    """``AttackConfig``'s ``start`` (and ``start_grid``) from ``--start``: a name of :data:`START_CHOICES`, or else
    the path of a black/white grid file of ``grid_n`` cells per side (FileNotFoundError / FormatError otherwise)."""
    if start in START_CHOICES:
        return {"start": start}
    from davis_rig.attack.export import load_texture_grid
    from davis_rig.errors import FormatError

    grid = load_texture_grid(start)  # a grid, or an upsampled map whose grid is detected
    if grid.shape != (grid_n, grid_n):
        raise FormatError(f"{start}: a {grid.shape[0]}x{grid.shape[1]} grid, the run's --cells is {grid_n}")
    return {"start": "grid", "start_grid": tuple(tuple(row) for row in grid.tolist())}


def _starting(command: str, args) -> None:
    """The first progress line, before the imports and loads that take seconds."""
    if not args.quiet:
        print(f"davis-attack {command}: loading torch, the detector and the body model ...", file=sys.stderr,
              flush=True)


def _interrupted(command: str, exc) -> int:
    """Report a run stopped by Ctrl-C / SIGTERM (:class:`~davis_rig.attack.optimize.AttackInterrupted`)."""
    print(f"davis-attack {command}: interrupted ({exc})", file=sys.stderr)
    return 130


def _set_threads(args) -> None:
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)


def optimize_command(args) -> int:
    """Action of ``davis-attack optimize``: one :func:`davis_rig.attack.optimize.optimize_texture` call."""
    _starting("optimize", args)
    import torch

    from davis_rig.attack.optimize import AttackInterrupted, load_attack_detector, optimize_texture

    _set_threads(args)
    parts = None if args.parts == ["all"] else tuple(args.parts)
    config = _attack_config(args, args.cells, parts)
    device = _init_distributed(resolve_device(args.device))
    detector = load_attack_detector(args.detector, device=device)
    motions = _motions(args, "train")
    try:
        result = optimize_texture(config, detector, args.out, resume=args.resume, device=device, motions=motions,
                                  progress=not args.quiet, max_steps=args.max_steps)
    except AttackInterrupted as exc:
        return _interrupted("optimize", exc)
    finally:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
    if int(os.environ.get("RANK", "0")) == 0:
        final = result.final_validation or {}
        print(json.dumps({"out_dir": str(result.out_dir), "steps": result.steps,
                          "seconds_per_step": result.seconds_per_step, "best_step": result.best_step,
                          "best_seq_asr": None if math.isnan(result.best_seq_asr) else result.best_seq_asr,
                          "final_texture": {"train_top_score": final["train_top_score"],
                                            "test_top_score": final["mean_top_score"],
                                            "transfer_gap": final["transfer_gap"]} if "transfer_gap" in final
                          else None}))
    return 0


def _motions(args, split: str) -> tuple:
    if args.amass:
        from davis_rig.attack.eot import amass_motions

        return tuple(amass_motions(args.amass, split, max_trials=args.max_trials))
    if args.bvh:
        from davis_rig.attack.eot import bvh_motions

        return tuple(bvh_motions(args.bvh, split, max_trials=args.max_trials))
    return ()


def _command_line(args=None) -> str:
    """This call as a shell command that re-runs it (arguments quoted where they need it): the arguments
    :func:`davis_rig.cli.attack.main` was given (``args.argv``), else the process's."""
    argv = getattr(args, "argv", None)
    return shlex.join(["davis-attack", *(sys.argv[1:] if argv is None else argv)])


def evaluate_command(args) -> int:
    """Action of ``davis-attack evaluate``: Table 1, Table 2 or named textures (one API call each)."""
    from davis_rig.cli.common import check_out_folder, removing_new_empty_dirs

    check_out_folder(args.out)  # before any work: a results folder that cannot be written loses nothing
    _starting("evaluate", args)
    from davis_rig.attack import evaluate as ev
    from davis_rig.attack import report
    from davis_rig.attack.export import load_texture_grid
    from davis_rig.attack.optimize import load_attack_detector
    from davis_rig.errors import FormatError
    from davis_rig.scene.body import BodyModel

    _set_threads(args)
    textures = dict(args.texture)
    default_thr = (ev.TABLE2_THRESHOLD,) if args.table == 2 else ev.PAPER_THRESHOLDS
    config = _eval_config(args, default_thr)
    parts = None if args.parts == ["all"] else tuple(args.parts)
    if args.table == 1:
        grids = {int(k): load_texture_grid(p, args.cells) for k, p in textures.items()}
        wrong = {f"{n}={textures[str(n)]}": list(g.shape) for n, g in grids.items() if g.shape != (n, n)}
        if wrong:
            raise FormatError(f"--texture: Table 1 keys are grid sizes, and these grids have other shapes: {wrong}")
    else:
        grids = {k: load_texture_grid(p, args.cells) for k, p in textures.items()}
    device = resolve_device(args.device)
    detector = load_attack_detector(args.detector, device=device)
    command = _command_line(args)
    model = BodyModel()
    motions = _motions(args, "test")
    with removing_new_empty_dirs(args.out):
        if args.table == 1:
            res = report.table1(grids, detector, args.out, config=config, model=model, parts=parts, command=command,
                            motions=motions, progress=not args.quiet)
            specs = {**ev.baseline_textures(parts),
                     **{f"ours {n}x{n}": ev.TextureSpec(g, parts) for n, g in grids.items()}}
        elif args.table == 2:
            res = report.table2(grids, detector, args.out, config=config, model=model, command=command, motions=motions,
                            progress=not args.quiet)
            specs = {k: ev.TextureSpec(g, tuple(k.split("+"))) for k, g in grids.items()}
        else:
            specs = {k: ev.TextureSpec(g, parts) for k, g in grids.items()}
            scenes = ev.prepare_scenes(ev.evaluation_scenes(config, model.num_shapes, motions), model, config,
                                       progress=not args.quiet)
            rows = ev.evaluate_textures(specs, detector, scenes, config, progress=not args.quiet)
            res = report.write_table(rows, config.thresholds, args.out, "evaluation",
                                 f"Digital evaluation ({ev.EVENT_MODEL_NAMES[config.events]})", command=command)
        summary = {"markdown": str(res["markdown"]), "json": str(res["json"]), "plot": str(res["plot"])}
        if args.visualise:
            vis = report.write_visualisations(specs, detector, args.out, config=config, model=model)
            summary.update(frames=[str(p) for p in vis["frames"]], gif=str(vis["gif"]))
    print(res["markdown"].read_text())
    print(json.dumps(summary))
    return 0


def reproduce_command(args) -> int:
    """Action of ``davis-attack reproduce``: one :func:`davis_rig.attack.reproduce.reproduce_table` call."""
    from davis_rig.cli.common import check_out_folder, removing_new_empty_dirs

    check_out_folder(args.out)
    _starting("reproduce", args)
    from davis_rig.attack import evaluate as ev
    from davis_rig.attack.optimize import AttackInterrupted, load_attack_detector
    from davis_rig.attack.reproduce import reproduce_table

    _set_threads(args)
    default_thr = (ev.TABLE2_THRESHOLD,) if args.table == 2 else ev.PAPER_THRESHOLDS
    attack, eval_config = _attack_config(args, 10, None), _eval_config(args, default_thr)
    device = resolve_device(args.device)
    detector = load_attack_detector(args.detector, device=device)
    try:
        with removing_new_empty_dirs(args.out):
            res = reproduce_table(args.table, detector, args.out, attack=attack, eval_config=eval_config,
                                  grids=args.grids, combinations=args.combinations,
                                  train_motions=_motions(args, "train"), test_motions=_motions(args, "test"),
                                  detector_name=str(args.detector) if args.detector else "bundled default",
                                  command=_command_line(args), progress=not args.quiet)
    except AttackInterrupted as exc:
        return _interrupted("reproduce", exc)
    print(res["markdown"].read_text())
    print(json.dumps({"markdown": str(res["markdown"]), "json": str(res["json"]), "plot": str(res["plot"]),
                      "record": str(res["record"])}))
    return 0
