"""Does the attack's gradient point towards a planted trigger? A diagnostic for a recovery that missed it.

On the clips an attack validates on (``davis_rig.attack.validation.validation_clips``: the same ``--cells``,
``--parts`` and ``--seed`` as the run) this takes the gradient of the attack's loss (``--loss``, summed over the
clips in batches) with respect to the cell values at hard grids: ``--random`` random grids (where a recovery
starts) and the trigger with each ``--flipped`` share of its visible cells flipped (inside and at the edge of its
basin). For each it reports, on the visible cells where the grid differs from the trigger
(:func:`davis_rig.controls.planted.descent_towards`), the share whose descent direction moves them towards the
trigger (0.5 is chance), the loss change the gradient predicts for setting them all to the trigger's values, and
the change measured. A trigger that lies downhill (negative change, agreement well above 0.5) from random grids
is one a gradient method can reach; agreement near 0.5 means a per-cell optimizer such as Adam sees little of it.

Whether a low agreement is EoT noise or a bias of the gradient: ``--clip-counts 4 16 64`` also reports the agreement
of the gradient summed over the first 4, 16 and 64 clips (noise averages out as clips are added, a bias does not), and
every row the share of those cells where the gradients of the first and the second half of the clips agree in sign
(``half_consistency``: near 1 the direction is settled, whatever it is; near 0.5 it is noise),
and ``--loss``, ``--loss-anchors`` and ``--v2e-gradient`` set the attack's loss and the backward rule of its event
counts as ``davis-attack optimize`` does, to compare the gradients an attack could follow. ``--contrast c`` takes
every gradient at the grid greyed towards 0.5 (cell values 0.5 ± c/2, as the generator's soft textures are early in
a run), where the edges between equal cells that a flip would create already carry a little contrast; the loss
change measured is then from that greyed grid.

Run: ``python tools/trigger_gradient_check.py --detector victim/model.safetensors --trigger victim/trigger.npy
[--random 6] [--flipped 0.2 0.3 0.4] [--clips 16] [--clip-counts 4 16] [--out result.json] [--threads 1]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import (PART_CHOICES, add_detector, add_out, add_quiet, add_threads, add_trigger,
                                       float_in, new_parser, non_negative_int, positive_int, probability,
                                       run_main)

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/trigger_gradient_check.py --detector victim/model.safetensors "
                        "--trigger victim/trigger.npy --threads 1\n")
    add_detector(parser, help="the trigger victim's weights (default: the bundled detector)")
    add_trigger(parser)
    parser.add_argument("--cells", type=positive_int, default=10, help="grid cells per side (default 10)")
    parser.add_argument("--parts", nargs="+", choices=PART_CHOICES, default=["torso", "arms", "legs"], metavar="PART",
                        help="painted parts of the run: torso, arms, legs, head, hands, feet, or all")
    parser.add_argument("--loss", choices=("mean", "top"), default="top",
                        help="the attack's loss reduction (default top, as the recovery runs)")
    parser.add_argument("--loss-anchors", choices=("all", "person"), default="all",
                        help="anchors the loss scores: all (default, paper) or person")
    parser.add_argument("--v2e-gradient", choices=("relaxed", "ste"), default="relaxed",
                        help="backward of the event counts: relaxed (default) or ste (the paper's straight-through)")
    parser.add_argument("--clips", type=positive_int, default=16, help="validation clips of the run (default 16)")
    parser.add_argument("--clip-counts", type=positive_int, nargs="*", default=[], metavar="K",
                        help="also report the agreement of the gradient over the first K clips (multiples of "
                             "--batch, at most --clips)")
    parser.add_argument("--batch", type=positive_int, default=4, help="clips per backward pass (default 4)")
    parser.add_argument("--contrast", type=float_in(0.0, 1.0, low_open=True), default=1.0,
                        help="take the gradients at 0.5 + contrast * (grid - 0.5) (default 1: the hard grids)")
    parser.add_argument("--random", type=non_negative_int, default=6, help="random grids (default 6)")
    parser.add_argument("--flipped", type=probability, nargs="*", default=[0.2, 0.3, 0.4], metavar="SHARE",
                        help="the trigger with these shares of its visible cells flipped (default 0.2 0.3 0.4)")
    parser.add_argument("--seed", type=int, default=0, help="the run's --seed (clips), and the grids' draws")
    add_out(parser, metavar="JSON", help="also write the rows as JSON here")
    add_threads(parser, help="torch CPU threads (1 is fastest on a shared machine)")
    add_quiet(parser)
    return run_main(parser, argv, _run, check=_check_clip_counts)


def _check_clip_counts(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Each ``--clip-counts`` K ends a batch and lies within ``--clips`` (exit 2 otherwise)."""
    for count in args.clip_counts:
        if count > args.clips or count % args.batch:
            parser.error(f"argument --clip-counts: {count} is not a multiple of --batch {args.batch} within "
                         f"--clips {args.clips}")


def _run(args: argparse.Namespace) -> int:
    import torch

    from davis_rig.attack.optimize import AttackConfig, attack_loss, load_attack_detector
    from davis_rig.cli.common import tool_provenance
    from davis_rig.attack.refine import visible_cells
    from davis_rig.attack.validation import validation_clips
    from davis_rig.controls.planted import descent_towards, flip_fraction, sign_consistency, trigger_grid
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    if args.threads:
        torch.set_num_threads(args.threads)
    n = args.cells
    parts = None if args.parts == ["all"] else tuple(args.parts)
    trigger, trigger_source = trigger_grid(n, seed=args.seed, path=args.trigger, white_parts=args.trigger_white_parts)
    detector = load_attack_detector(args.detector)
    config = AttackConfig(grid_n=n, parts=parts, seed=args.seed, loss_reduction=args.loss,
                          loss_anchors=args.loss_anchors, v2e_gradient=args.v2e_gradient)
    say = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    say(f"preparing {args.clips} validation clips ({n}x{n}, seed {args.seed})")
    clips = validation_clips(config, BodyModel(), part_mask(parts) if parts is not None else None, args.clips)
    visible = visible_cells(clips, n)

    def loss_and_gradient(grid: np.ndarray) -> tuple[float, np.ndarray, dict[int, np.ndarray]]:
        """The loss summed over the clips, its gradient [n, n], and the gradient over the first K clips per K."""
        cells = torch.tensor(grid, dtype=torch.float32, requires_grad=True)
        total, prefixes = 0.0, {}
        for start in range(0, len(clips), args.batch):
            loss = attack_loss(cells, clips[start:start + args.batch], detector, config).total
            loss.backward()
            total += float(loss.detach())
            if start + args.batch in (*args.clip_counts, half):
                prefixes[start + args.batch] = cells.grad.numpy().astype(np.float64).copy()
        return total, cells.grad.numpy().astype(np.float64), prefixes

    half = len(clips) // 2 if (len(clips) // 2) % args.batch == 0 else None  # the halves' gradients, when batches split
    rng = np.random.default_rng(args.seed)
    grids = [(f"random {k}", (rng.random((n, n)) > 0.5).astype(np.float32)) for k in range(args.random)]
    grids += [(f"trigger, {share:.0%} flipped", flip_fraction(trigger, share, rng, visible)) for share in args.flipped]
    loss_at_trigger = loss_and_gradient(trigger)[0]
    rows = []
    for name, grid in grids:
        loss, gradient, prefixes = loss_and_gradient(0.5 + args.contrast * (grid - 0.5))
        row = {"grid": name, "loss": loss, **descent_towards(gradient, grid, trigger, visible),
               "measured_change": loss_at_trigger - loss}
        if args.clip_counts:
            row["agreement_by_clips"] = {str(k): descent_towards(prefixes[k], grid, trigger, visible)
                                         ["descent_agreement"] for k in sorted(set(args.clip_counts))}
        row["half_consistency"] = (None if half is None else
                                   sign_consistency(prefixes[half], gradient - prefixes[half], grid, trigger, visible))
        rows.append(row)
        say(f"{name}: agreement {_share(row['descent_agreement'])} on {row['differing_cells']} cells, change predicted "
            f"{row['first_order_change']:.4g}, measured {row['measured_change']:.4g}")
    print("| grid | differing visible cells | descent towards the trigger (chance 0.5) | over the first K clips | "
          "halves agreeing in sign | loss | change to the trigger: first-order / measured |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        by_clips = ", ".join(f"{k}: {_share(v)}" for k, v in r.get("agreement_by_clips", {}).items()) or "—"
        print(f"| {r['grid']} | {r['differing_cells']} | {_share(r['descent_agreement'])} | {by_clips} | "
              f"{_share(r['half_consistency'])} | {r['loss']:.4g} | "
              f"{r['first_order_change']:.4g} / {r['measured_change']:.4g} |")
    if args.out:
        report = {**tool_provenance(Path(__file__).name, args.argv),
                  "detector": str(args.detector) if args.detector else "bundled default", "trigger": trigger_source,
                  "cells": n, "parts": parts, "loss": args.loss, "loss_anchors": args.loss_anchors,
                  "v2e_gradient": args.v2e_gradient, "contrast": args.contrast, "clips": args.clips, "seed": args.seed,
                  "visible_cells": int(visible.sum()), "loss_at_trigger": loss_at_trigger, "rows": rows}
        Path(args.out).write_text(json.dumps(report, indent=1))
    return 0


def _share(value: float | None) -> str:
    """A share for the table; "—" where no visible cell differs from the trigger (e.g. ``--flipped 0``)."""
    return "—" if value is None else f"{value:.3f}"


if __name__ == "__main__":
    raise SystemExit(main())
