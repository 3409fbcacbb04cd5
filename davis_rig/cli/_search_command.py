"""``davis-attack search``: the gradient-free texture search (the cross-entropy method over black/white grids).

Maps its arguments onto :func:`davis_rig.attack.search.search_texture`; heavy imports happen in the action.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from davis_rig.cli.common import PART_CHOICES, add_out, epilog, float_in, non_negative_int, positive_int, probability

EXAMPLES = """\
examples:
  davis-attack search --out runs/cem_0 --detector victim/model.safetensors --threads 1
  davis-attack search --out runs/cem_0 --detector victim/model.safetensors --resume --generations 80   # continue
  davis-attack search --out runs/cem_refine --start runs/n10/best_texture.npy --start-confidence 0.8
  davis-attack search --out runs/cem_t --detector victim/model.safetensors --trigger victim/trigger.npy

Each generation draws --population hard grids from one probability of white per visible cell, scores them all
on the same --clips-per-grid EoT clips (drawn from --pool-clips clips of the attack's training distribution;
exact event counts from each clip's own sensor; mean top pedestrian score) and moves every probability
--smoothing of the way towards the share of white in the --elite best grids. Every --validate-every generations
the most likely grid is validated on --val-clips clips (the clips `davis-attack optimize --seed S` validates on)
and the best is kept.

RUN_DIR gets log.jsonl (a record per generation), probabilities.npy, texture.npy/png (the final most likely grid),
best_texture.npy/png + best.json (the best validated), search.json, run.json and state.json. Ctrl-C or SIGTERM
abandons the generation under way and exits 130; --resume then continues after the last finished generation,
scoring the same grids on the same clips as a run that was never stopped (--generations and --validate-every may
change, nothing else; a run started with --start continues around its own start grid when --start is left out).
Score the textures with `davis-attack evaluate --texture NAME=PATH`.
"""


def add_search_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``search`` on the ``davis-attack`` subparsers; the action is stored as ``func``."""
    from davis_rig.cli._attack_commands import _cells, _common_run_args, scene_kind_args

    p = subparsers.add_parser("search", help="gradient-free texture search (cross-entropy method, resumable)",
                              description="Search black/white grids against a frozen RVT without the gradient: the "
                                          "cross-entropy method on one probability of white per cell.",
                              epilog=epilog(EXAMPLES), formatter_class=argparse.RawDescriptionHelpFormatter)
    add_out(p, required=True, metavar="RUN_DIR", help="run folder")
    p.add_argument("--cells", type=_cells, default=10, help="grid cells per side n (default 10)")
    p.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                   help="painted body parts: torso, arms, legs, head, hands, feet (default: torso arms legs); "
                        "'all' = whole body without mask")
    p.add_argument("--generations", type=positive_int, default=60, help="generations (default 60)")
    p.add_argument("--population", type=positive_int, default=12, help="grids per generation (default 12)")
    p.add_argument("--elite", type=positive_int, default=3,
                   help="best grids the probabilities move towards (default 3)")
    p.add_argument("--smoothing", type=float_in(0.0, 1.0, low_open=True), default=0.2,
                   help="step of each probability towards the elite's share of white, in (0, 1] (default 0.2)")
    p.add_argument("--floor", type=float_in(0.0, 0.5, high_open=True), default=0.02,
                   help="probabilities stay in [floor, 1 - floor] (default 0.02)")
    p.add_argument("--pool-clips", type=positive_int, default=32, help="EoT clips prepared (default 32)")
    p.add_argument("--clips-per-grid", type=positive_int, default=8,
                   help="clips each generation's grids are scored on (default 8)")
    p.add_argument("--val-clips", type=positive_int, default=64, help="validation clips (default 64)")
    p.add_argument("--validate-every", type=positive_int, default=10,
                   help="generations between validations (default 10; also after the last)")
    p.add_argument("--start", default=None, metavar="PATH",
                   help="a black/white n x n grid (.npy / image, e.g. davis-attack optimize's best_texture.npy) "
                        "the search starts around instead of from no prior; validated first (generation 0)")
    p.add_argument("--start-confidence", type=float_in(0.5, 1.0, high_open=True), default=0.9, metavar="P",
                   help="with --start: the probability that a draw keeps the start's colour of a cell, in "
                        "[0.5, 1) (default 0.9)")
    p.add_argument("--trigger", default=None, metavar="PATH",
                   help="a planted trigger n x n (.npy / image) each generation's grid is compared with (the log's "
                        "agreement); never shown to the search")
    p.add_argument("--resume", action="store_true",
                   help="continue RUN_DIR/state.json after its last finished generation (a clean new run when "
                        "RUN_DIR holds no run; --start and --start-confidence default to the run's own); without "
                        "it RUN_DIR must not hold a run")
    p.add_argument("--select-by", choices=["seqasr", "score"], default="seqasr",
                   help="best texture on validation, scored as trained: seqasr (SeqASR, then mean top score; as "
                        "optimize) or score (mean top score alone)")
    p.add_argument("--test-sensor-probability", type=probability, default=0.5, metavar="P",
                   help="share of the search and validation clips whose sensor is the evaluation's ideal one "
                        "(default 0.5, as optimize)")
    scene_kind_args(p)
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the grids, the clips and the validation")
    _common_run_args(p)
    p.set_defaults(func=search_command, check=_check_search)
    return p


def _check_search(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Cross-option rules (exit 2, before anything is loaded)."""
    if "all" in args.parts and len(args.parts) > 1:
        parser.error("argument --parts: 'all' (the whole body) cannot be combined with other parts")
    if args.population < 2:
        parser.error("argument --population: needs at least 2 grids")
    if args.elite > args.population:
        parser.error(f"argument --elite: {args.elite} is more than --population {args.population}")
    if args.clips_per_grid > args.pool_clips:
        parser.error(f"argument --clips-per-grid: {args.clips_per_grid} is more than --pool-clips {args.pool_clips}")


def _grid_file(path: str, n: int, option: str):
    """A black/white n x n grid from ``path`` (FileNotFoundError / FormatError naming ``option`` otherwise)."""
    from davis_rig.attack.export import load_texture_grid
    from davis_rig.errors import FormatError

    grid = load_texture_grid(path)
    if grid.shape != (n, n):
        raise FormatError(f"{path}: {option} is a {grid.shape[0]}x{grid.shape[1]} grid, the run's --cells is {n}")
    return grid


def search_command(args) -> int:
    """Action of ``davis-attack search``: one :func:`davis_rig.attack.search.search_texture` call."""
    from davis_rig.cli._attack_commands import _command_line, _eot_config, _motions, _set_threads, _starting
    from davis_rig.cli.common import check_out_folder, removing_new_empty_dirs, resolve_device

    n = args.cells
    start = None if args.start is None else _grid_file(args.start, n, "--start")
    reference = None if args.trigger is None else _grid_file(args.trigger, n, "--trigger")
    check_out_folder(args.out)
    _starting("search", args)
    import platform
    import time

    from davis_rig.attack.config import AttackConfig
    from davis_rig.attack.optimize import load_attack_detector
    from davis_rig.attack.search import SearchSettings, search_texture
    from davis_rig.stop import StopOnSignal

    _set_threads(args)
    parts = None if args.parts == ["all"] else tuple(args.parts)
    detector = load_attack_detector(args.detector, device=resolve_device(args.device))
    relaxed = args.events == "official_relaxed"  # the relaxed counts in the search and the validation, as optimize
    config = AttackConfig(eot=_eot_config(args), grid_n=n, parts=parts, seed=args.seed,
                          num_validation_clips=args.val_clips, select_by=args.select_by, events=args.events,
                          v2e_mode="official_relaxed" if relaxed else "dvs")
    settings = SearchSettings(generations=args.generations, population=args.population, elite=args.elite,
                              smoothing=args.smoothing, floor=args.floor)
    say = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    with removing_new_empty_dirs(args.out), StopOnSignal() as stop:
        result = search_texture(config, detector, args.out, settings, pool_clips=args.pool_clips,
                                clips_per_grid=args.clips_per_grid, validate_every=args.validate_every,
                                motions=_motions(args, "train"), reference=reference, start_grid=start,
                                start_confidence=args.start_confidence, resume=args.resume, say=say, stop=stop)
    run = {"command": _command_line(args), "measured": time.strftime("%Y-%m-%d"),
           "machine": f"{platform.machine()}, {platform.node()}",
           "detector": str(args.detector) if args.detector else "bundled default", "parts": parts, **result}
    Path(args.out, "run.json").write_text(json.dumps(run, indent=1))
    best = result["best"]
    print(json.dumps({"out_dir": str(args.out), "generations": result["generations"],
                      "seconds": round(result["seconds"], 1), "cells": result["cells"],
                      "best_generation": None if best is None else best["generation"],
                      "best_top_score": None if best is None else best["mean_top_score"],
                      "best_seq_asr": None if best is None else best["SeqASR"]}))
    if result["stopped"]:
        print(f"davis-attack search: interrupted after {result['generations']} finished generations, kept in "
              f"{args.out}; continue with --resume", file=sys.stderr)
        return 130
    return 0
