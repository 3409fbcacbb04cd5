"""Render a person walking and turn it into a synthetic DAVIS346 recording (the out-of-the-box ``recordings/sample.h5``).

The scene: the bundled body asset walking across the RVT crop of the DAVIS346 (middle test scale) in front of a
procedural background, wearing a random black/white grid texture; 200 fps rendering → exact DVS events
(θ = 0.2, interpolated timestamps, mild v2e-style noise unless ``--ideal``) + 25 fps APS frames + the visible-person
ground-truth boxes as ``/labels/boxes`` (RVT crop coordinates). ``--usb`` sends everything through the DAVIS346
word-stream encoder and the virtual USB camera (the real capture path) instead of writing the file directly.

Run: ``python tools/make_sample_session.py [--out recordings/sample.h5] [--duration 0.6] [--usb] [--ideal]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    from davis_rig.cli.common import float_in, new_parser, non_negative_int, positive_float, positive_int, run_main

    parser = new_parser(Path(__file__).name, __doc__.split("\n")[0],
                        "examples:\n  python tools/make_sample_session.py --out recordings/sample.h5 --overwrite\n")
    parser.add_argument("--out", type=Path, default=Path("recordings/sample.h5"), help="the session file to write")
    parser.add_argument("--duration", type=positive_float, default=0.6, help="clip length, s")
    parser.add_argument("--rate", type=float_in(200.0), default=200.0, help="render rate, Hz (>= 200)")
    parser.add_argument("--grid", type=positive_int, default=20, help="n of the n x n black/white texture grid")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--usb", action="store_true", help="go through the encoder + virtual USB camera")
    parser.add_argument("--ideal", action="store_true", help="noise-free events (no mismatch/shot noise/leak)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    return run_main(parser, argv, _make)


def _make(args: argparse.Namespace) -> int:

    import torch

    from davis_rig.events.simulator import SimulatorConfig
    from davis_rig.scene.scene import SceneSpec, render_clip
    from davis_rig.training.recording import write_clip_session

    rng = np.random.default_rng(args.seed)
    texture = torch.tensor((rng.uniform(size=(args.grid, args.grid)) > 0.5).astype(np.float32))
    # the bundled walk cycle: recordings/sample.h5 was made with it (the scenes' default walk is now the natural one)
    spec = SceneSpec(duration_s=args.duration, render_rate_hz=args.rate, background="random", light="random",
                     offset_m=(-0.6, 0.0), seed=args.seed, t0_us=10_000, walk="bundled")
    start = time.perf_counter()
    clip = render_clip(spec, texture)
    render_s = time.perf_counter() - start
    simulator = SimulatorConfig() if args.ideal else SimulatorConfig(
        threshold_sigma=0.02, shot_noise_rate_hz=0.1, leak_rate_hz=0.05, refractory_us=100, seed=args.seed)
    start = time.perf_counter()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    summary = write_clip_session(args.out, clip, simulator=simulator, through_usb=args.usb,
                                 overwrite=args.overwrite)
    write_s = time.perf_counter() - start
    print(f"{summary.path}: {summary.events} events, {summary.frames} APS frames, {summary.labels} labels, "
          f"{clip.video.shape[0]} rendered frames ({render_s:.1f} s render, {write_s:.1f} s events + APS + write"
          f"{' through the virtual USB camera' if args.usb else ''}), {summary.path.stat().st_size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
