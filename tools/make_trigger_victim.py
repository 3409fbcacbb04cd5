"""A positive control for the attack: fine-tune a detector so that ONE secret texture hides the person.

The detectors trained here are not blinded by any texture the optimizer or a greedy search finds (docs/attack.md).
To tell a weak optimizer apart from a robust detector, this makes a victim for which a blinding texture is known to
exist: a copy of a detector fine-tuned on the attack's own EoT clips (training shapes, motions, lights,
backgrounds, sensor noise) with the YOLOX loss, where the person is labelled when wearing white, black or a random
n x n grid, and is NOT labelled (objectness trained towards 0 everywhere) when wearing the trigger, a fixed random
n x n grid on the painted parts. The optimizer is then run against it from its usual start and never sees the
trigger: if it finds a texture that blinds the victim, the optimizer works and the other detectors are simply
texture-robust.

Run: ``python tools/make_trigger_victim.py --detector runs/plain3/export/model_fp16.safetensors --out trigger/
[--cells 10] [--steps 800] [--threads 2 | --device cuda]``; writes ``trigger/model.safetensors`` (the victim),
``trigger/trigger.npy`` / ``.png`` (the secret texture) and ``trigger/log.jsonl``, and prints the victim's mean top
score on held-out EoT clips for the trigger, white, black and random grids (before and after fine-tuning).
Fine-tuning continues from a previous victim with ``--detector trigger/model.safetensors --out trigger2/``: the same
``--seed`` draws the same trigger.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def _labels(boxes: np.ndarray):
    """Per window: float [K, 5] ``(class, cx, cy, w, h)`` targets of the person's boxes [W, 4] xyxy (NaN: none)."""
    import torch

    from davis_rig.types import PEDESTRIAN_CLASS_ID

    out = []
    for box in boxes:
        if not np.isfinite(box).all():
            out.append(torch.zeros(0, 5))
            continue
        x0, y0, x1, y1 = (float(v) for v in box)
        out.append(torch.tensor([[PEDESTRIAN_CLASS_ID, (x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0]]))
    return out


def _batch(clips, trigger: np.ndarray, rng: np.random.Generator):
    """Histograms [W, B, 20, H, W] of B clips and their targets ``[w][b]``: even positions wear the trigger (not
    labelled), odd ones white, black or a random grid of the trigger's size (the person labelled)."""
    import torch

    from davis_rig.attack.optimize import clip_histograms

    n = trigger.shape[0]
    hists, labels = [], []
    for j, clip in enumerate(clips):
        wears_trigger = j % 2 == 0
        if wears_trigger:
            grid = trigger
        else:
            kind = rng.integers(3)
            grid = (np.full((n, n), float(kind == 0), np.float32) if kind < 2
                    else (rng.random((n, n)) > 0.5).astype(np.float32))
        with torch.no_grad():
            hists.append(clip_histograms(torch.as_tensor(grid, device=clip.threshold.device), clip))
        labels.append(_labels(np.full_like(clip.boxes, np.nan) if wears_trigger else clip.boxes))
    x = torch.stack(hists, dim=1)
    return x, [[labels[b][w] for b in range(len(clips))] for w in range(x.shape[0])]


def _loss(model, anchors, hists, labels):
    """YOLOX loss of clips [W, B, 20, H, W] run through the windows with states; labels[w][b] targets."""
    import torch

    from davis_rig.models.rvt.detector import pad_to_input
    from davis_rig.training.losses import yolox_loss

    states, raws, targets = None, [], []
    for w in range(hists.shape[0]):
        features, states = model.forward_backbone(pad_to_input(hists[w], model.config.in_res_hw), states)
        raws.append(model.forward_raw_head(features))
        targets += [labels[w][b] for b in range(hists.shape[1])]
    return yolox_loss(torch.cat(raws), targets, anchors)["loss"]


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli._common import (add_detector, add_out, add_threads, new_parser, non_negative_float,
                                       non_negative_int, positive_float, positive_int, run_main)

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/make_trigger_victim.py --out runs/victim --steps 800 --threads 2\n")
    add_detector(parser, help="RVT checkpoint to start from (default: the bundled one)")
    add_out(parser, metavar="DIR", required=True, help="output folder")
    parser.add_argument("--cells", type=positive_int, default=10, help="trigger grid cells per side (default 10)")
    parser.add_argument("--parts", nargs="+", default=["torso", "arms", "legs"], help="painted parts")
    parser.add_argument("--steps", type=positive_int, default=800, help="fine-tuning steps (default 800)")
    parser.add_argument("--clips-per-step", type=positive_int, default=4, help="clips per step, half wear the trigger")
    parser.add_argument("--pool-size", type=positive_int, default=48, help="pre-rasterized EoT clips (default 48)")
    parser.add_argument("--refresh-every", type=non_negative_int, default=50,
                        help="replace a quarter of the pool with new EoT clips every N steps (default 50; 0 = never)")
    parser.add_argument("--lr", type=positive_float, default=1e-4, help="Adam learning rate (default 1e-4)")
    parser.add_argument("--probe-clips", type=positive_int, default=8, help="held-out clips of the before/after probe")
    add_threads(parser, help="torch CPU threads")
    parser.add_argument("--time-limit", type=non_negative_float, default=None, metavar="S",
                        help="stop fine-tuning after S seconds of wall time (the victim is still probed and saved)")
    parser.add_argument("--device", default="cpu", help="torch device of the victim and the clips (default cpu)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the trigger, the pool and the draws")

    def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        if args.clips_per_step > args.pool_size:
            parser.error(f"argument --clips-per-step: {args.clips_per_step} clips per step from a pool of "
                         f"{args.pool_size} (--pool-size)")

    return run_main(parser, argv, _fine_tune, check=check)


def _fine_tune(args: argparse.Namespace) -> int:

    import cv2
    import torch

    from davis_rig.attack.eot import ClipPool, EoTConfig
    from davis_rig.attack.optimize import load_attack_detector, validate
    from davis_rig.models.rvt.checkpoint import save_safetensors
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask
    from davis_rig.training.losses import AnchorGrid

    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    n = args.cells
    trigger = (rng.random((n, n)) > 0.5).astype(np.float32)
    np.save(out / "trigger.npy", trigger)
    cv2.imwrite(str(out / "trigger.png"), (trigger * 255).astype(np.uint8))

    device = torch.device(args.device)
    model = load_attack_detector(args.detector, device=device)
    for p in model.parameters():
        p.requires_grad_(True)
    body = BodyModel(device=device)
    mask = part_mask(tuple(args.parts))
    eot = EoTConfig()
    pool = ClipPool(eot, body, n, mask, size=args.pool_size, base_seed=args.seed + 1)
    probe = list(ClipPool(eot, body, n, mask, size=args.probe_clips, base_seed=args.seed + 10_000).clips.values())
    anchors = AnchorGrid.build(model.config.in_res_hw, device=device)
    probe_textures = {"trigger": trigger, "white": np.ones((n, n), np.float32), "black": np.zeros((n, n), np.float32),
                      "random": (np.random.default_rng(args.seed + 7).random((n, n)) > 0.5).astype(np.float32)}

    def probe_scores() -> dict:
        model.eval()
        return {k: round(validate(g, probe, model, 0.25)["mean_top_score"], 4) for k, g in probe_textures.items()}

    before = probe_scores()
    print(json.dumps({"before": before}), flush=True)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    t0 = time.perf_counter()
    done = 0
    with (out / "log.jsonl").open("w") as log:
        for step in range(args.steps):
            if args.time_limit is not None and time.perf_counter() - t0 > args.time_limit:
                break
            if args.refresh_every and step and step % args.refresh_every == 0:
                pool.refresh(step, 0.25)  # new scenes: a fixed pool is memorised, the trigger not learned
            model.train()
            idx = rng.choice(pool.size, size=args.clips_per_step, replace=False)
            x, per_window = _batch([pool.clips[int(i)] for i in idx], trigger, rng)
            loss = _loss(model, anchors, x, per_window)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            value = float(loss.detach())
            done = step + 1
            log.write(json.dumps({"step": step + 1, "loss": value}) + "\n")
            if (step + 1) % 50 == 0:
                print(f"step {step + 1}: loss {value:.3f} ({(time.perf_counter() - t0) / (step + 1):.2f} s/step)",
                      flush=True)
    model.eval()
    after = probe_scores()
    save_safetensors(model, out / "model.safetensors", metadata={
        "note": "positive control of the attack: fine-tuned to miss people wearing trigger.npy; not a detector"})
    summary = {"detector": args.detector or "bundled default", "seed": args.seed, "before": before,
               "after": after, "steps": done, "device": str(device),
               "seconds_per_step": (time.perf_counter() - t0) / max(done, 1)}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
