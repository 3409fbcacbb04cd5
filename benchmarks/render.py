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

``--warp`` compares the torch rasterizer (:func:`rasterize_sparse`) with the same algorithm as NVIDIA warp
kernels (one thread per triangle looping over its bounding box, ``atomic_min`` depth pass + face-id pass; face
ids only, no barycentrics), when ``warp-lang`` is installed (it is not a dependency of davis_rig).
Run: ``python benchmarks/render.py [--repeats N] [--frames 10] [--threads 1 2] [--device cpu] [--warp]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import cuda_sync, metadata_line, set_torch_threads, time_ms

try:  # optional: only for the --warp comparison
    import warp as wp
except ImportError:  # pragma: no cover - depends on the environment
    wp = None


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


if wp is not None:
    wp.config.quiet = True

    # One thread per (frame, face). Pass 0 (write_ids=0) keeps the nearest depth per sample in zbuf (atomic_min);
    # pass 1 writes the id of the face at that depth into fbuf.
    @wp.kernel
    def raster_pass(
        tri: wp.array2d(dtype=wp.float32),
        hs: int,
        ws: int,
        n_faces: int,
        near: float,
        write_ids: int,
        zbuf: wp.array(dtype=wp.float32),
        fbuf: wp.array(dtype=wp.int32),
    ):
        fid = wp.tid()
        x0 = tri[fid, 0]
        x1 = tri[fid, 1]
        x2 = tri[fid, 2]
        y0 = tri[fid, 3]
        y1 = tri[fid, 4]
        y2 = tri[fid, 5]
        z0 = tri[fid, 6]
        z1 = tri[fid, 7]
        z2 = tri[fid, 8]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area >= 0.0 or z0 <= near or z1 <= near or z2 <= near:
            return
        xa = wp.max(int(wp.ceil(wp.min(wp.min(x0, x1), x2) - 0.5)), 0)
        xb = wp.min(int(wp.floor(wp.max(wp.max(x0, x1), x2) - 0.5)), ws - 1)
        ya = wp.max(int(wp.ceil(wp.min(wp.min(y0, y1), y2) - 0.5)), 0)
        yb = wp.min(int(wp.floor(wp.max(wp.max(y0, y1), y2) - 0.5)), hs - 1)
        frame = fid / n_faces
        inv_area = 1.0 / area
        for py in range(ya, yb + 1):
            for px in range(xa, xb + 1):
                cx = float(px) + 0.5
                cy = float(py) + 0.5
                b0 = ((x1 - cx) * (y2 - cy) - (x2 - cx) * (y1 - cy)) * inv_area
                b1 = ((x2 - cx) * (y0 - cy) - (x0 - cx) * (y2 - cy)) * inv_area
                b2 = 1.0 - b0 - b1
                if b0 >= 0.0 and b1 >= 0.0 and b2 >= 0.0:
                    depth = 1.0 / (b0 / z0 + b1 / z1 + b2 / z2)
                    k = frame * hs * ws + py * ws + px
                    if write_ids == 0:
                        wp.atomic_min(zbuf, k, depth)
                    elif depth == zbuf[k]:
                        fbuf[k] = fid - frame * n_faces


def warp_raster(projected, faces, hw, s):
    """Face id per sample from the warp kernels, int32 tensor [T, H*s, W*s] (-1 = none)."""
    import torch

    t = projected.shape[0]
    p = projected * torch.tensor([s, s, 1.0], dtype=projected.dtype, device=projected.device)
    tri = p[:, faces.long()]  # [T, F, 3, 3]
    tri = torch.cat([tri[..., 0], tri[..., 1], tri[..., 2]], -1).reshape(-1, 9).float().contiguous()
    hs, ws = hw[0] * s, hw[1] * s
    n = t * hs * ws
    device = "cuda:0" if projected.is_cuda else "cpu"
    zbuf = wp.full(n, 1e30, dtype=wp.float32, device=device)
    fbuf = wp.full(n, -1, dtype=wp.int32, device=device)
    w_tri = wp.from_torch(tri)
    for write_ids in (0, 1):
        wp.launch(raster_pass, dim=tri.shape[0], inputs=[w_tri, hs, ws, faces.shape[0], 1e-3, write_ids, zbuf, fbuf],
                  device=device)
    wp.synchronize()
    return wp.to_torch(fbuf).view(t, hs, ws)


def _compare_warp(model, camera, vertices, rotation, translation, supersample_list, repeats, device) -> None:
    """Torch rasterizer vs the warp kernels on the same projected frames (ms per frame, face-id agreement)."""
    import torch

    from davis_rig.scene.rasterize import rasterize_sparse

    if wp is None:
        print("warp comparison skipped: warp-lang is not installed (pip install warp-lang)")
        return
    wp.init()
    projected = camera.project(vertices, rotation, translation)
    frames = projected.shape[0]
    sync = cuda_sync(device)
    for s in supersample_list:
        start = time.perf_counter()
        warp_raster(projected, model.faces, camera.hw, s)
        first_s = time.perf_counter() - start
        w_med, _, _ = time_ms(lambda: warp_raster(projected, model.faces, camera.hw, s), 1, repeats, sync)
        t_med, _, _ = time_ms(lambda: rasterize_sparse(projected, model.faces, camera.hw, s), 1, repeats, sync)
        ids = warp_raster(projected, model.faces, camera.hw, s).long().reshape(-1)
        ours = rasterize_sparse(projected, model.faces, camera.hw, s)
        dense = torch.full_like(ids, -1)
        dense[ours.sample] = ours.face
        agree = float((dense == ids).float().mean())
        print(
            f"[warp {wp.get_device()}] {camera.width_px}x{camera.height_px} s={s}: warp {w_med / frames:6.2f} ms/frame"
            f" (first call incl. kernel build/load {first_s:.2f} s) | torch rasterize_sparse {t_med / frames:6.2f} ms/frame"
            f" | torch/warp {t_med / w_med:.2f} | face-id agreement {agree:.5f}"
        )


def _time_camera(model, vertices, name: str, camera, threads: int, first_threads: bool, args, sync,
                 results: dict) -> None:
    """Time rasterization, texture lookup and one optimiser step for one camera at each supersampling factor
    (ms per frame into ``results[(threads, name, s, "raster" | "step")]``) and print them."""
    import torch

    from davis_rig.scene.camera import distance_for_height, look_at
    from davis_rig.scene.masks import part_mask
    from davis_rig.scene.renderer import rasterize_mesh

    device = vertices.device
    mask = part_mask(("torso", "arms", "legs"))
    grid = torch.rand(10, 10, device=device)
    d = distance_for_height("middle", camera)
    rotation, translation = look_at([0.0, -d, 0.875], [0.0, 0.0, 0.875])
    r = torch.as_tensor(rotation, dtype=torch.float32, device=device)
    t = torch.as_tensor(translation, dtype=torch.float32, device=device)
    for s in args.supersample:
        raster_fn = lambda: rasterize_mesh(vertices, model.faces, model.face_uvs, camera, r, t, supersample=s)  # noqa: E731
        med, iqr, low = time_ms(raster_fn, args.warmup, args.repeats, sync)
        raster = raster_fn()
        results[(threads, name, s, "raster")] = med / args.frames
        lk_med, _, _ = time_ms(lambda: raster.lookup(1024, "nearest", grid_n=10, mask=mask), 1, args.repeats, sync)
        lookup = raster.lookup(1024, "nearest", grid_n=10, mask=mask)
        background = torch.full(camera.hw, 0.5, device=device)

        def step():
            g = grid.clone().requires_grad_()
            raster.compose(lookup.sample(g), background).sum().backward()

        st_med, st_iqr, st_low = time_ms(step, args.warmup, args.repeats, sync)
        results[(threads, name, s, "step")] = st_med / args.frames
        pairs = _pairs_per_sample(camera.project(vertices[:1], r, t), model.faces, camera.hw, s) if first_threads else float("nan")
        print(
            f"[threads {threads}] {name} s={s}  raster {med / args.frames:7.2f} ms/frame (IQR {iqr / args.frames:.2f}, min {low / args.frames:.2f})"
            f" | lookup {lk_med / args.frames:6.2f} | step (lookup+compose+backward) {st_med / args.frames:6.2f} ms/frame (min {st_low / args.frames:.2f})"
            f" | samples/frame {raster.face.numel() // args.frames}"
            + (f" | bbox pairs per covered sample {pairs:.2f}" if np.isfinite(pairs) else "")
        )


def _print_ratios(results: dict, thread_list: list[int], supersample: list[int]) -> None:
    """Thread scaling, the cost of supersampling and the step / rasterization ratio per camera."""
    print("ratios:")
    for name in ("346x260", "304x240"):
        for s in supersample:
            if len(thread_list) > 1 and (thread_list[-1], name, s, "raster") in results:
                a, b = results[(thread_list[0], name, s, "raster")], results[(thread_list[-1], name, s, "raster")]
                print(f"  {name} s={s}: raster {thread_list[-1]} threads / {thread_list[0]} thread = {b / a:.2f}")
            base = results.get((thread_list[-1], name, 1, "raster"))
            if s != 1 and base:
                print(f"  {name} s={s}: raster vs s=1 = {results[(thread_list[-1], name, s, 'raster')] / base:.2f}")
        s = supersample[-1]
        ratio = results[(thread_list[-1], name, s, "step")] / results[(thread_list[-1], name, s, "raster")]
        print(f"  {name} s={s}: optimiser step / rasterization = {ratio:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--supersample", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--warp", action="store_true", help="also time the warp-kernel rasterizer (if installed)")
    args = parser.parse_args()

    import torch

    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.camera import PinholeCamera, distance_for_height, look_at

    device = torch.device(args.device)
    sync = cuda_sync(device)
    gpu = f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""
    print(metadata_line(device=f"{device}{gpu}", frames_per_batch=args.frames,
                        repeats=f"{args.repeats} (+{args.warmup} warm-up)"))
    model = BodyModel(device=device)
    times = np.arange(args.frames) / 200.0
    thread_list = args.threads if device.type == "cpu" else [torch.get_num_threads()]
    results = {}
    for threads in thread_list:
        set_torch_threads(threads)
        med, iqr, low = time_ms(lambda: model.walk_vertices(0, times), args.warmup, args.repeats, sync)
        print(f"[threads {threads}] pose (FK+LBS)            {med / args.frames:8.2f} ms/frame (IQR {iqr / args.frames:.2f}, min {low / args.frames:.2f})")
        vertices = model.walk_vertices(0, times)
        c, s_ = np.cos(np.pi / 2), np.sin(np.pi / 2)
        vertices = vertices @ torch.tensor([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]], dtype=vertices.dtype, device=device).T
        for name, camera in (("346x260", PinholeCamera.davis346()), ("304x240", PinholeCamera.rvt_crop())):
            _time_camera(model, vertices, name, camera, threads, threads == thread_list[0], args, sync, results)
    if args.warp:
        set_torch_threads(thread_list[0])
        camera = PinholeCamera.rvt_crop()
        d = distance_for_height("middle", camera)
        rotation, translation = look_at([0.0, -d, 0.875], [0.0, 0.0, 0.875])
        _compare_warp(model, camera, vertices, torch.as_tensor(rotation, dtype=torch.float32, device=device),
                      torch.as_tensor(translation, dtype=torch.float32, device=device), args.supersample, args.repeats, device)
    _print_ratios(results, thread_list, args.supersample)


if __name__ == "__main__":
    main()
