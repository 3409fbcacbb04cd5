"""Benchmark: the attack's validation per clip: preparation, memory and scoring as trained / as tested.

What :func:`davis_rig.attack.optimize.optimize_texture` does at each validation: ``--clips`` clips of the default EoT
(natural walk, half of them with the test sensor) are prepared once (pose + rasterize, no grad), then a hard 10 x 10
texture is scored on them by :func:`davis_rig.attack.optimize.validate`: as trained (each clip's own sensor, the
step's forward), as tested (the exact simulator on the person's box, ideal sensor), and both (the default). The
detector (the bundled RVT-T, or ``--detector``) runs on batches of 8 clips. The scorings run in the order given by
``--order`` and repeat ``--repeats`` times (their minimum is reported): CPU timings on a shared machine are noisy.

Run: ``python benchmarks/attack_validation.py [--threads 2] [--clips 16] [--repeats 2] [--detector CKPT]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
import torch
from _common import metadata_line, set_torch_threads

from davis_rig.attack.eot import EoTConfig, draw_scene, prepare_clip, slot_seed
from davis_rig.attack.optimize import _VAL_SEED_OFFSET, load_attack_detector, validate
from davis_rig.scene.body import BodyModel
from davis_rig.scene.masks import part_mask

TRAIN_PATH = ("dvs", "interval")
SCORINGS = {"both": {"train_path": TRAIN_PATH}, "test": {}, "train": {"train_path": TRAIN_PATH, "test_path": False}}


def clip_megabytes(clip) -> float:
    """Tensor memory a pool clip keeps (MB)."""
    total = 0
    for obj in (clip, clip.raster, clip.lookup):
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if isinstance(value, torch.Tensor):
                total += value.numel() * value.element_size()
    return total / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--clips", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--order", nargs="+", choices=sorted(SCORINGS), default=["both", "test", "train"])
    parser.add_argument("--detector", default=None, metavar="CKPT", help="default: the bundled detector")
    args = parser.parse_args()
    set_torch_threads(args.threads)
    print(metadata_line())
    detector = load_attack_detector(args.detector)
    body, mask, eot = BodyModel(), part_mask(("torso", "arms", "legs")), EoTConfig()
    start = time.perf_counter()
    clips = []
    for i in range(args.clips):
        seed = slot_seed(_VAL_SEED_OFFSET, i, 0)
        spec, sensor = draw_scene(eot, seed, body.num_shapes)
        clips.append(prepare_clip(spec, sensor, body, 10, mask, config=eot, seed=seed))
    prepare_s = (time.perf_counter() - start) / args.clips
    print(f"{args.clips} clips: prepare {prepare_s:.2f} s/clip, memory {np.mean([clip_megabytes(c) for c in clips]):.1f} "
          f"MB/clip (first preparation includes the natural walk's generation per shape)")
    grid = (np.random.default_rng(0).random((10, 10)) > 0.5).astype(np.float32)
    validate(grid, clips[:1], detector, 0.25, train_path=TRAIN_PATH)  # warm-up
    for name in args.order:
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            result = validate(grid, clips, detector, 0.25, **SCORINGS[name])
            times.append((time.perf_counter() - t0) / args.clips)
        print(f"  scored {name:5s}: min {min(times):.3f} s/clip over {args.repeats} repeats; "
              + ", ".join(f"{k} {v:.4f}" for k, v in result.items() if isinstance(v, float)))


if __name__ == "__main__":
    main()
