"""Benchmark: rendering the walking body (ms per frame) at 346x260 and 304x240, supersampling 1/2/3.

Cases, per frame, median (and IQR) over repeated runs after warm-up, for a batch of ``--frames`` frames
(default 10 = one 50 ms RVT window at 200 fps) of the walk cycle at the middle test scale:

* ``raster``: :func:`rasterize_mesh` = projection + rasterization (z-buffer) + per-sample UVs and Lambert
  shades; done once per clip (no autograd);
* ``step``: texture lookup of a 10x10 grid through the 1024^2 part mask + compositing + backward to the grid,
  i.e. what one optimiser step costs per frame once the clip is rasterized (lookup prepared once);
* ``lookup``: :meth:`RasterizedMesh.lookup` (texel taps with the mask), once per clip;
* ``pose``: :meth:`BodyModel.walk_vertices` (FK + LBS), for reference.

Also printed: candidate (face, sample) pairs per covered sample (the rasterizer's overhead factor) and the
ratios 2 threads / 1 thread and s = 2, 3 vs s = 1. CPU with 1 and 2 threads; ``--device cuda`` adds a GPU.
Run: ``python benchmarks/render.py [--repeats N] [--frames 10] [--threads 1 2] [--device cpu]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path

import numpy as np


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).resolve().parent, capture_output=True, text=True, check=True
        )
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _time_ms(fn, warmup: int, repeats: int, sync=lambda: None) -> tuple[float, float, float]:
    for _ in range(warmup):
        fn()
    sync()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        samples.append((time.perf_counter() - start) * 1e3)
    q = statistics.quantiles(samples, n=4) if len(samples) >= 2 else [samples[0]] * 3
    return statistics.median(samples), q[2] - q[0], min(samples)


def _pairs_per_sample(projected, faces, hw, s) -> float:
    """Candidate (face, sample) pairs of the bounding boxes per covered sample (front faces only)."""
    import torch

    from davis_rig.scene.rasterize import rasterize

    tri = (projected * torch.tensor([s, s, 1.0], dtype=projected.dtype))[:, faces]
    x, y = tri[..., 0], tri[..., 1]
    area = (x[..., 1] - x[..., 0]) * (y[..., 2] - y[..., 0]) - (x[..., 2] - x[..., 0]) * (y[..., 1] - y[..., 0])
    bw = (torch.floor(x.max(-1).values - 0.5) - torch.ceil(x.min(-1).values - 0.5) + 1).clamp(min=0)
    bh = (torch.floor(y.max(-1).values - 0.5) - torch.ceil(y.min(-1).values - 0.5) + 1).clamp(min=0)
    pairs = float((bw * bh)[area < 0].sum())
    covered = float(rasterize(projected, faces, hw, supersample=s).covered.sum())
    return pairs / max(covered, 1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--supersample", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    import torch

    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.camera import PinholeCamera, distance_for_height, look_at
    from davis_rig.scene.masks import part_mask
    from davis_rig.scene.renderer import rasterize_mesh

    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    load = os.getloadavg() if hasattr(os, "getloadavg") else ("n/a",)
    print(
        f"commit {_commit()} | python {platform.python_version()} | torch {torch.__version__} | numpy {np.__version__}"
        f" | device {device}" + (f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else f" ({platform.machine()}, {os.cpu_count()} cores)")
        + f" | load average {tuple(round(v, 2) for v in load)} | frames/batch {args.frames}"
    )
    model = BodyModel(device=device)
    times = np.arange(args.frames) / 200.0
    mask = part_mask(("torso", "arms", "legs"))
    grid = torch.rand(10, 10, device=device)
    thread_list = args.threads if device.type == "cpu" else [torch.get_num_threads()]
    results = {}
    for threads in thread_list:
        torch.set_num_threads(threads)
        med, iqr, low = _time_ms(lambda: model.walk_vertices(0, times), args.warmup, args.repeats, sync)
        print(f"[threads {threads}] pose (FK+LBS)            {med / args.frames:8.2f} ms/frame (IQR {iqr / args.frames:.2f}, min {low / args.frames:.2f})")
        vertices = model.walk_vertices(0, times)
        c, s_ = np.cos(np.pi / 2), np.sin(np.pi / 2)
        vertices = vertices @ torch.tensor([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]], dtype=vertices.dtype, device=device).T
        for name, camera in (("346x260", PinholeCamera.davis346()), ("304x240", PinholeCamera.rvt_crop())):
            d = distance_for_height("middle", camera)
            rotation, translation = look_at([0.0, -d, 0.875], [0.0, 0.0, 0.875])
            r = torch.as_tensor(rotation, dtype=torch.float32, device=device)
            t = torch.as_tensor(translation, dtype=torch.float32, device=device)
            for s in args.supersample:
                raster_fn = lambda: rasterize_mesh(vertices, model.faces, model.face_uvs, camera, r, t, supersample=s)  # noqa: E731
                med, iqr, low = _time_ms(raster_fn, args.warmup, args.repeats, sync)
                raster = raster_fn()
                results[(threads, name, s, "raster")] = med / args.frames
                lk_med, _, _ = _time_ms(lambda: raster.lookup(1024, "nearest", grid_n=10, mask=mask), 1, args.repeats, sync)
                lookup = raster.lookup(1024, "nearest", grid_n=10, mask=mask)
                background = torch.full(camera.hw, 0.5, device=device)

                def step():
                    g = grid.clone().requires_grad_()
                    raster.compose(lookup.sample(g), background).sum().backward()

                st_med, st_iqr, st_low = _time_ms(step, args.warmup, args.repeats, sync)
                results[(threads, name, s, "step")] = st_med / args.frames
                pairs = _pairs_per_sample(camera.project(vertices[:1], r, t), model.faces, camera.hw, s) if threads == thread_list[0] else float("nan")
                print(
                    f"[threads {threads}] {name} s={s}  raster {med / args.frames:7.2f} ms/frame (IQR {iqr / args.frames:.2f}, min {low / args.frames:.2f})"
                    f" | lookup {lk_med / args.frames:6.2f} | step (lookup+compose+backward) {st_med / args.frames:6.2f} ms/frame (min {st_low / args.frames:.2f})"
                    f" | samples/frame {raster.face.numel() // args.frames}"
                    + (f" | bbox pairs per covered sample {pairs:.2f}" if np.isfinite(pairs) else "")
                )
    print("ratios:")
    for name in ("346x260", "304x240"):
        for s in args.supersample:
            if len(thread_list) > 1 and (thread_list[-1], name, s, "raster") in results:
                a, b = results[(thread_list[0], name, s, "raster")], results[(thread_list[-1], name, s, "raster")]
                print(f"  {name} s={s}: raster {thread_list[-1]} threads / {thread_list[0]} thread = {b / a:.2f}")
            base = results.get((thread_list[-1], name, 1, "raster"))
            if s != 1 and base:
                print(f"  {name} s={s}: raster vs s=1 = {results[(thread_list[-1], name, s, 'raster')] / base:.2f}")
        s = args.supersample[-1]
        ratio = results[(thread_list[-1], name, s, "step")] / results[(thread_list[-1], name, s, "raster")]
        print(f"  {name} s={s}: optimiser step / rasterization = {ratio:.2f}")


if __name__ == "__main__":
    main()
