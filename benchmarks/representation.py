"""Benchmark: RVT stacked-histogram time per 50 ms window at 1 and 12 Mev/s (CPU).

Cases, each the median (and IQR) over repeated runs after warm-up, on synthetic uniform events over the
304x240 frame (sorted timestamps, random polarity):

* ``numpy``: :func:`davis_rig.events.stacked_histogram` (bincount, bit-exact with the official output);
* ``official_torch``: the official RVT ``StackedHistogram.construct`` code path (uint8 ``put_`` with
  accumulate), transcribed, as the baseline; ratio = official / numpy;
* ``torch_float``: :func:`davis_rig.events.histogram_torch.stacked_histogram_torch` with per-event weights
  (the differentiable version), forward only, and forward + backward w.r.t. the weights;
* ``windows_1s``: :func:`stacked_histograms` for 20 windows of 50 ms over 1 s (window search included),
  reported per window.

Run: ``python benchmarks/representation.py [--repeats N] [--rates-mev 1 12] [--threads 1]``.
"""

from __future__ import annotations

import argparse

import numpy as np
from _common import metadata_line, time_ms

from davis_rig.events import WINDOW_US, stacked_histogram, stacked_histograms

HEIGHT, WIDTH = 240, 304


def synthetic_events(rate_mev_s: float, duration_us: int, seed: int = 0):
    """Uniform events over the RVT frame: (x, y, t_us, p) columns, sorted by time."""
    rng = np.random.default_rng(seed)
    n = int(rate_mev_s * 1e6 * duration_us / 1e6)
    t_us = np.sort(rng.integers(0, duration_us + 1, n)).astype(np.int64)
    x = rng.integers(0, WIDTH, n).astype(np.uint16)
    y = rng.integers(0, HEIGHT, n).astype(np.uint16)
    p = rng.integers(0, 2, n).astype(np.uint8)
    return x, y, t_us, p


def _official_torch(torch, x, y, time_us, pol):
    """The official fastmode construct() (uint8 put_ with accumulate, clamp), on torch tensors."""
    representation = torch.zeros((2, 10, HEIGHT, WIDTH), dtype=torch.uint8)
    t0_int, t1_int = time_us[0], time_us[-1]
    t_norm = (time_us - t0_int) / max((t1_int - t0_int), 1)
    t_idx = torch.clamp((t_norm * 10).floor(), max=9)
    indices = x.long() + WIDTH * y.long() + HEIGHT * WIDTH * t_idx.long() + 10 * HEIGHT * WIDTH * pol.long()
    representation.put_(indices, torch.ones_like(indices, dtype=torch.uint8), accumulate=True)
    return torch.clamp(representation, min=0, max=10).reshape(20, HEIGHT, WIDTH)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--rates-mev", nargs="+", type=float, default=[1.0, 12.0])
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (numpy is single-threaded)")
    args = parser.parse_args()

    try:
        import torch

        torch.set_num_threads(args.threads)
    except ImportError:
        torch = None

    print("# RVT stacked-histogram benchmark (50 ms windows, 20x240x304 output, uniform synthetic events)")
    print(metadata_line(("numpy", "torch"), repeats=f"{args.repeats} (+{args.warmup} warm-up)"))
    for rate in args.rates_mev:
        x, y, t_us, p = synthetic_events(rate, WINDOW_US, seed=int(rate * 10))
        n = t_us.shape[0]
        results: dict[str, float] = {}

        median, iqr, min_ms = time_ms(lambda: stacked_histogram(x, y, t_us, p), args.warmup, args.repeats)
        results["numpy"] = median
        print(f"{rate:5.1f} Mev/s ({n:7d} ev/window)  numpy          median {median:8.2f} ms  IQR {iqr:6.2f} ms  min {min_ms:8.2f} ms")

        if torch is not None:
            from davis_rig.events.histogram_torch import stacked_histogram_torch

            tx, ty, tt, tp = (torch.from_numpy(a.astype(np.int64)) for a in (x, y, t_us, p))
            reference = _official_torch(torch, tx, ty, tt, tp).numpy()
            assert np.array_equal(reference, stacked_histogram(x, y, t_us, p)), "numpy != official torch"
            median, iqr, min_ms = time_ms(lambda: _official_torch(torch, tx, ty, tt, tp), args.warmup, args.repeats)
            results["official_torch"] = median
            print(f"{'':30s} official_torch median {median:8.2f} ms  IQR {iqr:6.2f} ms  min {min_ms:8.2f} ms")

            weights = torch.rand(n)
            median, iqr, min_ms = time_ms(lambda: stacked_histogram_torch(tx, ty, tt, tp, weights), args.warmup, args.repeats)
            results["torch_float"] = median
            print(f"{'':30s} torch_float    median {median:8.2f} ms  IQR {iqr:6.2f} ms  min {min_ms:8.2f} ms")

            def forward_backward():
                w = weights.clone().requires_grad_(True)
                hist = stacked_histogram_torch(tx, ty, tt, tp, w)
                (hist * hist).sum().backward()

            median, iqr, min_ms = time_ms(forward_backward, args.warmup, args.repeats)
            results["torch_float_fwd_bwd"] = median
            print(f"{'':30s} torch_fwd_bwd  median {median:8.2f} ms  IQR {iqr:6.2f} ms  min {min_ms:8.2f} ms")

        xs, ys, ts, ps = synthetic_events(rate, 1_000_000, seed=int(rate * 10) + 1)
        ends = np.arange(WINDOW_US, 1_000_001, WINDOW_US)
        median, iqr, min_ms = time_ms(lambda: stacked_histograms((xs, ys, ts, ps), ends), 1, max(3, args.repeats // 4))
        results["windows_1s_per_window"] = median / len(ends)
        print(
            f"{'':30s} windows_1s     median {median / len(ends):8.2f} ms/window  "
            f"(20 windows, {median:.1f} ms total, IQR {iqr:.1f} ms)"
        )
        realtime = results["numpy"] / (WINDOW_US / 1e3)
        print(f"{'':30s} ratios: numpy uses {realtime:.3f} of real time (50 ms window)", end="")
        if "official_torch" in results:
            print(f"; official_torch/numpy {results['official_torch'] / results['numpy']:.2f}", end="")
            print(f"; torch_float/numpy {results['torch_float'] / results['numpy']:.2f}", end="")
        print()


if __name__ == "__main__":
    main()
