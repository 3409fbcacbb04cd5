"""Benchmark: motion generation, resampling to the render rate and mocap retargeting (all numpy, CPU).

Cases, each the median (and IQR) over repeated runs after warm-up:

* ``gait_walk`` / ``gait_run``: :func:`generate_gait` of one cycle at 200 fps (1.3 m/s walk, 3.2 m/s run);
* ``resample_200``: :func:`resample` of a 10 s clip from 120 fps to the 200 fps render rate (slerp, 104 bones);
* ``amass_retarget``: :func:`retarget_smplh` of 1,000 SMPL-H frames (random body poses) onto the anny rig;
* ``ground_offsets``: the numpy sole-contact heights of those 1,000 frames.

Ratios: resampling per output frame vs one rendered frame's 5 ms budget at 200 fps.
Run: ``python benchmarks/motion.py [--repeats N] [--threads 2]``.
"""

from __future__ import annotations

import argparse

from _common import limit_blas_threads, metadata_line, time_ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None,
                        help="BLAS threads via OMP/OPENBLAS/MKL_NUM_THREADS, set before numpy is imported")
    args = parser.parse_args()
    limit_blas_threads(args.threads)
    import numpy as np

    from davis_rig.scene.body import BodyAsset
    from davis_rig.scene.gait import GaitParams, generate_gait
    from davis_rig.scene.mocap.amass import retarget_smplh
    from davis_rig.scene.mocap.retarget import ground_offsets
    from davis_rig.scene.motion import Motion, resample

    asset = BodyAsset.load()
    rng = np.random.default_rng(0)
    clip = Motion(rng.normal(size=(1201, asset.num_bones, 4)), rng.normal(size=(1201, 3)), 120.0)
    poses = np.zeros((1000, 156))
    poses[:, 0] = np.pi / 2
    poses[:, 3:66] = rng.normal(0, 0.3, (1000, 63))
    retargeted = retarget_smplh(poses, np.zeros((1000, 3)), 120.0, asset, 0)
    cases = {
        "gait_walk": lambda: generate_gait(GaitParams(speed_m_s=1.3), asset, 0),
        "gait_run": lambda: generate_gait(GaitParams(speed_m_s=3.2, run=1.0), asset, 0),
        "resample_200": lambda: resample(clip, 200.0),
        "amass_retarget": lambda: retarget_smplh(poses, np.zeros((1000, 3)), 120.0, asset, 0),
        "ground_offsets": lambda: ground_offsets(retargeted, asset, 0),
    }
    print("# motion benchmark (numpy, CPU)")
    print(metadata_line(packages=("numpy",), blas_threads=args.threads or "default",
                        repeats=f"{args.repeats} (+{args.warmup} warm-up)"))
    results = {}
    for name, fn in cases.items():
        timing = time_ms(fn, args.warmup, args.repeats)
        results[name] = timing.median_ms
        print(f"{name:16s} {timing}")
    per_frame = results["resample_200"] / 2001
    print(f"resample per 200 fps output frame: {per_frame * 1e3:.1f} µs = {per_frame / 5.0:.2%} of a 5 ms frame period")
    print(f"amass retarget per frame: {results['amass_retarget'] / 1000 * 1e3:.1f} µs; "
          f"ground offsets per frame: {results['ground_offsets'] / 1000 * 1e3:.1f} µs")


if __name__ == "__main__":
    main()
