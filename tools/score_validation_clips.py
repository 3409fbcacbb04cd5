"""Score textures on the clips an attack validates on: its EoT distribution, not the paper's test protocol.

``davis-attack optimize`` chooses its texture on ``--val-clips`` clips drawn from its training distribution
(backgrounds, lights, placements, sensors; davis_rig.attack.validation.validation_clips). This tool draws the same
clips (the same ``--cells``, ``--parts`` and ``--seed`` as the run) and scores white, black, ``--random`` random
n x n grids (with more than one, also their mean: one random grid is a noisy reference) and any ``--texture`` on
them, as tested (ideal sensor, exact events) and as trained (each clip's own sensor): the baselines an optimised
texture must beat where it was chosen. ``.npy`` textures keep their grey levels (float [n, n] in [0, 1]); images
are read as black/white grids (as ``davis-attack evaluate``).

Run: ``python tools/score_validation_clips.py --detector CKPT --cells 60 --texture ours=run/best_texture.npy
[--out result.json] [--threads 1]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import (PART_CHOICES, add_detector, add_out, add_quiet, add_threads, name_and_path,
                                       new_parser, non_negative_int, positive_int, probability, run_main)

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/score_validation_clips.py --cells 10 --texture ours=run/texture.npy "
                        "--threads 1\n")
    add_detector(parser)
    parser.add_argument("--cells", type=positive_int, default=10, help="grid cells per side of the run (default 10)")
    parser.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                        help="painted parts of the run: torso, arms, legs, head, hands, feet, or all")
    parser.add_argument("--texture", type=name_and_path, action="append", default=[], metavar="NAME=PATH",
                        help="a texture to score (.npy keeps grey levels; .png etc. read as black/white); repeatable")
    parser.add_argument("--clips", type=positive_int, default=64, help="validation clips (default 64, the run's)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="the run's --seed (default 0)")
    parser.add_argument("--random", type=positive_int, default=1, metavar="K",
                        help="random grids scored, drawn with seeds --seed ... --seed + K - 1 (default 1); with "
                             "K > 1 a row of their mean follows")
    parser.add_argument("--threshold", type=probability, default=0.25, metavar="T",
                        help="confidence threshold of SeqASR (default 0.25)")
    add_out(parser, metavar="JSON", help="also write the rows as JSON here")
    add_threads(parser, help="torch CPU threads (1 is fastest on a shared machine)")
    add_quiet(parser)
    return run_main(parser, argv, _run)


def mean_row(name: str, rows: list[dict]) -> dict:
    """The mean of the score rows' SeqASR and top scores, as tested and as trained (a reference of several grids)."""
    keys = ("SeqASR", "mean_top_score", "train_SeqASR", "train_top_score")
    return {"texture": name, **{key: float(np.mean([row[key] for row in rows])) for key in keys},
            "num_sequences": rows[0]["num_sequences"], "of": [row["texture"] for row in rows]}


def load_texture(path: str | Path) -> np.ndarray:
    """A texture as float32 [n, n] in [0, 1]: ``.npy`` as stored (grey levels kept), images as black/white grids.

    Raises:
        FileNotFoundError: no such file. FormatError: not a square 2-D array of finite values in [0, 1].
    """
    from davis_rig.attack.export import load_texture_grid
    from davis_rig.errors import FormatError

    path = Path(path)
    if path.suffix.lower() != ".npy":
        return load_texture_grid(path)
    if not path.is_file():
        raise FileNotFoundError(f"texture not found: {path}")
    try:
        grid = np.load(path, allow_pickle=False).astype(np.float32)
        while grid.ndim > 2 and grid.shape[0] == 1:  # [1, n, n]; a 1x1 grid stays 2-D
            grid = grid[0]
    except (OSError, ValueError, EOFError, AttributeError) as exc:
        raise FormatError(f"{path}: not a readable .npy array ({exc})") from exc
    if grid.ndim != 2 or grid.shape[0] != grid.shape[1] or not np.all(np.isfinite(grid)) \
            or grid.min() < 0 or grid.max() > 1:
        raise FormatError(f"{path}: expected a square [n, n] array of values in [0, 1], got shape {grid.shape}")
    return grid


def _run(args: argparse.Namespace) -> int:
    import torch

    from davis_rig.attack.optimize import AttackConfig, load_attack_detector
    from davis_rig.cli.common import check_out_folder, tool_provenance
    from davis_rig.attack.texture import random_texture
    from davis_rig.attack.validation import validate, validation_clips
    from davis_rig.errors import FormatError
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.out is not None and Path(args.out).is_dir():
        raise FormatError(f"{args.out}: --out names the JSON file to write, and it is a folder")
    if args.out is not None:
        check_out_folder(Path(args.out).parent)  # before the slow part
    parts = None if args.parts == ["all"] else tuple(args.parts)
    n = args.cells
    textures = {"white": np.ones((n, n), np.float32), "black": np.zeros((n, n), np.float32)}
    random_names = [f"random {n}x{n}"] if args.random == 1 else \
        [f"random {n}x{n}, seed {args.seed + k}" for k in range(args.random)]
    textures.update({name: random_texture(n, seed=args.seed + k) for k, name in enumerate(random_names)})
    for name, path in args.texture:  # all read and checked before the slow part
        textures[name] = load_texture(path)
        if textures[name].shape != (n, n):
            raise FormatError(f"{path}: a {textures[name].shape[0]}x{textures[name].shape[1]} texture, the run's "
                              f"--cells is {n}")
    detector = load_attack_detector(args.detector)
    config = AttackConfig(grid_n=n, parts=parts, seed=args.seed, num_validation_clips=args.clips)
    say = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    say(f"preparing {args.clips} validation clips ({n}x{n}, seed {args.seed})")
    clips = validation_clips(config, BodyModel(), part_mask(parts) if parts is not None else None, args.clips)
    rows = []
    for name, grid in textures.items():
        res = validate(grid, clips, detector, args.threshold, config.events,
                       train_path=(config.v2e_mode, config.v2e_binning))
        rows.append({"texture": name, **res})
        say(f"{name}: top score {res['mean_top_score']:.3f}, SeqASR {res['SeqASR']:.1%}")
        if name == random_names[-1] and len(random_names) > 1:
            rows.append(mean_row(f"random {n}x{n}, mean of {len(random_names)}", rows[-len(random_names):]))
    print(f"| texture | SeqASR % @ {args.threshold:g} | mean top score | as trained: SeqASR % / top score |")
    print("|---|---|---|---|")
    for r in rows:
        print(f"| {r['texture']} | {100 * r['SeqASR']:.1f} | {r['mean_top_score']:.3f} | "
              f"{100 * r['train_SeqASR']:.1f} / {r['train_top_score']:.3f} |")
    if args.out:
        report = {**tool_provenance(Path(__file__).name, args.argv),
                  "detector": str(args.detector) if args.detector else "bundled default", "cells": n,
                  "parts": parts, "clips": args.clips, "seed": args.seed, "threshold": args.threshold, "rows": rows}
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
