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


def _detector_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--detector", default=None, metavar="CKPT",
                        help="RVT checkpoint (.ckpt/.pt/.safetensors, official RVT included); default: the bundled one")
    parser.add_argument("--device", default="auto", help="auto (CUDA if available), cpu, cuda, cuda:1 ...")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads of torch (default: torch's)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    mocap = parser.add_mutually_exclusive_group()
    mocap.add_argument("--amass", default=None, metavar="DIR",
                       help="AMASS CMU folder: optimize draws train-split motions, evaluate uses test-split motions "
                            "(default: the body shapes' walk cycles)")
    mocap.add_argument("--bvh", default=None, metavar="DIR",
                       help="CMU BVH folder (DIR/<subject>/<subject>_<trial>.bvh): as --amass, same trial split")
    parser.add_argument("--max-trials", type=int, default=None,
                        help="with --amass or --bvh: use the first N trials of the split")


def _budget_args(p: argparse.ArgumentParser) -> None:
    """The optimisation budget and settings shared by ``optimize`` and ``reproduce``."""
    p.add_argument("--iterations", type=int, default=11_500,
                   help="optimisation steps (default: 11500); may change on resume, but the alpha schedule then runs "
                        "over the new total: extending a finished 300-step run to 11500 drops alpha from 1 back "
                        "to about 0.03")
    p.add_argument("--clips-per-step", type=int, default=1, help="EoT clips per step over all ranks (default: 1)")
    p.add_argument("--pool-size", type=int, default=32, help="pre-rasterized clips in the pool (default: 32)")
    p.add_argument("--refresh-every", type=int, default=50, help="pool refresh period in steps (default: 50)")
    p.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate (default: 1e-4)")
    p.add_argument("--alpha-schedule", default="linear",
                   help="binarization schedule: linear (paper), cosine, step, hard, soft")
    p.add_argument("--validate-every", type=int, default=1000, help="validation period in steps (default: 1000)")
    p.add_argument("--checkpoint-every", type=int, default=None, metavar="STEPS",
                   help="write checkpoints/last.pt every STEPS steps (default: every 5 minutes of work); a "
                        "checkpoint is also written after the last step of a call and on Ctrl-C / SIGTERM, "
                        "which then stops with exit code 130")
    p.add_argument("--val-clips", type=int, default=16, help="validation clips (default: 16)")
    p.add_argument("--box-margin", type=float, default=None, metavar="PX",
                   help="score only anchors within PX of the person's box (default: all anchors, paper)")
    p.add_argument("--loss", choices=["mean", "top"], default="mean",
                   help="mean: obj and p_ped averaged over all scored anchors (paper); top: the highest-confidence "
                        "anchor per window and clip (stronger signal on detectors with busy backgrounds)")
    p.add_argument("--v2e-gradient", choices=["relaxed", "ste"], default="relaxed",
                   help="backward of the event counts: relaxed-count surrogate (default) or the paper's "
                        "straight-through floor (ste); the forward counts are the same (docs/attack.md)")
    p.add_argument("--precision", choices=["fp32", "bf16"], default="fp32",
                   help="detector autocast: bf16 is faster on recent GPUs (default fp32)")
    p.add_argument("--refine-passes", type=int, default=0,
                   help="after the last step, sweeps of greedy cell flips starting from the better of the best "
                        "texture and plain white, each flip scored with the exact simulator (default 0: none, the "
                        "paper)")
    p.add_argument("--refine-clips", type=int, default=8,
                   help="EoT clips that score the refinement's flips (default 8)")
    p.add_argument("--select-by", choices=["seqasr", "score"], default="seqasr",
                   help="best texture on validation: seqasr (paper: SeqASR, then mean top score) or score (mean "
                        "top score alone; finer with few validation clips)")
    p.add_argument("--seed", type=int, default=0, help="seed of init, dropout, pool and sampling")


SCENES = ("toolkit", "official")


def _scene_kind_arg(p: argparse.ArgumentParser) -> None:
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
    p.add_argument("--playback-speed", type=float, default=1.0,
                   help="motion seconds per clip second in training and test (default 1: real time; the official "
                        "code's 10 frames of 120 fps motion per 50 ms window are 1.667)")


def _scene_args(p: argparse.ArgumentParser) -> None:
    """The test scenes and thresholds shared by ``evaluate`` and ``reproduce``."""
    _scene_kind_arg(p)
    p.add_argument("--thresholds", type=float, nargs="+", default=None, help="confidence thresholds")
    p.add_argument("--scales", nargs="+", default=["large", "middle", "small"], help="camera scales")
    p.add_argument("--headings", type=int, choices=[1, 2, 4], default=4,
                   help="person headings per shape: 1, 2 or 4 (default 4)")
    p.add_argument("--phases", type=float, nargs="+", default=[0.0, 0.5], help="walk phases (s)")


_HEADINGS_RAD = {1: (math.pi / 2,), 2: (math.pi / 2, -math.pi / 2), 4: (math.pi / 2, -math.pi / 2, 0.0, math.pi)}


def _eval_config(args, default_thresholds):
    from davis_rig.attack.evaluate import EvalConfig

    scales = tuple(float(s) if s.replace(".", "", 1).isdigit() else s for s in args.scales)
    make = EvalConfig.official if args.scene == "official" else EvalConfig
    return make(scales=scales, thresholds=tuple(args.thresholds or default_thresholds),
                headings_rad=_HEADINGS_RAD[args.headings], phases=tuple(args.phases), events=args.events,
                playback_speed=args.playback_speed)


def add_optimize_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``optimize`` on a subparsers object; the action is stored as ``func``."""
    p = subparsers.add_parser("optimize", help="optimise an adversarial texture (EoT, resumable, DDP)",
                              description="Optimise a black/white adversarial texture against a frozen RVT.",
                              epilog=OPTIMIZE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder")
    p.add_argument("--cells", type=int, default=10, help="grid cells per side n (paper: 10 ... 60; default 10)")
    p.add_argument("--parts", nargs="+", default=["torso", "arms", "legs"],
                   help="painted body parts (default: torso arms legs); 'all' = whole body without mask")
    _budget_args(p)
    _scene_kind_arg(p)
    p.add_argument("--max-steps", type=int, default=None, help="stop after N steps in this call (then --resume)")
    p.add_argument("--resume", action="store_true",
                   help="continue RUN_DIR/checkpoints/last.pt (a clean new run when there is none); without it "
                        "RUN_DIR must not hold a run")
    _detector_args(p)
    p.set_defaults(func=optimize_command)
    return p


def add_evaluate_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``evaluate`` on a subparsers object; the action is stored as ``func``."""
    p = subparsers.add_parser("evaluate", help="digital evaluation: AP and SeqASR, Tables 1 and 2",
                              description="Score textures with the paper's digital protocol (exact simulator).",
                              epilog=EVALUATE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--table", type=int, choices=[1, 2], default=None, help="reproduce Table 1 or Table 2")
    p.add_argument("--texture", action="append", default=[], metavar="KEY=PATH",
                   help="texture file (.npy/.png, n x n or upsampled map); repeatable")
    p.add_argument("--cells", type=int, default=None, metavar="N",
                   help="grid cells per side of every --texture that is an upsampled map (default: detected)")
    p.add_argument("--parts", nargs="+", default=["torso", "arms", "legs"], help="painted parts (Table 1 / named)")
    _scene_args(p)
    p.add_argument("--visualise", action="store_true", help="also write event frames with boxes and a GIF")
    _detector_args(p)
    p.set_defaults(func=evaluate_command)
    return p


def add_reproduce_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``reproduce`` on a subparsers object; the action is stored as ``func``."""
    p = subparsers.add_parser("reproduce", help="optimize every texture of Table 1 or 2, then evaluate the table",
                              description="Reproduce the paper's Table 1 or 2 with an explicit budget.",
                              epilog=REPRODUCE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--table", type=int, choices=[1, 2], required=True, help="Table 1 (grid sizes) or 2 (body parts)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (runs/ + table files)")
    p.add_argument("--grids", type=int, nargs="+", default=None,
                   help="Table 1 grid sizes (default: 60 50 40 30 20 10)")
    p.add_argument("--combinations", nargs="+", default=None, metavar="PARTS",
                   help="Table 2 part combinations joined by '+', e.g. legs torso+legs (default: all 7)")
    _budget_args(p)
    _scene_args(p)
    _detector_args(p)
    p.set_defaults(func=reproduce_command)
    return p


def _device(name: str):
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


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


def _attack_config(args, grid_n: int, parts):
    from davis_rig.attack.eot import EoTConfig
    from davis_rig.attack.optimize import AttackConfig

    make = EoTConfig.official if args.scene == "official" else EoTConfig
    # official_relaxed trains on the relaxed counts themselves (their own gradient, no surrogate needed); they take
    # one threshold per clip, so the EoT's per-pixel threshold mismatch is off
    relaxed = args.events == "official_relaxed"
    eot = make(playback_speed=args.playback_speed, **({"threshold_sigma": 0.0} if relaxed else {}))
    return AttackConfig(eot=eot, grid_n=grid_n, parts=parts, iterations=args.iterations,
                        clips_per_step=args.clips_per_step, pool_size=args.pool_size,
                        refresh_every=args.refresh_every, lr=args.lr, alpha_schedule=args.alpha_schedule,
                        validate_every=args.validate_every, num_validation_clips=args.val_clips,
                        checkpoint_every=args.checkpoint_every,
                        box_margin_px=args.box_margin, loss_reduction=args.loss,
                        v2e_mode="official_relaxed" if relaxed else "dvs",
                        v2e_gradient="ste" if relaxed else args.v2e_gradient, events=args.events,
                        precision=args.precision, refine_passes=args.refine_passes,
                        refine_clips=args.refine_clips, select_by=args.select_by,
                        seed=args.seed)


def _starting(command: str, args) -> None:
    """The first progress line, before the imports and loads that take seconds."""
    if not args.no_progress:
        print(f"davis-attack {command}: loading torch, the detector and the body model ...", file=sys.stderr,
              flush=True)


def _interrupted(command: str, exc) -> int:
    """Report a run stopped by Ctrl-C / SIGTERM (:class:`~davis_rig.attack.optimize.AttackInterrupted`)."""
    print(f"davis-attack {command}: interrupted ({exc})", file=sys.stderr)
    return 130


def optimize_command(args) -> int:
    """Action of ``davis-attack optimize``: one :func:`davis_rig.attack.optimize.optimize_texture` call."""
    _starting("optimize", args)
    import torch

    from davis_rig.attack.optimize import AttackInterrupted, load_attack_detector, optimize_texture

    if args.threads:
        torch.set_num_threads(args.threads)
    device = _init_distributed(_device(args.device))
    parts = None if args.parts == ["all"] else tuple(args.parts)
    config = _attack_config(args, args.cells, parts)
    detector = load_attack_detector(args.detector, device=device)
    motions = _motions(args, "train")
    try:
        result = optimize_texture(config, detector, args.out, resume=args.resume, device=device, motions=motions,
                                  progress=not args.no_progress, max_steps=args.max_steps)
    except AttackInterrupted as exc:
        return _interrupted("optimize", exc)
    finally:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
    if int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps({"out_dir": str(result.out_dir), "steps": result.steps,
                          "seconds_per_step": result.seconds_per_step, "best_step": result.best_step,
                          "best_seq_asr": None if math.isnan(result.best_seq_asr) else result.best_seq_asr}))
    return 0


def _motions(args, split: str) -> tuple:
    if args.amass:
        from davis_rig.attack.eot import amass_motions

        return tuple(amass_motions(args.amass, split, max_trials=args.max_trials))
    if args.bvh:
        from davis_rig.attack.eot import bvh_motions

        return tuple(bvh_motions(args.bvh, split, max_trials=args.max_trials))
    return ()


def _command_line() -> str:
    """This call as a shell command that re-runs it (arguments quoted where they need it)."""
    return shlex.join(["davis-attack", *sys.argv[1:]])


def _usage(message: str) -> int:
    print(f"davis-attack evaluate: error: {message}", file=sys.stderr)
    return 2


def _parse_textures(items: list[str]) -> dict[str, str] | None:
    out = {}
    for item in items:
        key, sep, path = item.partition("=")
        if not sep or not key or not path:
            return None
        out[key] = path
    return out


def evaluate_command(args) -> int:
    """Action of ``davis-attack evaluate``: Table 1, Table 2 or named textures (one API call each)."""
    textures = _parse_textures(args.texture)
    if textures is None:
        return _usage(f"--texture expects KEY=PATH, got {args.texture}")
    if args.table == 1 and not all(k.isdigit() for k in textures):
        return _usage(f"Table 1 keys are grid sizes (e.g. 10=path), got {sorted(textures)}")
    if args.table is None and not textures:
        return _usage("give at least one --texture NAME=PATH (or --table 1 / 2)")
    _starting("evaluate", args)
    import torch

    from davis_rig.attack import evaluate as ev
    from davis_rig.attack.export import load_texture_grid
    from davis_rig.attack.optimize import load_attack_detector

    if args.threads:
        torch.set_num_threads(args.threads)
    device = _device(args.device)
    default_thr = (ev.TABLE2_THRESHOLD,) if args.table == 2 else ev.PAPER_THRESHOLDS
    config = _eval_config(args, default_thr)
    detector = load_attack_detector(args.detector, device=device)
    command = _command_line()
    parts = None if args.parts == ["all"] else tuple(args.parts)
    from davis_rig.scene.body import BodyModel

    model = BodyModel()
    motions = _motions(args, "test")
    if args.table == 1:
        grids = {int(k): load_texture_grid(p, args.cells) for k, p in textures.items()}
        res = ev.table1(grids, detector, args.out, config=config, model=model, parts=parts, command=command,
                        motions=motions, progress=not args.no_progress)
        specs = {**ev.baseline_textures(parts), **{f"ours {n}x{n}": ev.TextureSpec(g, parts) for n, g in grids.items()}}
    elif args.table == 2:
        grids = {k: load_texture_grid(p, args.cells) for k, p in textures.items()}
        res = ev.table2(grids, detector, args.out, config=config, model=model, command=command, motions=motions,
                        progress=not args.no_progress)
        specs = {k: ev.TextureSpec(g, tuple(k.split("+"))) for k, g in grids.items()}
    else:
        specs = {k: ev.TextureSpec(load_texture_grid(p, args.cells), parts) for k, p in textures.items()}
        scenes = ev.prepare_scenes(ev.evaluation_scenes(config, model.num_shapes, motions), model, config)
        rows = ev.evaluate_textures(specs, detector, scenes, config, progress=not args.no_progress)
        res = ev.write_table(rows, config.thresholds, args.out, "evaluation",
                             f"Digital evaluation ({ev.EVENT_MODEL_NAMES[config.events]})", command=command)
    summary = {"markdown": str(res["markdown"]), "json": str(res["json"]), "plot": str(res["plot"])}
    if args.visualise:
        vis = ev.write_visualisations(specs, detector, args.out, config=config, model=model)
        summary.update(frames=[str(p) for p in vis["frames"]], gif=str(vis["gif"]))
    print(res["markdown"].read_text())
    print(json.dumps(summary))
    return 0


def reproduce_command(args) -> int:
    """Action of ``davis-attack reproduce``: one :func:`davis_rig.attack.reproduce.reproduce_table` call."""
    _starting("reproduce", args)
    import torch

    from davis_rig.attack import evaluate as ev
    from davis_rig.attack.optimize import AttackInterrupted, load_attack_detector
    from davis_rig.attack.reproduce import reproduce_table

    if args.threads:
        torch.set_num_threads(args.threads)
    device = _device(args.device)
    combos = None if args.combinations is None else [tuple(c.split("+")) for c in args.combinations]
    default_thr = (ev.TABLE2_THRESHOLD,) if args.table == 2 else ev.PAPER_THRESHOLDS
    detector = load_attack_detector(args.detector, device=device)
    try:
        res = reproduce_table(args.table, detector, args.out, attack=_attack_config(args, 10, None),
                              eval_config=_eval_config(args, default_thr), grids=args.grids, combinations=combos,
                              train_motions=_motions(args, "train"), test_motions=_motions(args, "test"),
                              detector_name=str(args.detector) if args.detector else "bundled default",
                              command=_command_line(), progress=not args.no_progress)
    except AttackInterrupted as exc:
        return _interrupted("reproduce", exc)
    print(res["markdown"].read_text())
    print(json.dumps({"markdown": str(res["markdown"]), "json": str(res["json"]), "plot": str(res["plot"]),
                      "record": str(res["record"])}))
    return 0
