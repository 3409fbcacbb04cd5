"""Benchmark: body model posing (FK + LBS) and UV part-mask construction.

Cases, each the median (and IQR) over repeated runs after warm-up:

* ``load``: :meth:`BodyAsset.load` of the bundled asset + :class:`BodyModel` construction;
* ``fk``: :meth:`BodyModel.forward_kinematics` for T frames (104 bones);
* ``pose``: :meth:`BodyModel.pose` (FK + dense LBS of 13,718 vertices) for T frames, reported per frame;
* ``pose_backward``: pose + backward of a scalar loss w.r.t. the rotations and root translation;
* ``walk_vertices``: :meth:`BodyModel.walk_vertices` (walk sampling with nlerp + pose) for T times;
* ``masks``: :func:`part_label_map` (rasterise + 4-texel seam padding) at 1024 x 1024, uncached.

Runs on CPU, and on CUDA too when available (``--device cuda``). Ratios: per-frame cost at T=256 vs T=1.
Run: ``python benchmarks/body.py [--repeats N] [--frames 1 40 256] [--threads 2] [--device cpu]``.
"""

from __future__ import annotations

import argparse

from _common import cuda_sync, metadata_line, set_torch_threads, time_ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--frames", type=int, nargs="+", default=[1, 40, 256])
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    import numpy as np
    import torch

    from davis_rig.scene import masks
    from davis_rig.scene.body import BodyAsset, BodyModel

    set_torch_threads(args.threads)
    device = torch.device(args.device)
    sync = cuda_sync(device)
    gpu = f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""
    print(metadata_line(device=f"{device}{gpu}", repeats=f"{args.repeats} (+{args.warmup} warm-up)"))

    med, iqr, _ = time_ms(lambda: BodyModel(BodyAsset.load(), device=device), 1, max(3, args.repeats // 3), sync)
    print(f"load asset + build model: {med:8.1f} ms (IQR {iqr:.1f})")
    model = BodyModel(device=device)
    walk = model.asset.walk_cycle(0)
    per_frame = {}
    for frames in args.frames:
        idx = np.arange(frames) % walk.num_frames
        quats = torch.as_tensor(np.array(walk.rotations_wxyz[idx]), device=device)
        root = torch.as_tensor(np.array(walk.root_translation_m[idx]), device=device)
        with torch.no_grad():
            fk, fk_iqr, _ = time_ms(lambda: model.forward_kinematics(0, quats, root), args.warmup, args.repeats, sync)
            pose, pose_iqr, _ = time_ms(lambda: model.pose(0, quats, root), args.warmup, args.repeats, sync)
            t_s = np.arange(frames) / 240.0
            walk_ms, walk_iqr, _ = time_ms(lambda: model.walk_vertices(0, t_s), args.warmup, args.repeats, sync)
        q = quats.clone().requires_grad_(True)
        r = root.clone().requires_grad_(True)

        def forward_backward():
            model.pose(0, q, r).square().mean().backward()

        bwd, bwd_iqr, _ = time_ms(forward_backward, args.warmup, args.repeats, sync)
        per_frame[frames] = pose / frames
        print(
            f"T={frames:4d}: fk {fk:8.2f} ms (IQR {fk_iqr:.2f}) | pose {pose:8.2f} ms (IQR {pose_iqr:.2f}, "
            f"{pose / frames:.3f} ms/frame) | pose+backward {bwd:8.2f} ms (IQR {bwd_iqr:.2f}) | "
            f"walk_vertices {walk_ms:8.2f} ms (IQR {walk_iqr:.2f})"
        )
    if 1 in per_frame and max(per_frame) > 1:
        big = max(per_frame)
        print(f"ratio per-frame pose cost T=1 / T={big}: {per_frame[1] / per_frame[big]:.1f}x (batching gain)")
    med, iqr, _ = time_ms(lambda: masks.part_label_map(1024, 4, asset=model.asset), 1, max(3, args.repeats // 3))
    print(f"part label map 1024x1024 (rasterise + pad 4): {med:8.1f} ms (IQR {iqr:.1f})")


if __name__ == "__main__":
    main()
