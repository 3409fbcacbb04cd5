"""Benchmark: seconds per attack iteration (RVT-B, seq len 3): texture compose + V2E + forward + backward + Adam.

One iteration is exactly what :func:`davis_rig.attack.optimize.optimize_texture` does per step (batch of
``--clips`` pool clips): generator -> binarize_ste -> texel lookup + compose of the pre-rasterized clip (grad) ->
differentiable V2E ("dvs" counts with the clip's per-pixel thresholds and noise; backward by ``--v2e-gradient``)
-> RVT (random weights of ``--model``, or ``--detector`` weights; eval mode, frozen) over 3 windows with recurrent
states -> L_adv -> backward -> Adam step. The one-off rasterization of a pool clip (no grad) is timed separately
and also reported amortised over the default pool refresh (a quarter of 32 clips every 50 steps). Stage shares
come from one extra instrumented iteration per setting.

``--step`` picks how the detector part (pad → RVT over the windows → L_adv) runs: ``attack_loss`` (the attack's
own function), or :class:`davis_rig.attack.fixed_step.FixedShapeAttackLoss` in the mode ``eager`` (same
operations, bit-identical), ``cuda_graph`` (recorded once, forward and backward; CUDA only) or ``compile``
(``torch.compile``; ``reduce-overhead`` on CUDA). The graph modes are built in the warm-up iterations.

Reported: median, IQR and min of ``--repeats`` iterations after ``--warmup`` untimed ones (``_common``), per
device and CPU thread count, and on the CPU the process CPU seconds per iteration (median; less sensitive to a
shared machine's load than the wall time); the official code's ~2.3 s/iteration (GPU) and the goal of <= 0.1 s on
one H100/H200 as ratios. CPU timings on a shared machine are noisy: the header line carries the load average.
``OMP_WAIT_POLICY`` is set to ``PASSIVE`` unless given: with OpenMP's default spin-waiting, eager torch on a loaded
machine stalls for 0.5–4.8 s in some steps.

Run: ``python benchmarks/attack_step.py [--threads 1 2] [--repeats 3] [--clips 1] [--model base] [--no-cuda | --no-cpu]
[--precision bf16] [--v2e-gradient relaxed|ste] [--detector CKPT] [--step attack_loss|eager|cuda_graph|compile]``
(bf16 applies to the CUDA run).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP: no spin-wait stalls under load

import torch  # noqa: E402
from _common import cuda_sync, metadata_line, random_detector, set_torch_threads, time_ms  # noqa: E402

from davis_rig.attack.eot import EoTConfig, draw_scene, prepare_clip  # noqa: E402
from davis_rig.attack.fixed_step import STEP_MODES, FixedShapeAttackLoss  # noqa: E402
from davis_rig.attack.optimize import AttackConfig, attack_loss, clip_histograms, load_attack_detector  # noqa: E402
from davis_rig.attack.texture import TextureGenerator, binarize_ste  # noqa: E402
from davis_rig.models.rvt.detector import pad_to_input  # noqa: E402
from davis_rig.scene.body import BodyModel  # noqa: E402
from davis_rig.scene.masks import part_mask  # noqa: E402

OFFICIAL_S = 2.3
GOAL_S = 0.1


def _detector(model_name: str, path: str | None, device: torch.device):
    if path is not None:
        return load_attack_detector(path, device=device)
    return random_detector(model_name, device)


def run(device: torch.device, detector, clips_per_step: int, warmup: int, repeats: int, precision: str = "fp32",
        v2e_gradient: str = "relaxed", step_mode: str = "attack_loss") -> float:
    """Time one setting; prints the iteration timing, the clip rasterization and the stage shares; returns s/it."""
    cfg = AttackConfig(grid_n=10, clips_per_step=clips_per_step, pool_size=max(clips_per_step, 1),
                       precision=precision, v2e_gradient=v2e_gradient)
    sync = cuda_sync(device) or (lambda: None)
    body = BodyModel(device=device)
    mask = part_mask(cfg.parts)
    eot = EoTConfig()
    t0 = time.perf_counter()
    clips = []
    for i in range(clips_per_step):
        spec, sensor = draw_scene(eot, 100 + i, body.num_shapes)
        clips.append(prepare_clip(spec, sensor, body, cfg.grid_n, mask, config=eot, seed=100 + i))
    sync()
    raster_s = (time.perf_counter() - t0) / clips_per_step
    generator = TextureGenerator(cfg.grid_n).to(device).train()
    optimizer = torch.optim.Adam(generator.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)

    if step_mode == "attack_loss":
        def loss_fn(grid):
            return attack_loss(grid, clips, detector, cfg)
    else:
        fixed = FixedShapeAttackLoss(detector, cfg, step_mode)

        def loss_fn(grid):
            return fixed(grid, clips)
    cpu_s = []

    def step() -> None:
        cpu = time.process_time()
        grid = binarize_ste(generator(), 0.5)
        loss = loss_fn(grid)
        optimizer.zero_grad(set_to_none=True)
        loss.total.backward()
        optimizer.step()
        cpu_s.append(time.process_time() - cpu)

    timing = time_ms(step, warmup, repeats, cuda_sync(device))
    cpu_s = sorted(cpu_s[warmup:])

    # instrumented iteration: stage shares
    stages = {}
    sync()
    t = time.perf_counter()
    grid = binarize_ste(generator(), 0.5)
    videos = [c.video(grid) for c in clips]
    sync()
    stages["generator + compose"] = time.perf_counter() - t
    t = time.perf_counter()
    x = torch.stack([clip_histograms(grid, c, gradient=v2e_gradient) for c in clips], dim=1)
    sync()
    stages["V2E (incl. compose again)"] = time.perf_counter() - t
    t = time.perf_counter()
    states, outs = None, []
    with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=precision == "bf16"):
        for w in range(x.shape[0]):
            out, states = detector(pad_to_input(x[w], detector.config.in_res_hw), states)
            outs.append(out.float())
    loss = sum(o[..., 4].mean() + o[..., 6].mean() for o in outs)
    sync()
    stages["RVT forward (3 windows)"] = time.perf_counter() - t
    t = time.perf_counter()
    loss.backward()
    sync()
    stages["backward (RVT + V2E + compose)"] = time.perf_counter() - t
    del videos
    med = timing.median_ms / 1e3
    paper = AttackConfig()
    refreshed = round(paper.refresh_fraction * paper.pool_size)
    refresh_s = raster_s * refreshed / paper.refresh_every
    print(f"  iteration ({step_mode}): {timing}  ({repeats} runs, {warmup} warm-up); process CPU median "
          f"{1e3 * cpu_s[len(cpu_s) // 2]:.0f} ms")
    print(f"  per-clip rasterization (one-off, no grad): {raster_s:.3f} s; amortised over the default pool refresh "
          f"({refreshed} clips / {paper.refresh_every} steps): {refresh_s:.3f} s/step")
    total = sum(stages.values())
    for name, value in stages.items():
        print(f"    {name:34s} {value:.3f} s  ({100 * value / total:.0f} %)")
    print(f"  ratio official 2.3 s / this: {OFFICIAL_S / med:.2f}x;  this / goal 0.1 s: {med / GOAL_S:.1f}x")
    return med


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--clips", type=int, default=1, help="EoT clips per iteration (batch)")
    parser.add_argument("--model", default="base", choices=["tiny", "small", "base", "mini"],
                        help="RVT size with random weights (ignored with --detector)")
    parser.add_argument("--detector", default=None, metavar="CKPT", help="time a trained detector's weights instead")
    parser.add_argument("--v2e-gradient", choices=["relaxed", "ste"], default="relaxed")
    parser.add_argument("--no-cuda", action="store_true")
    parser.add_argument("--no-cpu", action="store_true", help="skip the CPU runs (time the CUDA device only)")
    parser.add_argument("--precision", choices=["fp32", "bf16"], default="fp32", help="detector autocast on CUDA")
    parser.add_argument("--step", choices=["attack_loss", *STEP_MODES], default="attack_loss",
                        help="how the detector part runs (see the module docstring)")
    args = parser.parse_args()
    if args.step == "cuda_graph" and not args.no_cpu:
        parser.error("--step cuda_graph records a CUDA graph: add --no-cpu")
    name = args.detector or f"RVT-{args.model} (random weights)"
    print(f"attack step benchmark: {name}, seq len 3, 304x240, grid 10x10, clips/iter {args.clips}, "
          f"V2E gradient {args.v2e_gradient}")
    results = {}
    for threads in [] if args.no_cpu else args.threads:
        set_torch_threads(threads)
        print(metadata_line())
        print(f"CPU, {threads} thread(s):")
        cpu = torch.device("cpu")
        results[f"cpu{threads}"] = run(cpu, _detector(args.model, args.detector, cpu), args.clips, args.warmup,
                                       args.repeats, v2e_gradient=args.v2e_gradient, step_mode=args.step)
    if torch.cuda.is_available() and not args.no_cuda:
        cuda = torch.device("cuda")
        print(metadata_line(device=f"cuda ({torch.cuda.get_device_name(0)})"))
        torch.backends.cudnn.benchmark = True
        results["cuda"] = run(cuda, _detector(args.model, args.detector, cuda), args.clips, max(args.warmup, 3),
                              max(args.repeats, 10), args.precision, args.v2e_gradient, args.step)
    if "cpu1" in results and "cpu2" in results:
        print(f"speed-up 2 threads vs 1: {results['cpu1'] / results['cpu2']:.2f}x")
    if "cuda" in results and "cpu1" in results:
        print(f"speed-up CUDA vs CPU 1 thread: {results['cpu1'] / results['cuda']:.1f}x")


if __name__ == "__main__":
    main()
