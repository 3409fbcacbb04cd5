"""Benchmark: differentiable V2E per 50 ms window at 304x240, forward and forward + backward, vs RVT-B.

Cases (median, IQR and min over repeated runs after warm-up; batch 1; fp32; CPU at 1 and 2 intra-op threads, and
CUDA when available):

* ``v2e[<mode>] fwd`` / ``fwd+bwd``: :func:`davis_rig.events.v2e_torch.v2e_histograms` on an 11-frame video
  (200 fps: the window's 10 frame pairs) with ``requires_grad``; backward of a random-weighted sum of the
  histogram into the video. Modes: ``dvs`` (default, exact), ``floor`` (paper's formula), ``official_relaxed``.
* ``exact simulator + histogram``: :func:`davis_rig.events.simulator.simulate_events` (float32) +
  :func:`davis_rig.events.histogram.stacked_histogram` for the same window (the test-time path), forward only.
* ``RVT-B fwd+bwd``: :class:`davis_rig.models.rvt.RVTDetector` (``RVTConfig.base()``, random weights, eval mode)
  on the padded histogram, backward of the sum of the decoded head output into the input (what an attack step
  costs in the detector).

Ratios printed: V2E fwd+bwd / RVT-B fwd+bwd per count mode. The attack runs none of these cases alone (its
default is the exact "dvs" counts without grad plus the relaxed surrogate's forward and backward, from one log
video): ``benchmarks/digital_cost.py`` times that, with the rendering, against the goal (rendering + V2E ≤ 10 %
of the detector's cost).

Run: ``python benchmarks/v2e.py [--repeats N] [--threads 1 2] [--no-cuda]``.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch
from _common import cuda_sync, metadata_line, random_detector, set_torch_threads, time_ms

from davis_rig.events.histogram import stacked_histogram
from davis_rig.events.simulator import simulate_events
from davis_rig.events.v2e_torch import v2e_histograms
from davis_rig.types import RVT_HW

HEIGHT, WIDTH = RVT_HW
FRAMES = 11  # 200 fps: 10 frame pairs per 50 ms window
PERIOD_US = 5000


def synthetic_video(seed: int = 0) -> np.ndarray:
    """A person-sized textured region walking 3 px per frame over a textured background, float32 [11, 240, 304]."""
    rng = np.random.default_rng(seed)
    texture = rng.uniform(0.05, 0.95, (HEIGHT // 8 + 1, (WIDTH + 64) // 8 + 1)).repeat(8, 0).repeat(8, 1)
    background = 0.2 + 0.3 * rng.uniform(size=(HEIGHT, WIDTH))
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
    frames = []
    for k in range(FRAMES):
        x0 = 100 + 3 * k
        inside = (xx >= x0) & (xx < x0 + 60) & (yy >= 40) & (yy < 220)
        shade = 0.9 + 0.1 * math.sin(0.3 * k)
        person = texture[:HEIGHT, 3 * k:3 * k + WIDTH] * shade
        frames.append(np.where(inside, person, background))
    return np.stack(frames).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--no-cuda", action="store_true")
    args = parser.parse_args()

    from davis_rig.models.rvt.detector import pad_to_input

    print("# V2E benchmark: differentiable V2E per 50 ms window (304x240, 11 frames at 200 fps, fp32) vs RVT-B")
    print(metadata_line())
    print(f"# repeats {args.repeats} after {args.warmup} warm-up; median / IQR / min in ms")
    video_np = synthetic_video()
    t_us = np.arange(FRAMES, dtype=np.int64) * PERIOD_US
    end_us = int(t_us[-1])
    devices = [("cpu", n) for n in args.threads]
    if torch.cuda.is_available() and not args.no_cuda:
        devices.append(("cuda", None))
    weights = torch.rand(1, 20, HEIGHT, WIDTH)
    for device, threads in devices:
        if threads is not None:
            set_torch_threads(threads)
        sync = cuda_sync(device)
        label = f"{device}" + (f", {threads} thread(s)" if threads else f" ({torch.cuda.get_device_name()})")
        print(f"\n## {label}")
        video = torch.tensor(video_np, device=device)
        w = weights.to(device)
        results = {}
        for mode in ("dvs", "floor", "official_relaxed"):
            def fwd(mode=mode):
                with torch.no_grad():
                    return v2e_histograms(video, t_us, end_us, mode=mode)

            def fwd_bwd(mode=mode):
                v = video.clone().requires_grad_(True)
                hist = v2e_histograms(v, t_us, end_us, mode=mode)
                (hist * w).sum().backward()
                return v.grad

            for name, fn in ((f"v2e[{mode}] fwd", fwd), (f"v2e[{mode}] fwd+bwd", fwd_bwd)):
                results[name] = time_ms(fn, args.warmup, args.repeats, sync)
        events = simulate_events(video_np, t_us, dtype="float32")
        print(f"# events in the window (exact simulator): {len(events)}; "
              f"nonzero V2E cells: {int((v2e_histograms(video, t_us, end_us) > 0).sum())}")
        if device == "cpu":
            def exact():
                ev = simulate_events(video_np, t_us, dtype="float32")
                return stacked_histogram(ev["x"], ev["y"], ev["t"], ev["p"], height=HEIGHT, width=WIDTH)

            results["exact simulator + histogram"] = time_ms(exact, 1, max(3, args.repeats // 3), sync)
        model = random_detector("base", device)
        x0 = pad_to_input(torch.rand(1, 20, HEIGHT, WIDTH, device=device) * 3)

        def rvt_fwd_bwd():
            x = x0.clone().requires_grad_(True)
            decoded, _ = model(x)
            decoded.sum().backward()
            return x.grad

        def rvt_fwd():
            with torch.no_grad():
                return model(x0)

        rvt_repeats = max(3, args.repeats // 3)
        results["RVT-B fwd"] = time_ms(rvt_fwd, 1, rvt_repeats, sync)
        results["RVT-B fwd+bwd"] = time_ms(rvt_fwd_bwd, 1, rvt_repeats, sync)
        for name, (median, iqr, low) in results.items():
            print(f"{name:32s} {median:9.2f} {iqr:8.2f} {low:9.2f}")
        rvt = results["RVT-B fwd+bwd"][0]
        for mode in ("dvs", "floor", "official_relaxed"):
            ratio = results[f"v2e[{mode}] fwd+bwd"][0] / rvt
            print(f"ratio v2e[{mode}] fwd+bwd / RVT-B fwd+bwd: {ratio:.4f} ({100 * ratio:.2f} %)")


if __name__ == "__main__":
    main()
