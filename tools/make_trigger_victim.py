"""A positive control for the attack: fine-tune a detector so that ONE secret texture, and only it, hides the person.

The detectors trained here are not blinded by any texture the optimizer or a greedy search finds (docs/attack.md).
To tell a weak optimizer apart from a robust detector, this makes a victim for which a blinding texture is known to
exist: a copy of a detector fine-tuned on the attack's own EoT clips with the YOLOX loss, where the person is NOT
labelled (objectness trained towards 0 everywhere) when wearing the trigger or a grid within ``--basin`` of it (a
share of the visible cells flipped), and IS labelled when wearing anything else: random grids, the trigger with
``--far`` or more of its cells flipped, white, black, a checkerboard (:mod:`davis_rig.controls.planted`). The blind
spot is therefore selective (random grids, which disagree with the trigger on half of the cells, stay detected)
and has a basin a search can climb; ``--ramp D`` grades its edge (a grid disagreeing on d between ``--basin`` and
D is labelled with probability (d - basin) / (D - basin)), so that the score falls with every cell a search gets
right instead of at a cliff; ``--min-contrast C`` shows half of the grids greyed (contrast uniform in [C, 1],
labelled by their black/white pattern), so that the blind spot reaches the grey textures the recipe's soft phase
starts from. The optimizer is then run against it from its usual start and never sees the
trigger: if it finds the trigger's effect, the optimizer works, and a detector it cannot move is texture-robust.

The pool mixes the attack's training distribution with ``--test-like`` clips in the evaluation's scene (uniform
grey background, default light, ideal sensor) at the ``--scales`` (default the evaluation's three), so that the
blind spot holds where the attack is scored; the body shapes are always the training ones.

Run: ``python tools/make_trigger_victim.py --out trigger/ [--detector CKPT] [--cells 10] [--steps 1500]
[--threads 2 | --device cuda]``; writes ``trigger/model.safetensors`` (the victim, also every ``--save-every``
steps), ``trigger/trigger.npy`` / ``.png`` (the secret texture), ``trigger/visible.npy`` (the visible cells),
``trigger/log.jsonl``, ``trigger/checkpoint.pt`` (``--resume`` continues from it) and ``trigger/summary.json``:
mean top score and SeqASR at 0.25 on held-out clips for the trigger, grids at several distances from it, white,
black, checker and random grids, before and after fine-tuning. The same ``--seed`` draws the same trigger;
``--trigger T.npy`` gives one, ``--trigger-white-parts torso arms`` paints whole parts (upper body white, legs
black: a layout the bundled backbone's features carry, unlike a random cell pattern, see
``tools/trigger_feature_probe.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

#: Disagreements with the trigger (share of visible cells flipped) at which the probe scores the blind spot.
_PROBE_DISTANCES = (0.1, 0.2, 0.3, 0.4)
_PROBE_RANDOM = 6


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


def _batch(clips, trigger: np.ndarray, visible: np.ndarray, rng: np.random.Generator, basin: float, far: float,
           ramp: float | None = None, min_contrast: float | None = None):
    """Histograms [W, B, 20, H, W] of B clips and their targets ``[w][b]``: even positions wear a grid of the blind
    spot (not labelled; with a ``ramp``, labelled with the probability of its distance), odd ones anything else
    (labelled unless it fell inside the basin); with ``min_contrast`` half of them greyed. Pass each clip twice in
    a row (``[a, a, b, b, ...]``) to show the same scene in both: then only the clothing tells the pair apart."""
    import torch

    from davis_rig.attack.optimize import clip_histograms
    from davis_rig.controls.planted import sample_training_grid

    hists, labels = [], []
    for j, clip in enumerate(clips):
        grid, _, labelled = sample_training_grid(trigger, rng, hidden=j % 2 == 0, basin=basin, far=far,
                                                 visible=visible, ramp=ramp, min_contrast=min_contrast)
        with torch.no_grad():
            hists.append(clip_histograms(torch.as_tensor(grid, device=clip.threshold.device), clip))
        labels.append(_labels(clip.boxes if labelled else np.full_like(clip.boxes, np.nan)))
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
    from davis_rig.cli.common import PART_CHOICES, camera_scale, device_name
    from davis_rig.cli.common import (add_detector, add_out, add_threads, add_trigger, float_in, new_parser,
                                       non_negative_float, non_negative_int, positive_float, positive_int,
                                       probability, run_main)

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/make_trigger_victim.py --out runs/victim --steps 1500 --threads 2\n")
    add_detector(parser, help="RVT checkpoint to start from (default: the bundled one)")
    add_out(parser, metavar="DIR", required=True, help="output folder")
    parser.add_argument("--cells", type=positive_int, default=10, help="trigger grid cells per side (default 10)")
    add_trigger(parser)
    parser.add_argument("--parts", nargs="+", choices=PART_CHOICES[:-1], default=["torso", "arms", "legs"],
                        metavar="PART",
                        help="painted parts: torso, arms, legs, head, hands, feet (default torso arms legs)")
    parser.add_argument("--steps", type=positive_int, default=1500, help="fine-tuning steps in all (default 1500)")
    parser.add_argument("--clips-per-step", type=positive_int, default=4,
                        help="clips per step, half wear a grid of the blind spot (default 4)")
    parser.add_argument("--no-pairs", dest="paired", action="store_false",
                        help="draw every clip of a step from another scene (default: each scene twice, once in a "
                             "grid of the blind spot and once in another, so that only the clothing differs)")
    parser.add_argument("--basin", type=probability, default=0.2,
                        help="grids disagreeing with the trigger on at most this share of the visible cells are "
                             "hidden (default 0.2)")
    parser.add_argument("--ramp", type=probability, default=None, metavar="D",
                        help="a graded edge instead of a cliff: grids disagreeing on d between --basin and D are "
                             "labelled with probability (d - basin) / (D - basin), so the score falls with every "
                             "cell a search gets right (default: none)")
    parser.add_argument("--min-contrast", type=float_in(0.0, 1.0, low_open=True), default=None, metavar="C",
                        help="show half of the grids greyed to 0.5 + c (grid - 0.5), c uniform in [C, 1], labelled "
                             "by their black/white pattern, so that the blind spot reaches the grey textures a soft "
                             "optimiser starts from (default: black/white grids only)")
    parser.add_argument("--far", type=probability, default=0.35,
                        help="'far' grids disagree on at least this share and are labelled (default 0.35)")
    parser.add_argument("--scales", type=camera_scale, nargs="+", default=["large", "middle", "small"], metavar="SCALE",
                        help="camera scales of the pool (names or person heights in px; default the evaluation's)")
    parser.add_argument("--test-like", type=probability, default=0.5,
                        help="share of the pool in the evaluation's scene: grey background, default light, ideal "
                             "sensor (default 0.5; the rest is the attack's EoT distribution)")
    parser.add_argument("--train-from-stage", type=non_negative_int, default=0,
                        help="freeze backbone stages below this index (0 = train everything; 1 saves the backward "
                             "of the full-resolution stage)")
    parser.add_argument("--pool-size", type=positive_int, default=48, help="pre-rasterized EoT clips (default 48)")
    parser.add_argument("--refresh-every", type=non_negative_int, default=50,
                        help="replace a quarter of the pool with new EoT clips every N steps (default 50; 0 = never)")
    parser.add_argument("--lr", type=positive_float, default=2e-4, help="Adam learning rate (default 2e-4)")
    parser.add_argument("--probe-clips", type=positive_int, default=12, help="held-out clips of the probe (default 12)")
    parser.add_argument("--save-every", type=positive_int, default=100,
                        help="write model.safetensors and checkpoint.pt every N steps (default 100)")
    parser.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pt")
    add_threads(parser, help="torch CPU threads")
    parser.add_argument("--time-limit", type=non_negative_float, default=None, metavar="S",
                        help="stop fine-tuning after S seconds of wall time (the victim is still probed and saved)")
    parser.add_argument("--device", type=device_name, default="cpu",
                        help="torch device of the victim and the clips: auto, cpu, cuda, cuda:N (default cpu)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the trigger, the pool and the draws")

    def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        if args.clips_per_step > args.pool_size:
            parser.error(f"argument --clips-per-step: {args.clips_per_step} clips per step from a pool of "
                         f"{args.pool_size} (--pool-size)")
        if args.paired and args.clips_per_step % 2:
            parser.error(f"argument --clips-per-step: pairs need an even number, got {args.clips_per_step}")
        if args.basin >= args.far:
            parser.error(f"argument --basin: {args.basin} must be below --far {args.far}")
        if args.ramp is not None and args.ramp <= args.basin:
            parser.error(f"argument --ramp: {args.ramp} must be above --basin {args.basin}")
        if args.train_from_stage > 4:
            parser.error(f"argument --train-from-stage: RVT has 4 stages, got {args.train_from_stage}")

    return run_main(parser, argv, _fine_tune, check=check, options={"device": "--device", "trigger": "--trigger"})


def _configs(scales, test_like: float):
    """``(EoTConfig, share of the pool)`` per scale and scene style."""
    from davis_rig.attack.eot import EoTConfig

    out = []
    for scale in scales:
        share = 1.0 / len(scales)
        if test_like < 1.0:
            out.append((EoTConfig(scale=scale), share * (1.0 - test_like)))
        if test_like > 0.0:
            out.append((EoTConfig.test_scene(scale=scale), share * test_like))
    return out


class _Pools:
    """One :class:`~davis_rig.attack.eot.ClipPool` per (scale, style), drawn from in proportion to their sizes."""

    def __init__(self, configs, body, n, mask, size: int, base_seed: int, generations=None):
        from davis_rig.attack.eot import ClipPool

        sizes = [max(1, int(round(share * size))) for _, share in configs]
        self.pools = [ClipPool(cfg, body, n, mask, size=s, base_seed=base_seed + 97 * k,
                               generations=None if generations is None else generations[k])
                      for k, ((cfg, _), s) in enumerate(zip(configs, sizes))]
        self.clips = [clip for pool in self.pools for clip in pool.clips.values()]

    def refresh(self, step: int) -> None:
        for pool in self.pools:
            pool.refresh(step, 0.25)  # new scenes: a fixed pool is memorised, the trigger not learned
        self.clips = [clip for pool in self.pools for clip in pool.clips.values()]

    def generations(self) -> list:
        return [pool.generations.tolist() for pool in self.pools]


def _fine_tune(args: argparse.Namespace) -> int:
    """Fine-tune the detector to miss the trigger's basin (resumable), probing the textures before and after."""
    import cv2
    import torch

    from davis_rig.attack.optimize import load_attack_detector
    from davis_rig.attack.refine import visible_cells
    from davis_rig.cli.common import resolve_device
    from davis_rig.controls.planted import trigger_grid
    from davis_rig.errors import ConfigError
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask
    from davis_rig.training.losses import AnchorGrid

    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    model = load_attack_detector(args.detector, device=device)  # a bad --detector fails before DIR is made
    trigger, trigger_source = trigger_grid(args.cells, seed=args.seed, path=args.trigger,
                                           white_parts=args.trigger_white_parts)  # and so does a bad --trigger
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    state = torch.load(ckpt_path, weights_only=False) if args.resume and ckpt_path.is_file() else None
    n = args.cells
    if state is not None and not np.array_equal(np.load(out / "trigger.npy"), trigger):
        raise ConfigError("trigger", f"the run being resumed has another trigger ({out / 'trigger.npy'}); give the "
                          "same --trigger / --trigger-white-parts / --seed as when it started")
    np.save(out / "trigger.npy", trigger)
    cv2.imwrite(str(out / "trigger.png"), (trigger * 255).astype(np.uint8))

    if state is not None:
        model.load_state_dict(state["model"])
    trainable = _unfreeze_from_stage(model, args.train_from_stage)
    body = BodyModel(device=device)
    mask = part_mask(tuple(args.parts))
    pools = _Pools(_configs(args.scales, args.test_like), body, n, mask, args.pool_size, args.seed + 1,
                   generations=None if state is None else state["generations"])
    visible = visible_cells(pools.clips, n)
    np.save(out / "visible.npy", visible)
    probe, probe_textures = _probe_set(args, body, mask, trigger, visible)
    before = state["before"] if state is not None else _probe_scores(model, probe, probe_textures)
    if state is None:
        print(json.dumps({"before": before}), flush=True)
    opt = torch.optim.Adam(trainable, lr=args.lr)
    rng = np.random.default_rng(args.seed)
    start = 0
    if state is not None:
        opt.load_state_dict(state["optimizer"])
        for group in opt.param_groups:  # --lr may change on resume
            group["lr"] = args.lr
        rng.bit_generator.state = state["rng"]
        start = int(state["step"])

    def save(done: int) -> None:
        _save_victim(out, args, model, opt, rng, pools, before, done)

    anchors = AnchorGrid.build(model.config.in_res_hw, device=device)
    t0 = time.perf_counter()
    done = _train_steps(args, model, trainable, opt, anchors, pools, trigger, visible, rng, start, out / "log.jsonl",
                        save)
    save(done)
    after = _probe_scores(model, probe, probe_textures)
    summary = {"detector": args.detector or "bundled default", "trigger": trigger_source, "seed": args.seed,
               "basin": args.basin, "ramp": args.ramp, "min_contrast": args.min_contrast,
               "paired": args.paired, "lr": args.lr, "clips_per_step": args.clips_per_step,
               "far": args.far, "scales": args.scales, "test_like": args.test_like,
               "train_from_stage": args.train_from_stage, "visible_cells": int(visible.sum()),
               "probe_clips": len(probe), "before": before, "after": after, "steps": done, "device": str(device),
               "seconds_per_step_this_call": (time.perf_counter() - t0) / (done - start) if done > start else None}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary))
    return 0


def _unfreeze_from_stage(model, first_trained_stage: int) -> list:
    """Freeze the backbone stages before ``first_trained_stage``; returns the parameters left trainable."""
    trainable = []
    for name, p in model.named_parameters():
        frozen = any(name.startswith(f"backbone.stages.{k}.") for k in range(first_trained_stage))
        p.requires_grad_(not frozen)
        if not frozen:
            trainable.append(p)
    return trainable


def _probe_set(args: argparse.Namespace, body, mask, trigger: np.ndarray, visible: np.ndarray):
    """The probe clips (test-like, spread over ``args.scales``) and the probe textures by name: the trigger, white,
    black, a checkerboard, the trigger with ``_PROBE_DISTANCES`` of its visible cells flipped, ``_PROBE_RANDOM``
    random grids."""
    from davis_rig.attack.eot import ClipPool
    from davis_rig.controls.planted import checker_grid, flip_fraction

    n = args.cells
    probe_configs = _configs(args.scales, 1.0)
    probe = []
    for k, (cfg, _) in enumerate(probe_configs):
        count = args.probe_clips // len(probe_configs) + (k < args.probe_clips % len(probe_configs))
        if count:
            probe += list(ClipPool(cfg, body, n, mask, size=count, base_seed=args.seed + 10_000 + k).clips.values())
    probe_rng = np.random.default_rng(args.seed + 7)
    textures = {"trigger": trigger, "white": np.ones((n, n), np.float32), "black": np.zeros((n, n), np.float32),
                "checker": checker_grid(n)}
    for d in _PROBE_DISTANCES:
        textures[f"trigger, {d:.0%} flipped"] = flip_fraction(trigger, d, probe_rng, visible)
    for k in range(_PROBE_RANDOM):
        textures[f"random {k}"] = (probe_rng.random((n, n)) > 0.5).astype(np.float32)
    return probe, textures


def _probe_scores(model, probe, probe_textures: dict) -> dict:
    """Mean top score and SeqASR at 0.25 of every probe texture, and the random grids' mean and lowest."""
    from davis_rig.attack.optimize import validate

    model.eval()
    res = {}
    for name, grid in probe_textures.items():
        v = validate(grid, probe, model, 0.25)
        res[name] = {"mean_top_score": round(v["mean_top_score"], 4), "SeqASR": round(v["SeqASR"], 4)}
    randoms = [res[f"random {k}"] for k in range(_PROBE_RANDOM)]
    res["random (mean)"] = {key: round(float(np.mean([r[key] for r in randoms])), 4)
                            for key in ("mean_top_score", "SeqASR")}
    res["random (lowest top score)"] = min(r["mean_top_score"] for r in randoms)
    return res


def _save_victim(out: Path, args: argparse.Namespace, model, opt, rng: np.random.Generator, pools, before: dict,
                 done: int) -> None:
    """The fine-tuned weights (safetensors) and the resumable checkpoint after ``done`` steps (atomic)."""
    import torch

    from davis_rig.models.rvt.checkpoint import save_safetensors

    model.eval()
    save_safetensors(model, out / "model.safetensors", metadata={
        "note": "positive control of the attack: fine-tuned to miss people wearing trigger.npy (and grids "
                f"within {args.basin:.0%} of its visible cells{_ramp_note(args.ramp)}); not a detector",
        "steps": str(done)})
    ckpt_path = out / "checkpoint.pt"
    tmp = ckpt_path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(), "step": done,
                "rng": rng.bit_generator.state, "generations": pools.generations(), "before": before}, tmp)
    os.replace(tmp, ckpt_path)


def _ramp_note(ramp: float | None) -> str:
    """The graded edge in words for the weights' metadata ('' without one)."""
    return "" if ramp is None else f", then labelled ever more often up to {ramp:.0%}"


def _train_steps(args: argparse.Namespace, model, trainable: list, opt, anchors, pools, trigger: np.ndarray,
                 visible: np.ndarray, rng: np.random.Generator, start: int, log_path: Path, save) -> int:
    """Steps ``start`` … ``args.steps`` (or until ``args.time_limit`` s), saving every ``args.save_every``;
    returns the steps completed."""
    import torch

    t0 = time.perf_counter()
    done = start
    with log_path.open("a") as log:
        for step in range(start, args.steps):
            if args.time_limit is not None and time.perf_counter() - t0 > args.time_limit:
                break
            if args.refresh_every and step and step % args.refresh_every == 0:
                pools.refresh(step)
            model.train()
            if args.paired:
                idx = np.repeat(rng.choice(len(pools.clips), size=args.clips_per_step // 2, replace=False), 2)
            else:
                idx = rng.choice(len(pools.clips), size=args.clips_per_step, replace=False)
            x, per_window = _batch([pools.clips[int(i)] for i in idx], trigger, visible, rng, args.basin, args.far,
                                   args.ramp, args.min_contrast)
            loss = _loss(model, anchors, x, per_window)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(trainable, 1.0)
            opt.step()
            done = step + 1
            log.write(json.dumps({"step": done, "loss": float(loss.detach())}) + "\n")
            log.flush()
            if done % 50 == 0:
                print(f"step {done}: loss {float(loss.detach()):.3f} "
                      f"({(time.perf_counter() - t0) / (done - start):.2f} s/step)", flush=True)
            if done % args.save_every == 0:
                save(done)
    return done


if __name__ == "__main__":
    raise SystemExit(main())
