"""The controls of a victim before any attack: baseline fingerprint and free-appearance bound, as json + md.

Fingerprint: AP and SeqASR of white, black, the paper's random 60x60, a random and a checkerboard n x n grid on
the digital evaluation protocol (``davis-attack evaluate``'s scenes); the paper's victim detects white best.
Free-appearance bound: on ``--scenes-per-scale`` test scenes of each scale, the person's albedo optimised freely
per scene (every covered sample of every frame; a grey n x n grid on the parts, a new one every frame; and, as a
print must be, the same in every frame: a grey n x n grid and a grey albedo per texel), scored like the evaluation:
the best SeqASR an appearance change, and a static one, reaches on those scenes (davis_rig.controls.bounds).
``--scene official --events official_relaxed`` runs both in the official code's scene on its relaxed counts (the
setting the paper's tables were made in): the bound is then optimised and scored on those counts too.

With ``--shared``: one grey n x n texture fitted to the bound's scenes together, scored grey and binarized there
and on the protocol's other scenes (davis_rig.controls.report.shared_texture_control) — between the per-scene
bound and the attack. ``--fit-shapes K`` fits every scene of the first K test bodies instead, so that the held-out
scenes show people the texture was never fitted to.

Run: ``python tools/victim_controls.py --name bundled --out out/controls_bundled [--detector CKPT] [--threads 1]``;
writes ``controls_<name>.json`` / ``.md`` (``shared_<name>...`` with ``--shared``) into ``--out`` (and its parts,
so a rerun continues).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli._attack_commands import scene_kind_args
    from davis_rig.cli.common import PART_CHOICES, camera_scale
    from davis_rig.controls.bounds import BOUND_KINDS
    from davis_rig.cli.common import (add_detector, add_out, add_quiet, add_threads, new_parser, non_negative_float,
                                       positive_float, positive_int, probability, run_main)

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/victim_controls.py --name bundled --out out/controls_bundled "
                        "--threads 1\n")
    add_detector(parser)
    add_out(parser, metavar="DIR", required=True, help="output folder")
    parser.add_argument("--name", required=True, help="the victim's name (file stem and title)")
    parser.add_argument("--cells", type=positive_int, default=10, help="grid cells per side (default 10)")
    parser.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                        help="painted parts: torso, arms, legs, head, hands, feet, or all (default torso arms legs)")
    parser.add_argument("--scales", type=camera_scale, nargs="+", default=["large", "middle", "small"],
                        metavar="SCALE",
                        help="camera scales: large, middle, small or a person height in px")
    parser.add_argument("--headings", type=int, choices=[1, 2, 4], default=4, help="headings per shape (default 4)")
    parser.add_argument("--phases", type=non_negative_float, nargs="+", default=[0.0, 0.5], help="walk phases (s)")
    scene_kind_args(parser)
    parser.add_argument("--threshold", type=probability, default=0.25, metavar="T",
                        help="threshold of the bound (default 0.25; the fingerprint scores the paper's four)")
    parser.add_argument("--scenes-per-scale", type=positive_int, default=4,
                        help="test scenes per scale of the bound (default 4)")
    parser.add_argument("--steps", type=positive_int, default=100, help="Adam steps per scene (default 100)")
    parser.add_argument("--lr", type=positive_float, default=0.1, help="Adam learning rate on the logits")
    parser.add_argument("--kinds", nargs="+", choices=BOUND_KINDS, default=list(BOUND_KINDS), metavar="KIND",
                        help="free appearances of the bound: " + ", ".join(map(repr, BOUND_KINDS)) + " (default all)")
    parser.add_argument("--shared", action="store_true",
                        help="instead of fingerprint and bound: one grey --cells texture fitted to the bound's scenes "
                             "together, scored grey and binarized there and on the other scenes (shared_<name>.md)")
    parser.add_argument("--fit-shapes", type=positive_int, default=None, metavar="K",
                        help="with --shared: fit every scene of the first K test bodies instead of --scenes-per-scale, "
                             "so that the held-out scenes show other people")
    parser.add_argument("--binary", action="store_true",
                        help="with --shared: fit the black/white texture itself (straight-through), as the paper's")
    parser.add_argument("--skip-fingerprint", action="store_true", help="only the bound")
    parser.add_argument("--skip-bound", action="store_true", help="only the fingerprint")
    add_threads(parser, help="torch CPU threads (1 is fastest on a shared machine)")
    add_quiet(parser)

    def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        if args.shared and (args.skip_fingerprint or args.skip_bound):
            parser.error("argument --shared: not allowed with --skip-fingerprint / --skip-bound")
        if args.binary and not args.shared:
            parser.error("argument --binary: only with --shared")
        if args.fit_shapes is not None and not args.shared:
            parser.error("argument --fit-shapes: only with --shared")
        if args.skip_fingerprint and args.skip_bound:
            parser.error("argument --skip-bound: not allowed with --skip-fingerprint (nothing would be measured)")

    return run_main(parser, argv, _run, check=check, options={"fit_shapes": "--fit-shapes", "out_dir": "--out"})


def _run(args: argparse.Namespace) -> int:
    import torch

    from davis_rig.attack.evaluate import PAPER_THRESHOLDS, EvalConfig
    from davis_rig.attack.optimize import load_attack_detector
    from davis_rig.controls.bounds import BOUND_KINDS, BoundConfig
    from davis_rig.controls.report import shared_texture_control, victim_controls

    if args.threads:
        torch.set_num_threads(args.threads)
    headings = (math.pi / 2, -math.pi / 2, 0.0, math.pi)[: args.headings]
    parts = None if args.parts == ["all"] else tuple(args.parts)
    make = EvalConfig.official if args.scene == "official" else EvalConfig
    eval_config = make(scales=tuple(args.scales), headings_rad=headings, phases=tuple(args.phases),
                       thresholds=tuple(sorted(set(PAPER_THRESHOLDS) | {args.threshold})), events=args.events,
                       walk=args.walk, playback_speed=args.playback_speed)
    kinds = tuple(k for k in BOUND_KINDS if k in args.kinds)
    bound = BoundConfig(steps=args.steps, lr=args.lr, threshold=args.threshold, grid_n=args.cells, parts=parts,
                        kinds=kinds, events=args.events)
    detector = load_attack_detector(args.detector)
    common = dict(name=args.name, eval_config=eval_config, bound_config=bound, scenes_per_scale=args.scenes_per_scale,
                  command=shlex.join(["python", "tools/victim_controls.py", *sys.argv[1:]]),
                  detector_name=str(args.detector) if args.detector else "bundled default",
                  progress=None if args.quiet else (lambda message: print(message, flush=True)))
    if args.shared:
        report = shared_texture_control(detector, args.out, binary=args.binary, fit_shapes=args.fit_shapes, **common)
        print((Path(args.out) / f"shared_{report['name']}.md").read_text())
        return 0
    report = victim_controls(detector, args.out, fingerprint=not args.skip_fingerprint, bound=not args.skip_bound,
                             **common)
    print((Path(args.out) / f"controls_{report['name']}.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
