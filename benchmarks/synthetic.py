"""Benchmark: seconds of wall time per generated second of synthetic data (CPU), by pipeline stage.

Renders a fixed set of scenes from :func:`davis_rig.training.synthetic.sample_scene` (train split, default
config: 0-3 people, distractors, ego-motion, noise) and of held-out test scenes, each ``--seconds`` long, with
:func:`~davis_rig.training.synthetic.render_sequence`, after one warm-up scene (model load, gait and label-map
caches). Stages (``SyntheticSequence.timings_s``): pose (motion generation + FK/LBS), rasterize (z-buffered
multi-person raster), compose (textures, background warp, distractors), simulate (exact DVS simulator),
histogram (RVT stacked histograms), label (visible-coverage boxes). Reported: the median over scenes of each
stage's seconds per generated second, the total, and the ratio 1-person test scene / mixed train scene; plus
metadata (commit, versions, threads). Writing to disk is not timed (``davis-make-dataset`` adds ~0.1 s/seq).

Run: ``python benchmarks/synthetic.py [--scenes 4] [--seconds 1] [--threads 1] [--device cpu]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch
from _common import metadata_line

from davis_rig.scene.body import BodyModel
from davis_rig.training import synthetic as syn

STAGES = ("pose", "rasterize", "compose", "simulate", "histogram", "label")


def _run(scenes, model) -> dict[str, list[float]]:
    per_second: dict[str, list[float]] = {k: [] for k in (*STAGES, "total")}
    for scene in scenes:
        start = time.perf_counter()
        seq = syn.render_sequence(scene, model=model)
        total = time.perf_counter() - start
        for k in STAGES:
            per_second[k].append(seq.timings_s[k] / scene.duration_s)
        per_second["total"].append(total / scene.duration_s)
    return per_second


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=4, help="scenes per kind (default 4)")
    parser.add_argument("--seconds", type=float, default=1.0, help="seconds per scene (default 1)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = syn.SyntheticSceneConfig(duration_s=args.seconds)
    model = BodyModel(device=args.device)
    rng = np.random.default_rng(0)
    syn.render_sequence(syn.sample_scene(rng, "train", syn.SyntheticSceneConfig(duration_s=0.1)), model=model)
    train = [syn.sample_scene(rng, "train", config) for _ in range(args.scenes)]
    test = [syn.held_out_scene(rng, *syn.TEST_SUBSETS[i % 9], config) for i in range(args.scenes)]
    print(metadata_line(device=args.device))
    print(f"{args.scenes} scenes per kind x {args.seconds:g} s; train people per scene: "
          f"{[len(s.people) for s in train]}; median seconds per generated second")
    results = {}
    for name, scenes in (("train (mixed)", train), ("test (1 person)", test)):
        per_second = _run(scenes, model)
        results[name] = {k: statistics.median(v) for k, v in per_second.items()}
        row = "  ".join(f"{k} {results[name][k]:.2f}" for k in (*STAGES, "total"))
        print(f"{name:16s} {row}")
    ratio = results["test (1 person)"]["total"] / results["train (mixed)"]["total"]
    print(f"ratio test/train total: {ratio:.2f}")


if __name__ == "__main__":
    main()
