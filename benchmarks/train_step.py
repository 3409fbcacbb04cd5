"""Benchmark: seconds per training step of the TBPTT trainer (RVT-T, batch 8, L = 5 by default) on this machine.

One step = augmentation of the batch on the device, L recurrent backbone steps for B chunks, FPN + YOLOX head on
every labelled window, SimOTA + YOLOX losses, backward through the L steps, gradient clipping, AdamW and the
one-cycle scheduler (``Trainer.train_step``). The data are a small dataset of random sparse histograms with
1–3 boxes per window written with ``DatasetWriter`` to a temporary folder; the batch is collated once (reading
is not timed: ``read_batch`` reports it separately). Also timed: ``forward_loss`` (the same forward + loss
without backward/optimizer, no_grad) so that the backward share is visible, and the ``mini`` model as a
reference (ratio). CPU only unless --device cuda is given (no GPU was available where this was written).

Run: ``python benchmarks/train_step.py [--model tiny] [--batch 8] [--seq-len 5] [--repeats 3] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import metadata_line

from davis_rig.events.histogram import WINDOW_US
from davis_rig.models.rvt.config import RVTConfig
from davis_rig.models.rvt.detector import pad_to_input
from davis_rig.training.augment import AugmentConfig
from davis_rig.training.batches import collate_chunks
from davis_rig.training.dataset import DatasetWriter
from davis_rig.training.losses import yolox_loss, yolox_targets
from davis_rig.training.trainer import TrainConfig, Trainer
from davis_rig.types import BBOX_DTYPE, PEDESTRIAN_CLASS_ID


def _write_dataset(root: Path, num_sequences: int, num_windows: int) -> None:
    rng = np.random.default_rng(0)
    with DatasetWriter(root, name="bench", compression="lzf") as writer:
        for s in range(num_sequences):
            hist = np.zeros((num_windows, 20, 240, 304), np.uint8)
            mask = rng.random(hist.shape) < 0.01
            hist[mask] = rng.integers(1, 11, size=int(mask.sum()), dtype=np.uint8)
            ends = (np.arange(num_windows, dtype=np.int64) + 1) * WINDOW_US
            labels = []
            for end in ends.tolist():
                k = int(rng.integers(1, 4))
                boxes = np.zeros(k, BBOX_DTYPE)
                boxes["t"] = end
                boxes["x"], boxes["y"] = rng.uniform(0, 220, k), rng.uniform(0, 120, k)
                boxes["w"], boxes["h"] = rng.uniform(20, 80, k), rng.uniform(40, 110, k)
                boxes["class_id"] = PEDESTRIAN_CLASS_ID
                labels.append(boxes)
            writer.add_sequence(hist, ends, labels, {"seed": s}, split="train")


def _time_s(fn, warmup: int, repeats: int) -> tuple[float, float, list[float]]:
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    q = np.percentile(samples, [25, 75])
    return statistics.median(samples), float(q[1] - q[0]), samples


def _bench_model(data: Path, run: Path, model: str, args) -> dict[str, float]:
    config = TrainConfig(model=model, steps=10_000, batch_size=args.batch, seq_len=args.seq_len, val_every=0,
                         ckpt_every=0, log_every=0, device=args.device, precision=args.precision, sampling="random",
                         augment=AugmentConfig())
    trainer = Trainer(data, run / model, config)
    start = time.perf_counter()
    batch = collate_chunks([trainer.train_set[i] for i in range(args.batch)])
    read_s = time.perf_counter() - start

    def step():
        trainer.train_step(batch)
        if trainer.device.type == "cuda":
            torch.cuda.synchronize()

    @torch.no_grad()
    def forward_loss():
        hist, labels = trainer._augment(batch)
        states, feats, targets = None, {2: [], 3: [], 4: []}, []
        for t in range(hist.shape[0]):
            features, states = trainer.model.forward_backbone(pad_to_input(hist[t]), states)
            for level in feats:
                feats[level].append(features[level])
            targets.extend(yolox_targets(lab) for lab in labels[t])
        raw = trainer.model.forward_raw_head({k: torch.cat(v) for k, v in feats.items()})
        yolox_loss(raw, targets, trainer.anchors)
        if trainer.device.type == "cuda":
            torch.cuda.synchronize()

    step_med, step_iqr, _ = _time_s(step, args.warmup, args.repeats)
    fwd_med, fwd_iqr, _ = _time_s(forward_loss, 1, args.repeats)
    return {"step_s": step_med, "step_iqr_s": step_iqr, "forward_loss_s": fwd_med, "forward_loss_iqr_s": fwd_iqr,
            "read_batch_s": read_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="tiny", choices=sorted(RVTConfig.presets()))
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--seq-len", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--precision", default="auto")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(metadata_line(device=args.device))
    print(f"batch {args.batch}, L {args.seq_len}, every window labelled, augmentation on, repeats {args.repeats} "
          f"(median, IQR)")
    with tempfile.TemporaryDirectory() as tmp:
        data, run = Path(tmp) / "data", Path(tmp) / "runs"
        _write_dataset(data, num_sequences=max(2, args.batch // 2), num_windows=args.seq_len + 3)
        results = {}
        for model in dict.fromkeys([args.model, "mini"]):
            r = _bench_model(data, run, model, args)
            results[model] = r
            print(f"{model:>5}: train step {r['step_s']:.3f} s (IQR {r['step_iqr_s']:.3f}) | forward+loss no_grad "
                  f"{r['forward_loss_s']:.3f} s (IQR {r['forward_loss_iqr_s']:.3f}) | backward+optimizer share "
                  f"{1 - r['forward_loss_s'] / r['step_s']:.0%} | read+collate batch {r['read_batch_s']:.3f} s")
        if args.model != "mini":
            ratio = results[args.model]["step_s"] / results["mini"]["step_s"]
            print(f"ratio {args.model} / mini train step: {ratio:.1f}x")
            steps_per_hour = 3600 / results[args.model]["step_s"]
            print(f"{args.model}: {steps_per_hour:.0f} steps per hour here; RVT's 400k-step recipe would take "
                  f"{400_000 / steps_per_hour / 24:.0f} days at this rate")


if __name__ == "__main__":
    main()
