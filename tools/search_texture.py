"""A gradient-free texture search: the cross-entropy method over black/white grids against a detector.

``davis-attack optimize`` follows the loss's gradient, as the paper does. This searches the same grids without it
(``davis_rig.attack.search``): each generation draws ``--population`` hard grids from one probability of white per
visible cell, scores them all on the same ``--clips-per-grid`` EoT clips (drawn from a pool of ``--pool-clips``
clips of the attack's training distribution; exact event counts from each clip's own sensor; mean top pedestrian
score), and moves every probability ``--smoothing`` of the way towards the share of white in the ``--elite``
best grids. Every ``--validate-every`` generations the most likely grid is validated on ``--val-clips`` clips,
the same clips ``davis-attack optimize --seed S`` validates on, and the best is kept. ``--trigger`` names a
planted trigger that the log compares each generation's grid with (never shown to the search).

The run folder: ``log.jsonl`` (one record per generation), ``probabilities.npy``, ``texture.npy/png`` (the final
most likely grid), ``best_texture.npy/png`` + ``best.json`` (the best validated) and ``search.json``; score the
textures with ``davis-attack evaluate --texture NAME=PATH``. Ctrl-C (or SIGTERM) abandons the generation under
way, keeps the finished ones in the folder and exits 130.

Run: ``python tools/search_texture.py --out run --detector CKPT [--cells 10] [--generations 60] [--population 12]
[--elite 3] [--smoothing 0.2] [--clips-per-grid 8] [--seed 0] [--threads 1]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


NAME = Path(__file__).name


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import (PART_CHOICES, add_detector, add_out, add_quiet, add_threads, float_in,
                                       new_parser, positive_int, run_main)

    parser = new_parser(NAME, __doc__.splitlines()[0],
                        "examples:\n  python tools/search_texture.py --out out/cem_0 "
                        "--detector victim/model.safetensors --trigger victim/trigger.npy --threads 1\n")
    add_out(parser, metavar="DIR", help="the run folder (created; an existing run in it is replaced)",
            required=True)
    add_detector(parser, help="the victim's weights (default: the bundled detector)")
    parser.add_argument("--cells", type=positive_int, default=10, help="grid cells per side (default 10)")
    parser.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                        help="painted parts: torso, arms, legs, head, hands, feet, or all")
    parser.add_argument("--generations", type=positive_int, default=60, help="generations (default 60)")
    parser.add_argument("--population", type=positive_int, default=12, help="grids per generation (default 12)")
    parser.add_argument("--elite", type=positive_int, default=3,
                        help="best grids the probabilities move towards (default 3)")
    parser.add_argument("--smoothing", type=float_in(0.0, 1.0, low_open=True), default=0.2,
                        help="step of each probability towards the elite's share of white, in (0, 1] (default 0.2)")
    parser.add_argument("--floor", type=float_in(0.0, 0.5, high_open=True), default=0.02,
                        help="probabilities stay in [floor, 1 - floor] (default 0.02)")
    parser.add_argument("--pool-clips", type=positive_int, default=32, help="EoT clips prepared (default 32)")
    parser.add_argument("--clips-per-grid", type=positive_int, default=8,
                        help="clips each generation's grids are scored on (default 8)")
    parser.add_argument("--val-clips", type=positive_int, default=64, help="validation clips (default 64)")
    parser.add_argument("--validate-every", type=positive_int, default=10,
                        help="generations between validations (default 10; also after the last)")
    parser.add_argument("--trigger", default=None, metavar="NPY",
                        help="a planted trigger [n, n] (.npy or image) each generation's grid is compared with")
    parser.add_argument("--seed", type=int, default=0, help="seed of the grids, the clips and the validation")
    add_threads(parser, help="torch CPU threads (1 is fastest on a shared machine)")
    add_quiet(parser)
    return run_main(parser, argv, _run, check=_check)


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Cross-option rules (exit 2)."""
    if args.elite > args.population:
        parser.error(f"argument --elite: {args.elite} is more than --population {args.population}")
    if args.population < 2:
        parser.error("argument --population: needs at least 2 grids")
    if args.clips_per_grid > args.pool_clips:
        parser.error(f"argument --clips-per-grid: {args.clips_per_grid} is more than --pool-clips {args.pool_clips}")


def _run(args: argparse.Namespace) -> int:
    import torch

    from davis_rig.attack.config import AttackConfig
    from davis_rig.attack.optimize import load_attack_detector
    from davis_rig.attack.search import SearchSettings, search_texture
    from davis_rig.cli.common import (EXIT_INTERRUPTED, EXIT_OK, check_out_folder, removing_new_empty_dirs,
                                       tool_provenance)
    from davis_rig.controls.planted import trigger_grid
    from davis_rig.stop import StopOnSignal

    if args.threads:
        torch.set_num_threads(args.threads)
    parts = None if args.parts == ["all"] else tuple(args.parts)
    n = args.cells
    reference = None if args.trigger is None else trigger_grid(n, path=args.trigger)[0]
    check_out_folder(args.out)
    detector = load_attack_detector(args.detector)
    config = AttackConfig(grid_n=n, parts=parts, seed=args.seed, num_validation_clips=args.val_clips)
    settings = SearchSettings(generations=args.generations, population=args.population, elite=args.elite,
                              smoothing=args.smoothing, floor=args.floor)
    say = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    with removing_new_empty_dirs(args.out), StopOnSignal() as stop:
        result = search_texture(config, detector, args.out, settings, pool_clips=args.pool_clips,
                                clips_per_grid=args.clips_per_grid, validate_every=args.validate_every,
                                reference=reference, say=say, stop=stop)
    run = {**tool_provenance(NAME),
           "detector": str(args.detector) if args.detector else "bundled default", "parts": parts, **result}
    Path(args.out, "run.json").write_text(json.dumps(run, indent=1))
    best = result["best"]
    print(f"{result['generations']} generations in {result['seconds']:.0f} s"
          + ("" if best is None else f"; kept generation {best['generation']}: validation top score "
             f"{best['mean_top_score']:.3f}, SeqASR {best['SeqASR']:.1%}"))
    if result["stopped"]:
        print(f"{NAME}: stopped after {result['generations']} finished generations, kept in {args.out}",
              file=sys.stderr)
        print(f"{NAME}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK


if __name__ == "__main__":
    raise SystemExit(main())
