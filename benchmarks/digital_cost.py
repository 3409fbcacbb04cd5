"""Benchmark: the digital attack's cost per 50 ms window (rendering + V2E, as the optimiser runs them) vs RVT-B.

The issue's goal: rendering + V2E <= 10 % of the detector's forward + backward for the same window. Cases, per
window of the attack's default clip (:class:`davis_rig.attack.eot.EoTConfig`: 304x240, 200 fps, 3 windows of 10
frames + the reference frame, supersampling 2, 10x10 grid on torso/arms/legs), median and IQR in ms over
``--repeats`` runs after ``--warmup`` (the step cases and the detector interleaved, so load drift hits them alike):

* ``clip preparation``: :func:`davis_rig.attack.eot.prepare_clip` (pose, rasterization, texel lookup, sensor
  draws, backdrop; no autograd) of one clip, a new scene each run; per window (clip / 3) and amortised as the
  attack pays it: the pool's initial clips plus ``round(refresh_fraction * pool_size)`` rebuilt every
  ``refresh_every`` steps, over the run's iterations (:class:`davis_rig.attack.optimize.AttackConfig` defaults),
  per window of the ``clips_per_step`` clips a step uses;
* ``texture step``: :meth:`PoolClip.video` (texel lookup + compose) and backward of a fixed random gradient into
  the grid;
* ``V2E relaxed`` / ``V2E ste``: :func:`davis_rig.attack.optimize.clip_histograms` on a given video (the
  attack's exact "dvs" counts with the clip's thresholds and noise, on the person's box
  :attr:`~davis_rig.attack.eot.PoolClip.active_box` as a step runs it; backward by the default relaxed
  surrogate, or by the paper's straight-through floor), forward and backward of a fixed random gradient into the
  video;
* ``texture + V2E``: ``clip_histograms`` on the grid, as a step runs it (a check on the sum of the two above);
* ``RVT-B fwd+bwd``: random-weight RVT-B over the 3-window sequence with recurrent states, backward of
  sum(objectness x max class probability) over all windows into the inputs, divided by 3.

Printed: each case's ratio to RVT-B, and the combined ratio (amortised clip preparation + texture + V2E relaxed,
the step measured as one call) against the 10 % goal; per rendered frame figures beside the per-window ones.

Run: ``python benchmarks/digital_cost.py [--repeats 9] [--warmup 2] [--threads 1 2] [--device cpu cuda]
[--model base] [--quick]`` (``--device`` defaults to cpu, plus cuda when available; ``--quick``: 3 repeats after
1 warm-up).
"""

from __future__ import annotations

import argparse
import itertools
from typing import NamedTuple

from _common import (
    Timing,
    cuda_sync,
    detection_score,
    metadata_line,
    random_detector,
    set_torch_threads,
    time_interleaved_ms,
    time_ms,
)

#: The issue's goal: rendering + V2E at most this share of the detector's forward + backward.
GOAL_RATIO = 0.10
GRID_N = 10
PER_WINDOW = "clip preparation, per window (clip / 3)"
AMORTISED = "clip preparation, amortised"
STEP = "texture + V2E relaxed, one clip_histograms call"


class Schedule(NamedTuple):
    """How often the attack prepares clips, from :class:`~davis_rig.attack.optimize.AttackConfig` fields."""

    pool_size: int
    refresh_every: int
    refresh_fraction: float
    iterations: int
    clips_per_step: int
    seq_len: int


def clips_prepared_per_step(schedule: Schedule) -> float:
    """Clips prepared per optimisation step, averaged over the run: the initial pool plus every refresh.

    A refresh runs at each step ``s`` in ``1 .. iterations - 1`` with ``s % refresh_every == 0`` and rebuilds
    ``round(refresh_fraction * pool_size)`` clips (:meth:`davis_rig.attack.eot.ClipPool.refresh`).
    """
    refreshes = (schedule.iterations - 1) // schedule.refresh_every
    rebuilt = round(schedule.refresh_fraction * schedule.pool_size)
    return (schedule.pool_size + refreshes * rebuilt) / schedule.iterations


def preparations_per_window(schedule: Schedule) -> float:
    """Clips prepared per window a step processes (``clips_per_step`` clips of ``seq_len`` windows each)."""
    return clips_prepared_per_step(schedule) / (schedule.clips_per_step * schedule.seq_len)


def cost_lines(per_window: dict[str, Timing], rvt: Timing, frames_per_window: int, combined: tuple[str, ...],
               goal: float = GOAL_RATIO) -> list[str]:
    """The report: one line per case (ms per window and per frame, ratio to the detector), then the combined ratio.

    Args:
        per_window: case name -> timing per window, ms.
        rvt: the detector's forward + backward per window, ms.
        frames_per_window: rendered frames per window (per-frame figures).
        combined: the case names whose medians add up to the digital cost of a step.
        goal: the target ratio of the combined cost to the detector's.
    """
    lines = [f"{'case (per 50 ms window)':52s} {'median ms':>10s} {'IQR':>8s} {'ms/frame':>9s} {'/ RVT':>8s}"]
    for name, timing in {**per_window, "RVT fwd+bwd (3-window sequence / 3)": rvt}.items():
        lines.append(f"{name:52s} {timing.median_ms:10.2f} {timing.iqr_ms:8.2f} "
                     f"{timing.median_ms / frames_per_window:9.3f} {100 * timing.median_ms / rvt.median_ms:7.2f}%")
    total = sum(per_window[name].median_ms for name in combined)
    ratio = total / rvt.median_ms
    verdict = "met" if ratio <= goal else "not met"
    lines.append(f"combined ({' + '.join(combined)}): {total:.2f} ms = {100 * ratio:.2f} % of RVT fwd+bwd "
                 f"(goal <= {100 * goal:.0f} %: {verdict})")
    return lines


class _GivenVideo:
    """A pool clip whose video is a fixed leaf tensor: :func:`clip_histograms` on it times V2E alone."""

    def __init__(self, clip, video):
        self._clip = clip
        self._video = video

    def video(self, grid):
        return self._video.detach().requires_grad_(True)

    def active_video(self, grid):
        y0, y1, x0, x1 = self._clip.active_box
        return self.video(grid)[:, y0:y1, x0:x1]

    def __getattr__(self, name):
        return getattr(self._clip, name)


def run(device, model_name: str, warmup: int, repeats: int) -> None:
    """Time every case on one device (the current torch thread count) and print the report."""
    import torch

    from davis_rig.attack.eot import EoTConfig, draw_scene, prepare_clip
    from davis_rig.attack.optimize import AttackConfig, clip_histograms
    from davis_rig.models.rvt.detector import pad_to_input
    from davis_rig.scene.body import BodyModel
    from davis_rig.scene.masks import part_mask

    config = AttackConfig(grid_n=GRID_N)
    eot: EoTConfig = config.eot
    schedule = Schedule(config.pool_size, config.refresh_every, config.refresh_fraction, config.iterations,
                        config.clips_per_step, eot.seq_len)
    sync = cuda_sync(device)
    body = BodyModel(device=device)
    mask = part_mask(config.parts)
    seeds = itertools.count(100)

    def prepare(seed: int):
        spec, sensor = draw_scene(eot, seed, body.num_shapes)
        return prepare_clip(spec, sensor, body, GRID_N, mask, config=eot, seed=seed)

    clip_timing = time_ms(lambda: prepare(next(seeds)), warmup, repeats, sync)
    clip = prepare(100)
    frames = clip.raster.num_frames
    frames_per_window = (frames - 1) // eot.seq_len
    generator = torch.Generator(device=device).manual_seed(0)
    grid = torch.rand(GRID_N, GRID_N, generator=generator, device=device)
    grad_video = torch.randn(frames, *clip.raster.hw, generator=generator, device=device)
    grad_hist = torch.randn(eot.seq_len, 20, *clip.raster.hw, generator=generator, device=device)
    given = _GivenVideo(clip, clip.video(grid).detach())
    detector = random_detector(model_name, device)
    with torch.no_grad():
        inputs = [pad_to_input(h[None], detector.config.in_res_hw) for h in clip_histograms(grid, clip)]

    def texture() -> None:
        clip.video(grid.clone().requires_grad_(True)).backward(grad_video)

    def v2e(gradient: str, source) -> None:
        clip_histograms(grid.clone().requires_grad_(True), source, gradient=gradient).backward(grad_hist)

    def detector_fwd_bwd() -> None:
        xs = [x.clone().requires_grad_(True) for x in inputs]
        states, score = None, 0.0
        for x in xs:
            decoded, states = detector(x, states)
            score = score + detection_score(decoded)
        score.backward()

    cases = {
        "texture step (lookup + compose + backward)": texture,
        "V2E relaxed (default) fwd+bwd": lambda: v2e("relaxed", given),
        "V2E ste fwd+bwd": lambda: v2e("ste", given),
        STEP: lambda: v2e("relaxed", clip),
        "texture + V2E ste, one clip_histograms call": lambda: v2e("ste", clip),
        "rvt": detector_fwd_bwd,
    }
    timings = time_interleaved_ms(cases, warmup, repeats, sync)
    rvt = timings.pop("rvt").scaled(1 / eot.seq_len)
    per_window = {
        PER_WINDOW: clip_timing.scaled(1 / eot.seq_len),
        AMORTISED: clip_timing.scaled(preparations_per_window(schedule)),
        **{name: timing.scaled(1 / eot.seq_len) for name, timing in timings.items()},
    }
    y0, y1, x0, x1 = clip.active_box
    print(f"  clip: {frames} frames ({frames_per_window} per window), {tuple(clip.raster.hw)} px, "
          f"{clip.lookup.index.shape[0]} covered samples, V2E on the person's {y1 - y0}x{x1 - x0} px box "
          f"({100 * (y1 - y0) * (x1 - x0) / (clip.raster.hw[0] * clip.raster.hw[1]):.0f} % of the frame); "
          f"preparation amortised over the default pool "
          f"({clips_prepared_per_step(schedule):.3f} clips per step of {schedule.clips_per_step} clip(s)); "
          f"RVT: {detector.config.name}")
    lines = cost_lines(per_window, rvt, frames_per_window, combined=(AMORTISED, STEP))
    lines += cost_lines(per_window, rvt, frames_per_window, combined=(PER_WINDOW, STEP))[-1:]
    print("\n".join("  " + line for line in lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="CPU intra-op thread counts")
    parser.add_argument("--device", nargs="+", default=None, help="default: cpu, and cuda when available")
    parser.add_argument("--model", default="base", choices=["tiny", "small", "base", "mini"],
                        help="RVT preset with random weights (the goal is stated against base)")
    parser.add_argument("--quick", action="store_true", help="3 repeats after 1 warm-up")
    args = parser.parse_args()
    if args.quick:
        args.repeats, args.warmup = 3, 1

    import torch

    devices = args.device or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    print(f"# digital attack cost per 50 ms window vs RVT-{args.model} fwd+bwd (goal: <= {100 * GOAL_RATIO:.0f} %); "
          f"median / IQR of {args.repeats} runs after {args.warmup} warm-up, fp32")
    for name in devices:
        device = torch.device(name)
        for threads in args.threads if device.type == "cpu" else [None]:
            if threads is not None:
                set_torch_threads(threads)
            label = f"{device} ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else f"{device}"
            print(metadata_line(device=label))
            print(f"## {label}" + (f", {threads} thread(s)" if threads is not None else ""))
            run(device, args.model, args.warmup, args.repeats)


if __name__ == "__main__":
    main()
