"""Benchmark: eager PyTorch RVT detector on the CPU (random weights, batch 1, 256×320, fp32).

Measures, for RVT-T and RVT-B at 1 and 2 intra-op threads: one recurrent forward step (backbone + FPN +
head with states), the backbone alone, forward + backward w.r.t. the input for one step, and a 3-step BPTT
(3 forwards + backward), as the median (and IQR) of repeated runs after warm-up. Prints the figures, the
B/T ratio, the 2-thread speed-up, and the ratio to the official model measured on the reference machine
(``shared/rvt/ARCHITECTURE.md`` §9, 1 thread) — a ratio ≈ 1 means no overhead versus the official code.

Run: ``python benchmarks/rvt_eager.py [--repeats N] [--variants tiny base] [--threads 1 2]``.
"""

from __future__ import annotations

import argparse

import torch
from _common import bptt_case, detection_score, metadata_line, random_detector, set_torch_threads, time_ms

from davis_rig.models.rvt.detector import RVTDetector

#: Official model, 1 thread, ms (ARCHITECTURE.md §9, measured on the reference machine).
OFFICIAL_1T_MS = {
    ("tiny", "forward_step"): 55.0,
    ("tiny", "backbone"): 40.0,
    ("tiny", "fwd_bwd_1step"): 130.0,
    ("tiny", "bptt_3steps"): 431.0,
    ("base", "forward_step"): 164.0,
    ("base", "backbone"): 113.0,
    ("base", "fwd_bwd_1step"): 364.0,
    ("base", "bptt_3steps"): 1135.0,
}


def _cases(model: RVTDetector, generator: torch.Generator):
    inputs = [torch.randint(0, 11, (1, 20, 256, 320), generator=generator).float() for _ in range(3)]
    with torch.no_grad():
        _, warm_states = model(inputs[0])

    def forward_step():
        with torch.inference_mode():
            model(inputs[1], warm_states)

    def backbone():
        with torch.inference_mode():
            model.forward_backbone(inputs[1], warm_states)

    def fwd_bwd_1step():
        x = inputs[1].clone().requires_grad_(True)
        decoded, _ = model(x, warm_states)
        detection_score(decoded).backward()

    return {
        "forward_step": forward_step,
        "backbone": backbone,
        "fwd_bwd_1step": fwd_bwd_1step,
        "bptt_3steps": bptt_case(model, inputs),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--variants", nargs="+", default=["tiny", "base"], choices=["tiny", "small", "base", "mini"])
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    args = parser.parse_args()

    print("# RVT eager benchmark (random weights, batch 1, input 20x256x320, fp32, CPU)")
    print(metadata_line(packages=("torch",), capability=torch.backends.cpu.get_cpu_capability(),
                        repeats=f"{args.repeats} (+{args.warmup} warm-up)"))
    results: dict[tuple[str, int, str], float] = {}
    generator = torch.Generator().manual_seed(0)
    for variant in args.variants:
        model = random_detector(variant)
        config = model.config
        cases = _cases(model, generator)
        for threads in args.threads:
            set_torch_threads(threads)
            for name, fn in cases.items():
                repeats = args.repeats if variant != "base" or name != "bptt_3steps" else max(3, args.repeats // 2)
                median_ms, iqr_ms, _ = time_ms(fn, args.warmup, repeats)
                results[(variant, threads, name)] = median_ms
                official = OFFICIAL_1T_MS.get((variant, name)) if threads == 1 else None
                ratio = f"  ours/official(1 thread) {median_ms / official:.2f}" if official else ""
                print(
                    f"{config.name:8s} threads {threads}  {name:14s} median {median_ms:8.1f} ms  "
                    f"IQR {iqr_ms:6.1f} ms{ratio}"
                )
    print("# ratios")
    for threads in args.threads:
        for name in ("forward_step", "backbone", "fwd_bwd_1step", "bptt_3steps"):
            if ("tiny", threads, name) in results and ("base", threads, name) in results:
                ratio = results[("base", threads, name)] / results[("tiny", threads, name)]
                print(f"B/T  threads {threads}  {name:14s} {ratio:.2f}")
    if 1 in args.threads and 2 in args.threads:
        for variant in args.variants:
            for name in ("forward_step", "bptt_3steps"):
                speedup = results[(variant, 1, name)] / results[(variant, 2, name)]
                print(f"{variant:5s} 1->2 threads speed-up  {name:14s} {speedup:.2f}")


if __name__ == "__main__":
    main()
