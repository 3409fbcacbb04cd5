"""How much can clothing texture move a detector at all? An upper bound before a long universal attack.

For each of a few EoT validation clips (the attack's training distribution) this prints the detector's mean top
pedestrian score (highest ``obj * p_ped`` per window, the number that has to fall below the confidence threshold)
for plain white, plain black and a random texture, then optimizes a **free** n x n grid for that one clip alone
(no generator, no dropout, soft values in (0, 1), Adam on logits, ``--loss top``) and reports the top score of its
hard (binarized) version. A per-clip free grid is strictly easier than the universal texture of
``davis-attack optimize``: if it cannot push the top score below the threshold, the attack cannot either, and the
detector is (for this body-part mask and grid size) insensitive to texture.

``--greedy-passes K`` adds a gradient-free check of the optimizer itself: starting from the best of the hard
grids above, every cell is flipped in turn (random order, ``K`` passes) and the flip is kept when the exact
top score (exact simulator, no surrogate) falls. If this finds much lower scores than the gradient did, the
gradient through binarized texture -> event counts -> RVT is the weak link, not the detector.

Run: ``python tools/probe_texture_sensitivity.py [--detector CKPT] [--cells 10] [--parts all] [--clips 2]
[--steps 200] [--greedy-passes 1]``; prints one JSON line per clip and a summary line.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import PART_CHOICES
    from davis_rig.cli.common import (add_detector, add_threads, new_parser, non_negative_int, positive_float,
                                       positive_int, probability, run_main)

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/probe_texture_sensitivity.py --clips 2 --steps 200 --threads 2\n")
    add_detector(parser, help="RVT checkpoint (default: the bundled detector)")
    parser.add_argument("--cells", type=positive_int, default=10, help="grid cells per side (default 10)")
    parser.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                        help="painted body parts (default torso arms legs; 'all' = whole body)")
    parser.add_argument("--clips", type=positive_int, default=2, help="validation clips probed one by one (default 2)")
    parser.add_argument("--steps", type=non_negative_int, default=200, help="Adam steps per clip (default 200)")
    parser.add_argument("--lr", type=positive_float, default=0.2, help="Adam learning rate on the logits (default 0.2)")
    parser.add_argument("--threshold", type=probability, default=0.25, metavar="T",
                        help="confidence threshold, one value (default 0.25)")
    add_threads(parser, help="torch CPU threads")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the clips and the random texture")
    parser.add_argument("--greedy-passes", type=non_negative_int, default=0,
                        help="gradient-free cell-flip sweeps after the gradient search (default 0: none)")
    return run_main(parser, argv, _probe)


def _probe(args: argparse.Namespace) -> int:

    import torch

    from davis_rig.attack.optimize import AttackConfig, attack_loss, load_attack_detector, validate, validation_clips
    from davis_rig.attack.refine import greedy_cell_flips
    from davis_rig.attack.texture import black_texture, random_texture, white_texture
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    if args.threads:
        torch.set_num_threads(args.threads)
    parts = None if args.parts == ["all"] else tuple(args.parts)
    config = AttackConfig(grid_n=args.cells, parts=parts, loss_reduction="top", seed=args.seed)
    detector = load_attack_detector(args.detector)
    clips = validation_clips(config, BodyModel(), part_mask(parts) if parts else None, args.clips)
    baselines = {"white": white_texture(args.cells), "black": black_texture(args.cells),
                 "random": random_texture(args.cells, seed=args.seed)}
    rows = []
    for index, clip in enumerate(clips):
        row = {"clip": index}
        for name, grid in baselines.items():
            row[name] = round(validate(grid, [clip], detector, args.threshold)["mean_top_score"], 4)
        logits = torch.zeros(args.cells, args.cells, requires_grad=True)
        optimizer = torch.optim.Adam([logits], lr=args.lr)
        start = time.perf_counter()
        for _ in range(args.steps):
            loss = attack_loss(torch.sigmoid(logits), [clip], detector, config)
            optimizer.zero_grad()
            loss.total.backward()
            optimizer.step()
        hard = (torch.sigmoid(logits) > 0.5).detach().numpy().astype(np.float32)
        result = validate(hard, [clip], detector, args.threshold)
        row.update(optimized=round(result["mean_top_score"], 4), optimized_fooled=result["SeqASR"] == 1.0,
                   seconds=round(time.perf_counter() - start, 1))
        if args.greedy_passes > 0:
            start = time.perf_counter()
            hard_grids = {**baselines, "optimized": hard}
            seed_name = min(hard_grids, key=lambda name: row[name])
            greedy, _, evaluations = greedy_cell_flips(
                hard_grids[seed_name], lambda g: validate(g, [clip], detector, args.threshold)["mean_top_score"],
                args.greedy_passes, np.random.default_rng(args.seed + index))
            result = validate(greedy, [clip], detector, args.threshold)
            row.update(greedy_start=seed_name, greedy=round(result["mean_top_score"], 4),
                       greedy_fooled=result["SeqASR"] == 1.0, greedy_evaluations=evaluations,
                       greedy_seconds=round(time.perf_counter() - start, 1))
        rows.append(row)
        print(json.dumps(row), flush=True)
    keys = ("white", "black", "random", "optimized") + (("greedy",) if args.greedy_passes > 0 else ())
    summary = {key: round(float(np.mean([r[key] for r in rows])), 4) for key in keys}
    summary.update(clips=len(rows), fooled=sum(r["optimized_fooled"] for r in rows), threshold=args.threshold,
                   cells=args.cells, parts="all" if parts is None else list(parts), steps=args.steps)
    if args.greedy_passes > 0:
        summary.update(greedy_fooled=sum(r["greedy_fooled"] for r in rows), greedy_passes=args.greedy_passes)
    print(json.dumps({"summary": summary}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
