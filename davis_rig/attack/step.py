"""The differentiable forward of one optimisation step: texture grid -> clips' event histograms -> ``L_adv``.

- :func:`soft_grid`: the generator's output with its dropout seeded by ``(seed, step)`` (identical on all ranks,
  exact on resume); :func:`binarization_threshold`: the cut of its binarization (0.5, or per-cell draws);
- :func:`clip_histograms`: one pre-rasterized clip in a texture -> RVT's input [W, 20, H, W] (V2E counts of the
  clip's sensor plus its noise events; the backward a relaxed-count surrogate or the paper's straight-through
  floor);
- :func:`attack_loss`: the frozen RVT over the windows of a batch of clips, with recurrent states ->
  :class:`~davis_rig.attack.loss.AdversarialLoss`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.attack.config import V2E_GRADIENTS, AttackConfig
from davis_rig.attack.eot import PoolClip
from davis_rig.attack.loss import AdversarialLoss, adversarial_loss, anchor_cells, anchors_on_boxes
from davis_rig.attack.texture import TextureGenerator, sampled_thresholds
from davis_rig.events.histogram import COUNT_CUTOFF, NUM_BINS

with optional_dependency("the attack"):
    import torch

__all__ = ["attack_loss", "clip_histograms", "soft_grid"]

def clip_histograms(grid: "torch.Tensor", clip: PoolClip, mode: str = "dvs", binning: str = "interval",
                    gradient: str = "relaxed") -> "torch.Tensor":
    """Differentiable RVT input of one pool clip: float tensor [W, 20, H, W] (V2E counts + noise, clipped at 10).

    The forward value is always the event counts of ``mode`` plus the clip's noise events, clipped at
    ``COUNT_CUTOFF``. Counts (``"dvs"``, ``"floor"``) are taken in float64, the exact simulator's precision: with a
    uniform threshold map they are the simulator's events per pixel and window (float32 lin-log values move
    ~1 % of the events across a threshold; the bins still differ where events fall near a bin edge, see
    :func:`validate`). ``"official_relaxed"`` counts are the value itself (float32, their own gradient). The
    backward pass depends on ``gradient``:

    - ``"ste"`` (paper): the V2E's own gradient, straight through the floor of the counts; the clamp at 10 has
      zero gradient. Measured on the interim RVT-mini (2 clips, ``docs/attack.md``): a step along its negative
      gradient does not reliably lower the loss (the floor's surrogate ignores whether a threshold is crossed).
    - ``"relaxed"``: the gradient of the continuous counts ``relu(±(L_{k+1} - L_k) / theta)`` per frame pair
      (the official code's relaxed simulator in count units, clip-mean threshold theta) through the same binning,
      used as a straight-through surrogate of the exact counts (value: the exact counts; gradient: the
      surrogate's), no clamp. Along its negative gradient the exact-count loss falls monotonically for steps up to
      0.3 grid units.

    Args:
        grid: float tensor [n, n] texture grid (1 = white), gradients flow to it.
        clip: a :class:`~davis_rig.attack.eot.PoolClip`.
        mode, binning: V2E settings (:func:`davis_rig.events.v2e_torch.v2e_histograms`).
        gradient: ``"relaxed"`` or ``"ste"`` (:data:`V2E_GRADIENTS`).

    Raises:
        ValueError: unknown ``gradient``; a grid mode (``"floor"``, ``"official_relaxed"``) with a non-uniform
            threshold map.
    """
    from davis_rig.events.v2e_torch import OFFICIAL_RELAXED_SCALE, log_histograms, log_intensity

    if gradient not in V2E_GRADIENTS:
        raise ValueError(f"gradient must be one of {V2E_GRADIENTS}, got {gradient!r}")
    # events can only fire where the person is: the V2E runs on clip.active_box; the full-frame tensor is built
    # once (zeros, the crop's counts, the noise events of PoolClip.add_noise, the clip at COUNT_CUTOFF)
    y0, y1, x0, x1 = clip.active_box
    video = clip.active_video(grid)
    log_video = log_intensity(video)
    uniform = clip.base_threshold is not None or bool((clip.threshold == clip.threshold.flatten()[0]).all())
    if mode != "dvs" and not uniform:  # the grid modes take one θ
        raise ValueError(f"v2e mode {mode!r} needs one threshold θ for all pixels; turn off the EoT's "
                         f"threshold mismatch")
    if uniform:  # one θ, as drawn (float64) when the clip knows it
        threshold = clip.base_threshold if clip.base_threshold is not None else float(clip.threshold.flatten()[0])
    else:
        threshold = clip.threshold[y0:y1, x0:x1]
    shape = (len(clip.window_end_us), 2 * NUM_BINS, *clip.threshold.shape)

    def full_frame(crop: "torch.Tensor") -> "torch.Tensor":
        hist = torch.zeros(shape, dtype=crop.dtype, device=crop.device)
        hist[..., y0:y1, x0:x1] = crop
        return torch.clamp(clip.add_noise(hist), max=float(COUNT_CUTOFF))

    def counts(log: "torch.Tensor", theta) -> "torch.Tensor":
        return log_histograms(log, clip.t_us, clip.window_end_us, mode=mode, binning=binning,
                              window_us=clip.window_us, count_cutoff=None, threshold_on=theta, threshold_off=theta)

    if mode == "official_relaxed":  # not counts: the relaxed value carries its own gradient
        return full_frame(counts(log_video, threshold))
    with torch.no_grad():  # the exact simulator's precision
        theta64 = threshold if uniform else threshold.double()
        exact = counts(log_intensity(video.detach().double()), theta64).to(log_video.dtype)
    if gradient == "ste":
        ste = counts(log_video, threshold)
        return full_frame(exact + (ste - ste.detach()))  # the value of the float64 counts, the floor's gradient
    theta = float(clip.threshold.mean())
    surrogate = log_histograms(log_video, clip.t_us, clip.window_end_us, mode="official_relaxed", binning=binning,
                               window_us=clip.window_us, count_cutoff=None, threshold_on=theta,
                               threshold_off=theta) / OFFICIAL_RELAXED_SCALE
    with torch.no_grad():
        hist = full_frame(exact)
    # the value stays the exact counts bit for bit (surrogate - surrogate == 0); the gradient is the surrogate's
    hist[..., y0:y1, x0:x1] += surrogate - surrogate.detach()
    return hist


def attack_loss(grid: "torch.Tensor", clips: Sequence[PoolClip], detector, config: AttackConfig) -> AdversarialLoss:
    """``L_adv`` of a texture grid over a batch of clips (over all windows and clips; ``config.loss_reduction``).

    Args:
        grid: float tensor [n, n] (after :func:`binarize_ste`).
        clips: pool clips of this rank (same number of windows).
        detector: frozen RVT detector in eval mode.
        config: the attack settings.

    Returns:
        :class:`~davis_rig.attack.loss.AdversarialLoss` (``total`` differentiable w.r.t. ``grid``).
    """
    from davis_rig.models.rvt.detector import pad_to_input

    device = next(detector.parameters()).device
    x = torch.stack([clip_histograms(grid, c, config.v2e_mode, config.v2e_binning, config.v2e_gradient)
                     for c in clips], dim=1)
    x = x.to(device)
    decoded, states = [], None
    amp = config.precision == "bf16"
    with torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=amp):
        for w in range(x.shape[0]):
            out, states = detector(pad_to_input(x[w], detector.config.in_res_hw), states)
            decoded.append(out.float())
    boxes = torch.as_tensor(np.stack([c.boxes for c in clips], axis=1), device=device)  # [W, B, 4]
    on_person = None
    if config.loss_anchors == "person":
        cells = anchor_cells(detector.config.in_res_hw, detector.config.head_strides, device=device)
        on_person = anchors_on_boxes(cells, boxes)  # [W, B, A]
    return adversarial_loss(decoded, config.lambda_obj, config.lambda_cls,
                            boxes=boxes if config.box_margin_px is not None else None,
                            box_margin_px=config.box_margin_px or 0.0, reduction=config.loss_reduction,
                            anchor_mask=on_person)


def _step_seed(seed: int, step: int, stream: int = 0xA77AC) -> int:
    """The 63-bit torch seed of a step's dropout (``stream`` 0xA77AC) or binarization cuts (0xB1A5)."""
    state = np.random.SeedSequence([int(stream), int(seed), int(step)]).generate_state(1, dtype=np.uint64)
    return int(state[0] >> np.uint64(1))


def binarization_threshold(binarize: str, seed: int, step: int, like: "torch.Tensor") -> "float | torch.Tensor":
    """The cut of a step's binarization (:func:`~davis_rig.attack.texture.binarize_ste`'s ``threshold``).

    Args:
        binarize: ``"threshold"`` (the paper's 0.5) or ``"sample"`` (uniform per-cell cuts seeded by
            ``(seed, step)``: the same on every rank, a new draw every step, independent of the dropout's).
        seed: the run's seed.
        step: the step (0-based).
        like: the soft grid [n, n] (shape and device of the cuts).

    Returns:
        0.5, or a float32 tensor shaped like ``like``.
    """
    if binarize == "threshold":
        return 0.5
    if binarize != "sample":
        raise ValueError(f"unknown binarize {binarize!r}; expected 'threshold' or 'sample'")
    return sampled_thresholds(tuple(like.shape), _step_seed(seed, step, 0xB1A5), like.device)


def soft_grid(generator: TextureGenerator, seed: int, step: int) -> "torch.Tensor":
    """The generator's soft texture with its dropout seeded by ``(seed, step)`` (global RNG state left untouched).

    Args:
        generator: the texture generator (train mode: dropout active).
        seed: the run's seed.
        step: the step (0-based).

    Returns:
        float tensor [n, n] in [0, 1], differentiable w.r.t. the generator's parameters.
    """
    device = next(generator.parameters()).device
    devices = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(_step_seed(seed, step))
        return generator()
